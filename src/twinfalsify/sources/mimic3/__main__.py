"""CLI: python -m twinfalsify.sources.mimic3 FOLDER OUTDIR [options] (see cohort.main)."""

from .cohort import main

main()
