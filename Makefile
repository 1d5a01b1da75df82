# Two commands for a newcomer: `make reproduce` and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
CORES ?= 2
STAMP := $(VENV)/.installed

.PHONY: setup reproduce test lint report docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

## Set up and run the default study (synthetic world, builtin twins).
reproduce: $(STAMP)
	$(BIN)/snakemake --cores $(CORES)

## Set up and run the test suite.
test: $(STAMP)
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check src scripts tests benchmarks
	$(BIN)/snakefmt --check Snakefile workflow/rules
	$(BIN)/snakemake --lint --cores 1

## Build the documentation site into site/ (strict: a broken link fails).
docs: $(STAMP)
	$(BIN)/mkdocs build --strict

clean:
	rm -rf results .snakemake
