#!/usr/bin/env bash
# Build the Pulse Physiology Engine 4.2 with its Python API, outside the repository.
#
#   envs/pulse/build.sh SRC_DIR PREFIX
#
# SRC_DIR  a Pulse 4.2 source checkout, or a bare git repository (its PULSE_REF, default HEAD,
#          is extracted blob by blob into PREFIX/src; blobs missing from the snapshot are skipped)
# PREFIX   work and install directory: PREFIX/{src,venv,build,install,datagen,logs}
#
# Steps (each one is skipped when its stamp PREFIX/.stamps/<step> exists; delete the stamp to
# redo it and, if needed, the later ones): source, venv, configure, compile, python, data.
# The package check and the smoke check run every time. Progress and
# timings go to stderr (timings also to PREFIX/logs/timings.tsv, command output to
# PREFIX/logs/<step>.log); stdout gets only the two `export` lines to use the engine, so
#   eval "$(envs/pulse/build.sh SRC_DIR PREFIX)"
# works. Environment: PYTHON (default python3), PULSE_REF (HEAD), PULSE_JOBS (2), PULSE_NICE (10).
# See envs/pulse/README.md for what every step does and why.
set -euo pipefail

usage() { echo "usage: $0 SRC_DIR PREFIX   (SRC_DIR: Pulse 4.2 checkout or bare git repo)" >&2; exit 2; }
[[ $# -eq 2 ]] || usage

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
SRC_IN=$(realpath "$1")
PREFIX=$(realpath -m "$2")
PYTHON=${PYTHON:-python3}
PULSE_REF=${PULSE_REF:-HEAD}
JOBS=${PULSE_JOBS:-2}
NICE=${PULSE_NICE:-10}

VENV=$PREFIX/venv
BUILD=$PREFIX/build
INSTALL=$PREFIX/install
LOGS=$PREFIX/logs
STAMPS=$PREFIX/.stamps
mkdir -p "$PREFIX" "$LOGS" "$STAMPS"

log() { printf '[pulse-build %(%H:%M:%S)T] %s\n' -1 "$*" >&2; }
die() { log "ERROR: $*"; exit 1; }
hms() { printf '%dm%02ds' $(($1 / 60)) $(($1 % 60)); }

# run_step NAME DESCRIPTION FUNCTION [always]: run FUNCTION (timed) unless NAME is stamped done;
# with "always" it runs every time and leaves no stamp (the package check and the smoke check).
run_step() {
    local name=$1 desc=$2 fn=$3 always=${4:-} t0 dt
    if [[ -z $always && -e $STAMPS/$name ]]; then
        log "step $name: already done ($(cat "$STAMPS/$name")), skipped"
        return 0
    fi
    log "step $name: $desc ..."
    t0=$SECONDS
    "$fn"
    dt=$((SECONDS - t0))
    [[ -n $always ]] || printf '%s took %ss\n' "$(date -Is)" "$dt" >"$STAMPS/$name"
    printf '%s\t%s\t%s\n' "$(date -Is)" "$name" "$dt" >>"$LOGS/timings.tsv"
    log "step $name: done in $(hms "$dt")"
}

# ------------------------------------------------------------------------------ packages
# Checked on every run (not stamped). Installs with apt-get only when run as root.
step_packages() {
    local want=(cmake g++ libeigen3-dev libprotobuf-dev protobuf-compiler python3-dev python3-venv
                libprotobuf-java) missing=() p
    command -v javac >/dev/null || want+=(default-jdk-headless)
    for p in "${want[@]}"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' \
            || missing+=("$p")
    done
    if [[ ${#missing[@]} -eq 0 ]]; then
        log "step packages: all present"
        return 0
    fi
    [[ $(id -u) -eq 0 ]] || die "missing Debian packages (run as root or install them): ${missing[*]}"
    log "step packages: apt-get install ${missing[*]}"
    { apt-get update && DEBIAN_FRONTEND=noninteractive \
        apt-get install -y --no-install-recommends "${missing[@]}"; } >"$LOGS/packages.log" 2>&1 \
        || die "apt-get failed, see $LOGS/packages.log"
}

# ------------------------------------------------------------------------------ source
# A bare repository cannot be `git archive`d when blobs are missing (the public snapshot lacks
# 4: a POI jar and 3 csv files): write every blob that exists, list the missing ones.
step_source() {
    rm -rf "$PREFIX/src.partial"
    git -C "$SRC_IN" rev-parse --verify "$PULSE_REF^{commit}" >"$LOGS/source-commit"
    "$PYTHON" - "$SRC_IN" "$PULSE_REF" "$PREFIX/src.partial" >"$LOGS/missing-blobs.txt" <<'PY'
import os, subprocess, sys
repo, ref, dest = sys.argv[1:4]
env = dict(os.environ, GIT_NO_LAZY_FETCH="1")  # never try to fetch a missing object
tree = subprocess.run(["git", "-C", repo, "ls-tree", "-r", "-z", ref],
                      check=True, capture_output=True, env=env).stdout
cat = subprocess.Popen(["git", "-C", repo, "cat-file", "--batch"], env=env,
                       stdin=subprocess.PIPE, stdout=subprocess.PIPE)
for rec in filter(None, tree.split(b"\0")):
    meta, path = rec.split(b"\t", 1)
    mode, kind, sha = meta.decode().split()
    if kind != "blob":  # submodule entries
        continue
    cat.stdin.write(sha.encode() + b"\n"); cat.stdin.flush()
    head = cat.stdout.readline().split()
    if head[-1] == b"missing":
        print(path.decode())
        continue
    data = cat.stdout.read(int(head[2])); cat.stdout.read(1)
    out = os.path.join(dest, os.fsdecode(path))
    os.makedirs(os.path.dirname(out), exist_ok=True)
    if mode == "120000":
        os.symlink(os.fsdecode(data), out)
    else:
        with open(out, "wb") as f:
            f.write(data)
        if mode == "100755":
            os.chmod(out, 0o755)
cat.stdin.close(); cat.wait()
PY
    for f in CMakeLists.txt src/cpp/CMakeLists.txt src/python/pulse/engine/PulseEngine.py \
             data/Data.xlsx; do
        [[ -f $PREFIX/src.partial/$f ]] || die "extracted source lacks $f"
    done
    rm -rf "$PREFIX/src"
    mv "$PREFIX/src.partial" "$PREFIX/src"
    log "step source: commit $(cut -c1-12 "$LOGS/source-commit"): $(find "$PREFIX/src" -type f | wc -l) files," \
        "$(wc -l <"$LOGS/missing-blobs.txt") missing blob(s) skipped (listed in $LOGS/missing-blobs.txt)"
}

# ------------------------------------------------------------------------------ venv
# pybind11 >= 2.12 is required with numpy 2 (2.11 builds return wrong pull_data() values).
step_venv() {
    rm -rf "$VENV"
    "$PYTHON" -m venv "$VENV"
    "$VENV/bin/python" -m pip install --disable-pip-version-check -q \
        pybind11==2.13.6 numpy protobuf==4.21.12 pandas openpyxl >"$LOGS/venv.log" 2>&1 \
        || die "pip install failed, see $LOGS/venv.log"
    log "step venv: $("$VENV/bin/python" -c 'import sys, numpy, pybind11, google.protobuf as p
print(f"python {sys.version.split()[0]}, numpy {numpy.__version__}, pybind11 {pybind11.__version__}, protobuf {p.__version__}")')"
}

# ------------------------------------------------------------------------------ configure
# No superbuild (Debian's protobuf 3.21 and eigen 3.4). protobuf_SRC is demanded anyway and its
# python/build/lib/google is copied into the bindings: an empty dummy tree satisfies it (the
# venv's protobuf is used). The unity build exclusions are injected, Pulse's tree is not edited.
step_configure() {
    mkdir -p "$PREFIX/protobuf_src_dummy/python/build/lib/google" "$PREFIX/cmake"
    cp "$HERE/unity-exclusions.cmake" "$PREFIX/cmake/unity-exclusions.cmake"
    rm -rf "$BUILD"
    cmake -S "$SRC" -B "$BUILD" \
        -DPulse_SUPERBUILD=OFF -DPulse_JAVA_API=OFF -DPulse_PYTHON_API=ON \
        -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$INSTALL" \
        -Dprotobuf_SRC="$PREFIX/protobuf_src_dummy" \
        -Dpybind11_DIR="$("$VENV/bin/python" -m pybind11 --cmakedir)" \
        -DPython3_EXECUTABLE="$VENV/bin/python" -DPYTHON_EXECUTABLE="$VENV/bin/python" \
        -DCMAKE_UNITY_BUILD=ON -DCMAKE_UNITY_BUILD_BATCH_SIZE=16 \
        -DCMAKE_PROJECT_INCLUDE="$PREFIX/cmake/unity-exclusions.cmake" \
        >"$LOGS/configure.log" 2>&1 || die "cmake configure failed, see $LOGS/configure.log"
    grep -h 'twinfalsify:' "$LOGS/configure.log" | sed 's/^-- //' | while read -r l; do log "step configure: $l"; done
}

# ------------------------------------------------------------------------------ compile
# Only the PyPulse target (make install would build every engine, driver and test). Its
# POST_BUILD copies PyPulse.*.so into PREFIX/install/bin. make resumes an interrupted build.
step_compile() {
    log "step compile: nice -n $NICE make -j$JOBS PyPulse (log: $LOGS/compile.log; 8-16 min on 2 cores, more when they are busy)"
    nice -n "$NICE" make -C "$BUILD" -j"$JOBS" PyPulse >"$LOGS/compile.log" 2>&1 \
        || { tail -n 30 "$LOGS/compile.log" >&2; die "make PyPulse failed, see $LOGS/compile.log"; }
    compgen -G "$INSTALL/bin/PyPulse*.so" >/dev/null || die "no PyPulse*.so in $INSTALL/bin after make"
}

# ------------------------------------------------------------------------------ python
# Manual install of the python package (make install would build every target): Pulse's pure
# python sources plus the generated *_pb2.py bindings from the build tree.
step_python() {
    rm -rf "$INSTALL/python/pulse"
    mkdir -p "$INSTALL/python"
    cp -r "$SRC/src/python/pulse" "$INSTALL/python/"
    cp -r "$BUILD/src/python/pulse/." "$INSTALL/python/pulse/"
    [[ -f $INSTALL/python/pulse/cdm/bind/Patient_pb2.py ]] || die "no generated Patient_pb2.py in $INSTALL/python"
}

# ------------------------------------------------------------------------------ data
# Pulse's engine data (substances, compounds, patients, environments, nutrition, ecg, config) is
# generated from data/Data.xlsx by Pulse's Java DataSetReader (Apache POI). The POI OOXML jar is
# missing from the public snapshot and UnitConverter needs the native PulseJNI (not built): our
# own stand-ins replace both (envs/pulse/datagen/poi-standins/ and jni-standins/, see
# datagen/README.md); javac takes them first on the source path.
step_data() {
    local dg=$PREFIX/datagen cp n d
    local standins=$HERE/datagen:$HERE/datagen/poi-standins:$HERE/datagen/jni-standins
    rm -rf "$dg"
    mkdir -p "$dg/bind" "$dg/classes" "$dg/out"
    find "$SRC/src/schema" -name '*.proto' -print0 \
        | xargs -0 protoc --proto_path="$SRC/src/schema" --java_out="$dg/bind" >"$LOGS/data.log" 2>&1 \
        || die "protoc --java_out failed, see $LOGS/data.log"
    cp=$(find "$SRC/src/java/jar" -name '*.jar' ! -name 'poi*' | sort | tr '\n' ':')
    cp+=/usr/share/java/protobuf.jar:/usr/share/java/protobuf-util.jar
    javac -nowarn -encoding UTF-8 -d "$dg/classes" -cp "$cp" \
        -sourcepath "$standins:$SRC/src/java:$dg/bind" "$HERE/datagen/GenData.java" \
        >>"$LOGS/data.log" 2>&1 || die "javac failed, see $LOGS/data.log"
    (cd "$dg/out" && java -cp "$dg/classes:$cp" GenData "$SRC/data/Data.xlsx") >>"$LOGS/data.log" 2>&1 \
        || die "data generation failed, see $LOGS/data.log"
    if grep -E '^\[(ERROR|FATAL)\]|Exception' "$LOGS/data.log" >&2; then
        die "data generation reported errors, see $LOGS/data.log"
    fi
    local summary=""
    for d in config ecg environments nutrition patients substances substances/compounds; do
        n=$(find "$dg/out/$d" -maxdepth 1 -name '*.json' | wc -l)
        [[ $n -gt 0 ]] || die "data generation wrote no $d/*.json"
        summary+=" $d=$n"
    done
    for f in substances/compounds/Saline.json substances/Norepinephrine.json nutrition/Standard.json; do
        [[ -f $dg/out/$f ]] || die "data generation wrote no $f"
    done
    log "step data:$summary"
    mkdir -p "$INSTALL/bin"
    cp -r "$dg/out/." "$INSTALL/bin/"
}

# ------------------------------------------------------------------------------ smoke
# Runs on every invocation (not stamped). Initialises an engine for one patient (data root =
# PREFIX/install/bin, run from another directory) and advances 60 s. The stabilised values are
# compared with the recorded real-engine run of this patient (tests/fixtures/pulse-reference P1,
# Pulse 4.2.0 @ 9af9d8f6, pybind11 2.13.6, numpy 2): equal to 6 digits there; a difference
# above 0.1 % fails, a smaller one warns.
step_smoke() {
    mkdir -p "$PREFIX/smoke"
    (cd "$PREFIX/smoke" && PYTHONPATH="$INSTALL/bin:$INSTALL/python" \
        "$VENV/bin/python" - "$INSTALL/bin" "$PREFIX/smoke/smoke-engine.log") \
        >"$LOGS/smoke.log" 2>&1 <<'PY' || { cat "$LOGS/smoke.log" >&2; die "smoke check failed, see $LOGS/smoke.log"; }
import sys, time
from pulse.engine.PulseEngine import PulseEngine, version
from pulse.cdm.engine import SEDataRequest, SEDataRequestManager
from pulse.cdm.patient import SEPatientConfiguration, eSex
from pulse.cdm.scalars import (FrequencyUnit, LengthUnit, MassUnit, PressureUnit, SEScalarUnit,
                               TimeUnit)
data_root, engine_log = sys.argv[1], sys.argv[2]
mmol_L = SEScalarUnit("mmol/L")  # Pulse's python cdm has no amount-per-volume unit class
R = SEDataRequest
requests = {
    "MAP_mmHg": R.create_physiology_request("MeanArterialPressure", PressureUnit.mmHg),
    "HR_per_min": R.create_physiology_request("HeartRate", FrequencyUnit.Per_min),
    "Na_mmol_L": R.create_liquid_compartment_substance_request("Aorta", "Sodium", "Molarity", mmol_L),
    "Cl_mmol_L": R.create_liquid_compartment_substance_request("Aorta", "Chloride", "Molarity", mmol_L),
    "K_mmol_L": R.create_liquid_compartment_substance_request("Aorta", "Potassium", "Molarity", mmol_L),
    "pH": R.create_physiology_request("BloodPH"),
}
expected = {"MAP_mmHg": 95.6575, "HR_per_min": 95.0, "Na_mmol_L": 143.651}  # recorded P1, hour 0

pc = SEPatientConfiguration()
p = pc.get_patient()
p.set_name("smoke")
p.set_sex(eSex.Male)
p.get_age().set_value(50, TimeUnit.yr)
p.get_weight().set_value(80, MassUnit.kg)
p.get_height().set_value(178, LengthUnit.cm)
p.get_heart_rate_baseline().set_value(95, FrequencyUnit.Per_min)
p.get_systolic_arterial_pressure_baseline().set_value(115, PressureUnit.mmHg)
p.get_diastolic_arterial_pressure_baseline().set_value(75, PressureUnit.mmHg)
p.get_respiration_rate_baseline().set_value(18, FrequencyUnit.Per_min)
pc.set_data_root_dir(data_root)

engine = PulseEngine(data_root_dir=data_root)
engine.set_log_filename(engine_log)
engine.log_to_console(False)
print(f"Pulse {version()}, data root {data_root}")
t0 = time.time()
ok = engine.initialize_engine(pc, SEDataRequestManager(list(requests.values())))
print(f"initialize_engine: {ok} ({time.time() - t0:.1f} s wall)")
if not ok:
    sys.exit("initialize_engine returned False (see the engine log)")

def values():
    v = engine.pull_data()
    if len(v) != len(requests) + 1:
        sys.exit(f"pull_data() returned {len(v)} values for {len(requests)} requests + time")
    return dict(zip(requests, map(float, v[1:])))

stable = values()
print("stabilised: " + ", ".join(f"{k} {v:.6g}" for k, v in stable.items()))
bad = []
for k, want in expected.items():
    got = stable[k]
    if f"{got:.6g}" != f"{want:.6g}":
        print(f"WARNING: {k} = {got:.6g}, recorded {want:.6g}")
        if abs(got - want) > 1e-3 * abs(want):
            bad.append(f"{k} {got:.6g} != {want:.6g}")
print("recorded values (MAP 95.6575, HR 95, Na 143.651): " + ("MISMATCH " + "; ".join(bad) if bad else "match"))
t0 = time.time()
ok = engine.advance_time_s(60)
after = values()
print(f"advance_time_s(60): {ok} ({time.time() - t0:.1f} s wall); "
      + ", ".join(f"{k} {v:.6g}" for k, v in after.items()))
sys.exit(1 if bad or not ok else 0)
PY
    while read -r l; do log "step smoke: $l"; done <"$LOGS/smoke.log"
}

# ------------------------------------------------------------------------------ main
if [[ -f $SRC_IN/CMakeLists.txt && -d $SRC_IN/src/cpp ]]; then
    SRC=$SRC_IN                      # a checkout: used in place, never written to
elif [[ $(git -C "$SRC_IN" rev-parse --is-bare-repository 2>/dev/null || true) == true ]]; then
    SRC=$PREFIX/src
else
    die "$SRC_IN is neither a Pulse source checkout nor a bare git repository"
fi
log "Pulse source: $SRC_IN -> $SRC; prefix: $PREFIX"
T_ALL=$SECONDS

run_step packages "Debian packages" step_packages always
if [[ $SRC == "$PREFIX/src" ]]; then
    run_step source "extract $PULSE_REF of $SRC_IN into $SRC" step_source
fi
run_step venv "python venv $VENV" step_venv
run_step configure "cmake configure in $BUILD" step_configure
run_step compile "compile PyPulse" step_compile
run_step python "install the python package into $INSTALL/python" step_python
run_step data "generate the engine data files into $INSTALL/bin" step_data
run_step smoke "smoke check: one patient, stabilise, advance 60 s" step_smoke always

log "all steps done in $(hms $((SECONDS - T_ALL))) (this run)"
echo "export PYTHONPATH=$INSTALL/bin:$INSTALL/python"
echo "export PULSE_DATA_ROOT=$INSTALL/bin"
