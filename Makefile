# The README's two commands: `make demo` and `make test`. Both set up .venv on first use.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The CPU wheel of torch lies on this machine's disk; a looser pin would pull a CUDA build.
PIP_FLAGS ?= --disable-pip-version-check -q

.PHONY: demo test bench check-wheel venv clean completion-data

# The compiled tracer core builds on install: a change to its source reinstalls.
$(STAMP): pyproject.toml setup.py scube_sim/raytrace/_core.cpp scube_sim/reconstruct/stereo/_sweep.cpp
	@bash tools/ensure-system-deps.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install $(PIP_FLAGS) --upgrade pip
	$(PY) -m pip install $(PIP_FLAGS) -e '.[test,ray]'
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/scube-sim demo -o out

# Two test processes (pytest-xdist), each taking a whole test file at a time: most of the suite
# runs on one core, and a file's fixtures are then built once. TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile tests

# The completion stage's training data (docs/converter.md, "The learned completion"): worlds
# with +-4 context instants and the evidence the stereo pipeline measures in them, cached under
# $(WORLDS)/evidence. Resumable: run it again to go on where it stopped (hours on 2 cores).
WORLDS ?= data/worlds9
WORLDS_OPTS := --rig waymo-5 --image-scale 0.25 --fine-voxel 0.1 --coarse-factor 4 --frame-offsets=-4,-3,-2,-1,0,1,2,3,4
completion-data: $(STAMP)
	test -f $(WORLDS)/dataset.json || $(VENV)/bin/scube-sim worlds generate -o $(WORLDS) --split val --count 8 $(WORLDS_OPTS)
	$(VENV)/bin/scube-sim worlds generate -o $(WORLDS) --split val --count 8
	$(VENV)/bin/scube-sim worlds generate -o $(WORLDS) --split train --count 200 -j 2
	$(VENV)/bin/scube-sim worlds generate -o $(WORLDS) --split test --count 40 -j 2
	$(VENV)/bin/scube-sim worlds evidence $(WORLDS) --split val -j 2
	$(VENV)/bin/scube-sim worlds evidence $(WORLDS) --split train -j 2

bench: $(STAMP)
	$(PY) -m bench.run_all

# The wheel, installed into a fresh environment and used from there (CI runs it after test).
check-wheel: $(STAMP)
	$(PY) tools/check_wheel.py

clean:
	rm -rf out $(VENV) *.egg-info
