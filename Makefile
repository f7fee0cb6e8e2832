# Set-up and the two everyday commands. Everything installs into .venv on first use.
#   make demo   the main job: the demo sweep (216 tasks) on local processes, then merge, NSL fits,
#               figures, MLflow and report.html
#   make test   start the local SLURM cluster (cluster/up.sh) and run the test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
INSTALLED := $(VENV)/.installed
DEMO_DIR ?= runs/demo

.PHONY: install demo test lint

install: $(INSTALLED)

# torch first, pinned: its CPU wheel; an unpinned torch (or one pulled in by a dependency) is a CUDA build.
$(INSTALLED): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check torch==2.13.0
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	touch $@

demo: $(INSTALLED)
	$(PY) -m nsl_hpc.launch +sweep=demo sweep_dir=$(DEMO_DIR)
	$(PY) -m nsl_hpc.report sweep_dir=$(DEMO_DIR)

# The SLURM tests need the real single-node cluster; without root they are skipped (under CI=true,
# a cluster that cannot start fails the run).
test: $(INSTALLED)
	bash cluster/up.sh --optional
	$(PY) -m pytest

lint: $(INSTALLED)
	$(VENV)/bin/ruff check .
