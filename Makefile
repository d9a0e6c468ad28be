# The README's two commands: `make demo` and `make test`. Both set up .venv on first use.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The CPU wheel of torch lies on this machine's disk; a looser pin would pull a CUDA build.
PIP_FLAGS ?= --disable-pip-version-check -q

.PHONY: demo test bench check-wheel venv clean

# The compiled tracer core builds on install: a change to its source reinstalls.
$(STAMP): pyproject.toml setup.py scube_sim/raytrace/_core.cpp
	@bash tools/ensure-system-deps.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install $(PIP_FLAGS) --upgrade pip
	$(PY) -m pip install $(PIP_FLAGS) -e '.[test,ray]'
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/scube-sim demo -o out

test: $(STAMP)
	$(PY) -m pytest -q -p no:cacheprovider tests

bench: $(STAMP)
	$(PY) -m bench.run_all

# The wheel, installed into a fresh environment and used from there (CI runs it after test).
check-wheel: $(STAMP)
	$(PY) tools/check_wheel.py

clean:
	rm -rf out $(VENV) *.egg-info
