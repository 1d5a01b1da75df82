"""Rule figure_histograms: raw outcomes, observational vs twin, with Hoeffding intervals."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(snakemake.scriptdir).parent / "src"))  # noqa: F821 - library without install


from twinfalsify.figures import outcome_histograms, save_all  # noqa: E402
from twinfalsify.io import run_rule  # noqa: E402
from twinfalsify.summary import histogram_data, load_study_twin, pick_hypothesis  # noqa: E402


def main(sm):
    st = load_study_twin(dict(sm.input.items()))
    opts = sm.params.figures.get("histograms") or {}  # no default: picked automatically
    alpha = float(sm.params.testing["alpha"])
    ids = opts.get("hyp_ids")
    if not ids:  # one rejected and one non-rejected case
        first = pick_hypothesis(st.results, rejected=True, prefer_long=False,
                                run_status=st.run_status)
        ids = [first, pick_hypothesis(st.results, rejected=False, exclude=(first,))]
    cases = [histogram_data(st, int(h), alpha=alpha) for h in ids]
    methods = [str(m) for m in st.results["method"].unique()]  # "min p" is over these
    fig = outcome_histograms(cases, twin=sm.wildcards.twin, methods=methods, alpha=alpha)
    save_all(fig, sm.output.png, sm.output.pdf)


run_rule(snakemake, main)  # noqa: F821
