"""Every figure/table rule on the tiny test study (one snakemake run per module), the report."""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib.image as mpimg
import pandas as pd
import pytest
import yaml
from helpers.paths import ROOT
from helpers.workflow import run_snakemake

pytestmark = pytest.mark.slow
FIGURES = ("pvalues", "longitudinal", "histograms", "sample_sizes", "propensity")
HAS_SWEEP = (ROOT / "src" / "twinfalsify" / "inference" / "sensitivity.py").exists()




@pytest.fixture(scope="module")
def study(test_study):
    work, config = test_study
    cfg = yaml.safe_load(config.read_text())
    return work, config, cfg, work / "results" / cfg["study"]


def _image_ok(path: Path) -> None:
    assert path.stat().st_size > 10_000, path
    if path.suffix == ".png":
        img = mpimg.imread(path)
        assert img.shape[0] > 300 and img.shape[1] > 300 and img[..., :3].std() > 0.02, path
    else:
        assert path.read_bytes()[:5] == b"%PDF-", path


def test_every_figure_rule_gives_a_nonempty_image(study):
    _, _, cfg, r = study
    names = FIGURES + (("sensitivity",) if HAS_SWEEP else ())
    for twin in cfg["twins"]:
        for name in names:
            for ext in ("png", "pdf"):
                _image_ok(r / "twins" / twin / "figures" / f"{name}.{ext}")
    for ext in ("png", "pdf"):  # synthetic source: the confounding illustration
        _image_ok(r / "figures" / f"confounding.{ext}")


@pytest.mark.skipif(not HAS_SWEEP, reason="no sensitivity sweep in this version")
def test_sensitivity_rule_logs_its_progress_and_is_benchmarked(study):
    _, _, cfg, r = study
    deltas = (cfg.get("figures", {}).get("sensitivity", {}).get("deltas")
              or [0.0, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2])  # fmt: skip
    for twin in cfg["twins"]:
        lines = (r / "logs" / "twins" / twin / "figure_sensitivity.log").read_text().splitlines()
        steps = [ln for ln in lines if "Delta = " in ln]
        methods = {ln.split(": Delta")[0].split()[-1] for ln in steps}
        assert methods == set(cfg["testing"]["methods"]), lines[-5:]
        assert len(steps) == len(deltas) * len(methods), lines[-5:]
        assert any("sensitivity sweep done in" in ln for ln in lines)
        bench = r / "benchmarks" / "twins" / twin / "figure_sensitivity.tsv"
        assert bench.is_file() and bench.read_text().startswith("s\t")


def test_tables_match_the_results_they_summarise(study):
    _, _, cfg, r = study
    for twin in cfg["twins"]:
        res = pd.read_parquet(r / "twins" / twin / "results.parquet")
        tex = (r / "twins" / twin / "tables" / "rejections.tex").read_text()
        for method, part in res.groupby("method"):
            c, m = part[part["kind"] == "causal"], part[part["kind"] == "manski"]
            want = (f"Total & {c['rejected'].sum()} / {len(c)} & "
                    f"{m['rejected'].sum()} / {len(m)} \\\\")  # fmt: skip
            assert want in tex, (method, want)
        # longitudinal numbers at the last hour are the results row of the shown hypothesis
        lon = pd.read_csv(r / "twins" / twin / "figures" / "longitudinal.csv")
        row = res[res["hyp_id"] == lon["source_hyp_id"].iloc[0]].iloc[0]
        last = lon.iloc[-1]
        assert (int(last["n"]), int(last["nhat"])) == (row["n"], row["nhat"])
        assert last["q_twin_hat"] == pytest.approx(row["q_twin_hat"])
        assert last["q_lo_hat"] == pytest.approx(row["q_lo_hat"])
    space = pd.read_csv(r / "tables" / "action_space.csv")
    grid = pd.read_csv(r / "tables" / "action_space_grid.csv")
    counts = [int(m) for cell in grid.iloc[:, 1:].to_numpy().ravel()
              for m in re.findall(r"\((\d+)\)$", cell)]  # fmt: skip
    assert sorted(counts) == sorted(space["n_hours"].tolist())
    md = (r / "summary.md").read_text()
    # every twin's outputs at the bounds, per outcome
    assert "## Outputs at the bounds" in md and "twin_at_y_lo" in md
    for twin in cfg["twins"]:
        res = pd.read_parquet(r / "twins" / twin / "results.parquet")
        for (method, kind), part in res.groupby(["method", "kind"]):
            line = f"| {twin} | {method} | {kind} | {len(part)} | {part['rejected'].sum()} |"
            assert line in md


def test_editing_a_plotting_script_reruns_only_that_figure(study):
    work, config, cfg, _ = study
    run = run_snakemake(
        work, config, "--cores", "1", "--dry-run", "--forcerun", "figure_propensity"
    )
    assert run.returncode == 0, run.stderr[-2000:]
    jobs = [j for j in re.findall(r"^rule (\w+):", run.stdout, re.M) if j != "all"]
    assert set(jobs) == {"figure_propensity"} and len(jobs) == len(cfg["twins"])


def test_report_includes_every_figure_with_captions(study):
    work, config, cfg, r = study
    out = work / "report.zip"
    run = run_snakemake(work, config, "--report", str(out))
    assert run.returncode == 0, run.stderr[-3000:]
    import zipfile

    zf = zipfile.ZipFile(out)
    html = next(zf.read(n).decode() for n in zf.namelist() if n.endswith("report.html"))
    study_dir = f"results/{cfg['study']}"
    for twin in cfg["twins"]:  # every figure is an entry, with its caption
        for name in FIGURES:
            assert f"{study_dir}/twins/{twin}/figures/{name}.png" in html, (twin, name)
    for phrase in ("One hypothesis followed over time", "Raw outcome values behind",
                   "How much data each hypothesis", "Why some hypotheses cannot be rejected",
                   "Study summary", "brake-pad"):  # fmt: skip
        assert phrase in html, phrase
    assert f"{study_dir}/summary.html" in html and f"{study_dir}/figures/confounding.png" in html
    # job parameters read as written, not as escaped JSON (a config section is a params dict)
    shown = re.findall(r'"params": "(.*?)"}', html)
    assert any("'alpha': 0.05" in p for p in shown), shown[:3]
    assert not any("\\" in p for p in shown), [p for p in shown if "\\" in p][:3]
    assert sum(n.endswith(".png") for n in zf.namelist()) >= len(FIGURES) * len(cfg["twins"]) + 1
    # the introduction: documentation pages by name (no file paths a report reader cannot
    # open), the correction's families, what the `code` parameter is, the Software table
    intro = re.sub(r"<[^>]+>", "", re.search(r'var workflow_desc = "(.*?)";\n', html,
                                             re.S).group(1))  # fmt: skip
    assert "docs/" not in intro and ".md" not in intro
    assert "Statistics page of the documentation" in intro
    assert "one test method and one bound kind" in intro
    assert "fingerprint of the code the job ran" in intro and "Software" in intro
