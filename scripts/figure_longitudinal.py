"""Rule figure_longitudinal: bounds, twin and naive means over t for one hypothesis."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install


from twinfalsify.figures import longitudinal, longitudinal_title, save_all  # noqa: E402
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
    opts = sm.params.figures.get("longitudinal") or {}
    testing = sm.params.testing
    hyp_id = opts.get("hyp_id")
    if hyp_id is None:
        hyp_id = pick_hypothesis(st.results, rejected=True, outcome=opts.get("outcome"),
                                 run_status=st.run_status)
        hyp_id = extend_to_horizon(st.results, st.hyps, hyp_id)  # show t = 1..T
    frame = longitudinal_frame(
        st, int(hyp_id), alpha=float(testing["alpha"]),
        quantiles=tuple(sm.params.quantiles),
    )  # fmt: skip
    # hours of the path that are themselves tested hypotheses, and which were rejected
    kind = st.hyps.loc[st.hyps["hyp_id"] == int(hyp_id), "kind"].iloc[0]
    ids = {
        _key(r.outcome, r.kind, r.t, r.actions, r.bins): r.hyp_id
        for r in st.hyps.itertuples(index=False)
    }
    # per test method, the hours whose own hypothesis it rejected (the figure draws
    # Hoeffding intervals; its title names which method rejected which hour)
    path_ids = [ids.get(_key(r.outcome, kind, r.t, r.actions, r.bins))
                for r in frame.itertuples(index=False)]  # fmt: skip
    rej_hours = {}
    for method, part in st.results.groupby("method", sort=False):
        rejected = set(part.loc[part["rejected"], "hyp_id"])
        rej_hours[method] = [int(t) for t, h in zip(frame["t"], path_ids, strict=True)
                             if h in rejected]  # fmt: skip
    log.info("hypothesis %s; rejected hours per method %s", hyp_id, rej_hours)
    frame = frame.assign(kind=kind, **{
        f"rejected_{m}": frame["t"].isin(hours) for m, hours in rej_hours.items()
    })  # fmt: skip
    write_csv(frame, sm.output.csv)
    correction = str(st.results["correction"].iloc[0]) if len(st.results) else "holm"
    title = longitudinal_title(sm.wildcards.twin, frame, kind, rej_hours, correction)
    save_all(longitudinal(frame, title=title), sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
