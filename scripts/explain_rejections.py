"""Rule explain_rejections: the first k rejections of one twin in clinical words, each with
its own bounds-over-time figure, as one page of the report."""

import io
import sys
from pathlib import Path

import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install

from twinfalsify.explain import (  # noqa: E402
    explain,
    explained_html,
    rejections_to_explain,
)
from twinfalsify.figures import longitudinal, longitudinal_title  # noqa: E402
from twinfalsify.io import log, run_rule, write_text  # noqa: E402
from twinfalsify.summary import load_study_twin, longitudinal_frame  # noqa: E402
from twinfalsify.twin_tests import outcome_sizes  # noqa: E402


def main(sm):
    twin = sm.wildcards.twin
    st = load_study_twin({k: v for k, v in sm.input.items()})
    k = int(sm.params.figures["explained"]["k"])
    ids, n_rejected = rejections_to_explain(st.results, k)
    alpha = float(sm.params.testing["alpha"])
    correction = str(st.results["correction"].iloc[0]) if len(st.results) else "holm"
    results_dir = Path(sm.input.hypotheses).parent.parent
    sizes = {twin: outcome_sizes(st.samples).set_index(st.hyps["hyp_id"].to_numpy())}
    sections = []
    for hyp_id in ids:
        # the hypothesis's own path, hours 1..t (t = 1: one hour, drawn as a box)
        frame = longitudinal_frame(st, hyp_id, alpha=alpha, quantiles=tuple(sm.params.quantiles))
        mine = st.results[st.results["hyp_id"] == hyp_id]
        kind = str(mine["kind"].iloc[0])
        t = int(mine["t"].iloc[0])
        rejected = {m: [t] for m in mine.loc[mine["rejected"], "method"].unique()}
        fig = longitudinal(frame, title=longitudinal_title(twin, frame, kind, rejected,
                                                           correction))
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110)
        plt.close(fig)
        sections.append((hyp_id, explain(results_dir, hyp_id, twin, sizes), buf.getvalue()))
    log.info("twin %s: %d of %d rejections explained (%s)", twin, len(ids), n_rejected, ids)
    write_text(explained_html(twin, sections, n_rejected), sm.output[0])


run_rule(snakemake, main)  # noqa: F821
