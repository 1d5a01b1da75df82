"""Rule figure_longitudinal: bounds, twin and naive means over t for one hypothesis."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

import json  # noqa: E402

from twinfalsify.figures import longitudinal, save_all  # noqa: E402
from twinfalsify.io import log, run_rule, write_csv  # noqa: E402
from twinfalsify.summary import (  # noqa: E402
    extend_to_horizon,
    load_study_twin,
    longitudinal_frame,
    pick_hypothesis,
)


def _key(outcome, kind, t, actions, bins) -> str:
    return f"{outcome}|{kind}|{int(t)}|{list(map(int, actions))}|{list(map(int, bins))}"


def main(sm):
    st = load_study_twin(dict(sm.input.items()))
    opts = json.loads(sm.params.figures).get("longitudinal") or {}
    testing = json.loads(sm.params.testing)
    hyp_id = opts.get("hyp_id")
    if hyp_id is None:
        hyp_id = pick_hypothesis(st.results, rejected=True, outcome=opts.get("outcome"),
                                 run_status=st.run_status)
        hyp_id = extend_to_horizon(st.results, st.hyps, hyp_id)  # show t = 1..T
    frame = longitudinal_frame(
        st, int(hyp_id), alpha=float(testing.get("alpha", 0.05)),
        quantiles=tuple(json.loads(sm.params.quantiles)),
    )  # fmt: skip
    # hours of the path that are themselves tested hypotheses, and which were rejected
    kind = st.hyps.loc[st.hyps["hyp_id"] == int(hyp_id), "kind"].iloc[0]
    ids = {
        _key(r.outcome, r.kind, r.t, r.actions, r.bins): r.hyp_id
        for r in st.hyps.itertuples(index=False)
    }
    rejected = set(st.results.loc[st.results["rejected"], "hyp_id"])
    rej_t = [
        int(r.t) for r in frame.itertuples(index=False)
        if ids.get(_key(r.outcome, kind, r.t, r.actions, r.bins)) in rejected
    ]  # fmt: skip
    log.info("hypothesis %s; rejected at hours %s", hyp_id, rej_t)
    write_csv(frame.assign(kind=kind, rejected=frame["t"].isin(rej_t)), sm.output.csv)
    last = frame.iloc[-1]
    state = f"rejected at t = {', '.join(map(str, rej_t))}" if rej_t else "not rejected"
    title = (
        f"twin {sm.wildcards.twin}: {last['outcome']} ({kind}), a = "
        f"{'-'.join(map(str, last['actions']))}, B = {'-'.join(map(str, last['bins']))}\n{state}"
    )
    save_all(longitudinal(frame, title=title), sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
