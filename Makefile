# Set-up and the two everyday commands. Everything installs into .venv on first use.
#   make demo   run a handful of tasks end to end (the main job at this stage)
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
	@for system in spring ball motor; do \
	  for arch in unstructured input_affine port_hamiltonian; do \
	    $(PY) -m nsl_hpc.train system=$$system arch=$$arch epochs=32 data_tier=16 width_tier=8 \
	      depth_tier=2 seed=0 out_dir=$(DEMO_DIR) || exit 1; \
	  done; \
	done
	@echo "rows: $(DEMO_DIR)/rows/"

# The SLURM tests need the real single-node cluster; without root they are skipped (under CI=true,
# a cluster that cannot start fails the run).
test: $(INSTALLED)
	bash cluster/up.sh --optional
	$(PY) -m pytest

lint: $(INSTALLED)
	$(VENV)/bin/ruff check .
