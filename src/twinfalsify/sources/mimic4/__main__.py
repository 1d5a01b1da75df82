from twinfalsify.sources.mimic3.cohort import main
from twinfalsify.sources.mimic4 import MIMIC4

main(layout=MIMIC4)
