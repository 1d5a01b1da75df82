"""Every study config the project ships is valid as a user would run it: a whole config on
its own, an overlay (first line ``# Overlay for config/<base>.yaml``) merged onto its base the
way Snakemake merges ``--configfile base overlay``."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from helpers.paths import ROOT
from snakemake.utils import update_config

from twinfalsify.studyconfig import study_config_error

SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
# not study configs: the calibration harness's own settings (read by its rules as a file)
NOT_STUDIES = {"calibration.yaml"}
CONFIGS = sorted(p for p in (ROOT / "config").glob("*.yaml") if p.name not in NOT_STUDIES)


def _as_run(path: Path) -> dict:
    cfg = yaml.safe_load(path.read_text())
    first = path.read_text().splitlines()[0]
    if not first.startswith("# Overlay for config/"):
        return cfg
    base_name = first.removeprefix("# Overlay for config/").split(":")[0]
    assert f"config/{base_name} config/{path.name}" in path.read_text(), (
        f"{path.name}: the overlay's command must give its base first, then the overlay")
    base = yaml.safe_load((ROOT / "config" / base_name).read_text())
    update_config(base, cfg)
    return base


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_config_is_valid(path):
    assert study_config_error(_as_run(path), SCHEMA) is None


def test_overlays_are_found():
    overlays = [p.name for p in CONFIGS
                if p.read_text().startswith("# Overlay for config/")]
    assert {"mimic4.yaml", "paper-scale-adaptive.yaml", "paper-scale-2x.yaml"} <= set(overlays)
    assert _as_run(ROOT / "config" / "mimic4.yaml")["source"]["kind"] == "mimic4"
