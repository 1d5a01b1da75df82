"""A command twin that writes into what its code fingerprint reads (a log inside its
``code:`` folder, a file named on its command line) does not rerun at every start.

The jobs that run the twin record the tracked files it changed
(``runs.command.watch_code``); the next start names such a file and ``code_exclude`` in one
line (``runs.command.code_written_error``) instead of planning the twin's jobs again; with
the file listed under ``code_exclude`` a finished study has nothing to do.
"""

from __future__ import annotations

import shutil

import pytest
import yaml
from fakes import FAULTY_TWIN
from helpers.paths import ROOT
from helpers.workflow import copy_study, run_snakemake


def test_a_write_through_a_symlinked_code_folder_is_named_and_excludable(tmp_path,
                                                                      monkeypatch):
    """``code: [link/]`` with link -> twin/: a file the twin writes under twin/cache/ is
    recorded, named at the next start, and ``code_exclude`` by either name leaves it out."""
    from twinfalsify.runs.command import code_written_error, command_fingerprint, watch_code

    monkeypatch.chdir(tmp_path)
    (tmp_path / "twin" / "cache").mkdir(parents=True)
    (tmp_path / "twin" / "main.py").write_text("print('twin')\n")
    (tmp_path / "link").symlink_to(tmp_path / "twin", target_is_directory=True)
    spec = {"kind": "command", "command": "python twin/main.py", "code": ["link/"]}
    folder = tmp_path / "results" / "s" / "twins" / "t"
    before = command_fingerprint(spec)
    with watch_code(spec, None, folder / "code_written" / "shard_0.json"):
        (tmp_path / "twin" / "cache" / "state.bin").write_bytes(b"x")
    assert command_fingerprint(spec) != before  # what would rerun it at every start
    problem = code_written_error("t", spec, folder)
    assert problem is not None and "'link/cache/state.bin'" in problem
    assert "twins.t.code_exclude" in problem
    for exclude in (["link/cache/"], ["twin/cache"]):
        fixed = {**spec, "code_exclude": exclude}
        assert code_written_error("t", fixed, folder) is None
        assert command_fingerprint(fixed) == before


def _config(tmp_path, excludes: dict[str, list[str]]):
    cfg = yaml.safe_load((ROOT / "config" / "test.yaml").read_text())
    cfg["twin_runs"].update(runs_per_sequence=20, n_shards=2)
    cfg["twins"] = {
        # a log inside its code folder, named on its command line too
        "inside": {"kind": "command", "code": ["twin/"], "workers": 1,
                   "command": "python twin/faulty_twin.py --log-requests "
                              "twin/state/requests.log"},
        # a file named on its command line, created by the twin's first run
        "named": {"kind": "command", "workers": 1,
                  "command": "python twin/faulty_twin.py --log-requests named.log"},
    }
    for twin, paths in excludes.items():
        cfg["twins"][twin]["code_exclude"] = paths
    config = tmp_path / "self.yaml"
    config.write_text(yaml.safe_dump(cfg))
    return config


@pytest.mark.slow
def test_a_twin_writing_its_own_files_is_named_then_finished_studies_stay_finished(
        tmp_path, test_study):
    """Two command twins writing into their fingerprint, on a copy of the shared
    config/test.yaml study (``test_study``: every step before the twin plan is the
    same), so only the twin stage runs."""
    work = copy_study(test_study[0], tmp_path / "study")
    (work / "twin" / "state").mkdir(parents=True)
    shutil.copy(FAULTY_TWIN[1], work / "twin" / "faulty_twin.py")
    targets = [f"results/test/twins/{t}/runs.parquet" for t in ("inside", "named")]
    config = _config(work, {})
    done = run_snakemake(work, config, "--cores", "2", *targets)
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    assert (work / "named.log").is_file()

    # the next start: one line naming the file and the key, no job planned
    again = run_snakemake(work, config, "--cores", "2", "-n", *targets)
    out = again.stdout + again.stderr
    assert again.returncode != 0
    line = next(ln for ln in out.splitlines() if ln.startswith("invalid config:"))
    assert line.startswith("invalid config: twins.inside: the twin wrote "
                           "'twin/state/requests.log' while it ran"), line
    assert "twins.inside.code_exclude" in line
    config = _config(work, {"inside": ["twin/state/"]})
    again = run_snakemake(work, config, "--cores", "2", "-n", *targets)
    line = next(ln for ln in (again.stdout + again.stderr).splitlines()
                if ln.startswith("invalid config:"))
    assert line.startswith("invalid config: twins.named: the twin wrote 'named.log'"), line

    # both excluded: the twins rerun once (their spec changed), then nothing to do
    config = _config(work, {"inside": ["twin/state/"], "named": ["named.log"]})
    done = run_snakemake(work, config, "--cores", "2", *targets)
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    for _ in range(2):
        again = run_snakemake(work, config, "--cores", "2", "-n", *targets)
        out = again.stdout + again.stderr
        assert again.returncode == 0, out[-3000:]
        assert "Nothing to be done" in out, out[-3000:]
