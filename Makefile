# Two-command set-up: `make demo` and `make test` each create .venv when missing
# and install the package with its dependencies from PyPI.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench experiments lint clean bytecode

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev,geo]'
	@touch $(STAMP)

# the package's bytecode, as a regular (not editable) pip install writes it: under
# PYTHONDONTWRITEBYTECODE every fresh process (a run, a test's subprocess) would
# compile the modules again, ~0.15 s each (incremental: only changed modules)
bytecode: $(STAMP)
	@$(PY) -m compileall -q src/reblur

demo: bytecode
	$(PY) -m reblur demo --out demo_output --overwrite

test: bytecode
	$(PY) -m pytest -n 2 --dist loadfile tests

bench: bytecode
	$(PY) -m benchmarks.run

# the paper's experiments and the baselines -> docs/results/ (about half an hour on 2 cores)
experiments: bytecode
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $(PY) -m experiments.run

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks experiments

clean:
	rm -rf $(VENV) demo_output
