"""Rule figure_longitudinal: bounds, twin and naive means over t for one hypothesis."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import json  # noqa: E402

from twinfalsify.figures import longitudinal, save_all  # noqa: E402
from twinfalsify.io import log, run_rule, write_csv  # noqa: E402
from twinfalsify.summary import load_study_twin, longitudinal_frame, pick_hypothesis  # noqa: E402


def main(sm):
    st = load_study_twin(dict(sm.input.items()))
    opts = json.loads(sm.params.figures).get("longitudinal") or {}
    testing = json.loads(sm.params.testing)
    hyp_id = opts.get("hyp_id")
    if hyp_id is None:
        hyp_id = pick_hypothesis(st.results, rejected=True, outcome=opts.get("outcome"))
    frame = longitudinal_frame(
        st, int(hyp_id), alpha=float(testing.get("alpha", 0.05)),
        quantiles=tuple(json.loads(sm.params.quantiles)),
    )  # fmt: skip
    rej = st.results.loc[st.results["hyp_id"] == int(hyp_id), "rejected"].any()
    log.info("hypothesis %s (%s)", hyp_id, "rejected" if rej else "not rejected")
    write_csv(frame, sm.output.csv)
    last = frame.iloc[-1]
    title = (
        f"twin {sm.wildcards.twin}: {last['outcome']}, a = "
        f"{'-'.join(map(str, last['actions']))}, B = {'-'.join(map(str, last['bins']))} "
        f"({'rejected' if rej else 'not rejected'} at t = {int(last['t'])})"
    )
    save_all(longitudinal(frame, title=title), sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
