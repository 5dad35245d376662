# Two-command set-up: `make demo` and `make test` each create .venv when missing
# and install the package with its dependencies from PyPI.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench experiments lint clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev,geo]'
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m reblur demo --out demo_output --overwrite

test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile tests

bench: $(STAMP)
	$(PY) -m benchmarks.run

# the paper's experiments and the baselines -> docs/results/ (about half an hour on 2 cores)
experiments: $(STAMP)
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $(PY) -m experiments.run

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks experiments

clean:
	rm -rf $(VENV) demo_output
