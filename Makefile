# Set-up and the two everyday commands. Everything installs into .venv on first use.
#   make demo   the main job: the demo sweep (216 tasks) on local processes, then merge, NSL fits,
#               figures, MLflow and report.html
#   make test   start the two local SLURM clusters (cluster/up.sh) and run the test suite but its slow tier
#   make test-slow  the slow tier: the tests over about 10 s of CPU that need no cluster (CI runs it after make test)
#   make test-fast  the tests that need no cluster, run no command end to end and are not slow (README: its time)
#   make test-without-slurm  make test-fast with SLURM's client commands off PATH, as on a laptop (CI runs it)
#   make demo-io  the input-output demo (io_demo, 60 tasks on the simulated stand-ins), merge ... report.html
#   make repro  the reduced-scale reproduction (docs/reproduction.md): the repro and repro_io sweeps (~1.8 predicted
#               core-hours) into runs/repro/{input_state,input_output}, then the SUBNET laws' slices subnet_compute
#               and subnet_data (~1.2 predicted core-hours) into runs/repro/subnet_{compute,data}, each with its
#               report (52, 15, 11 and 17 min on one worker each), then the status table of docs/reproduction.md
#               (benchmarks/reproduction_status.py). REPRO_DIR=...
#               REPRO_ARGS="sweep_seed=1 repro.seeds=[0]": the cheaper check run of the first two.
#   make repro-candidates  the other settings the status table sets beside the defaults (conf/reproduction.yaml,
#               candidates) into REPRO_DIR/<slice>__<name>, and the slices that decide the remaining gaps (gap_slices)
#               into REPRO_DIR/<slice>, then the table again
#   make mechanisms  the mechanism table (docs/reproduction.md, "One table for every candidate"): every candidate of
#               conf/mechanisms.yaml trained on the slices mechanism_compute and mechanism_data into runs/mechanisms,
#               scored on every published law they cover; runs/mechanisms/table.md. MECHANISMS_ARGS="only=[...]"
#   make data   the measured Silverbox / Wiener-Hammerstein files into data/: from DATA_SOURCE, else downloaded
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
INSTALLED := $(VENV)/.installed
DEMO_DIR ?= runs/demo
IO_DEMO_DIR ?= runs/io_demo
DATA_SOURCE ?= ../shared/data
REPRO_DIR ?= runs/repro
REPRO_ARGS ?=
MECHANISMS_ARGS ?=

.PHONY: install demo demo-io repro repro-candidates mechanisms data test test-slow test-fast test-without-slurm lint

install: $(INSTALLED)

# torch first, pinned, and the CPU build: from what pip has without an index (its local wheels or cache, no wait on
# an index it cannot reach), else from TORCH_INDEX, PyTorch's CPU wheel index (about 200 MB; PyPI's Linux torch is
# the CUDA build, gigabytes of GPU libraries). GPU nodes: TORCH_INDEX=https://download.pytorch.org/whl/cu126.
# torch's own dependencies come from PyPI with the package's.
TORCH := torch==2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
PIP := $(PY) -m pip install --quiet --disable-pip-version-check
# The rest with uv (Astral's resolver and installer, from PyPI: 72 s where pip takes 172 on this 2-core VM, a fresh
# .venv and an empty uv cache), which keeps the torch above; else with pip (a site whose index only pip's
# configuration names: uv does not read it). Compiled to bytecode as pip does: where PYTHONDONTWRITEBYTECODE is set,
# every process would compile what it imports anew (mlflow's imports: 5.3 s instead of 1.8).
UV := $(PY) -m uv pip install --quiet --compile-bytecode --python $(PY)
# The package's own bytecode (an editable install compiles none), brought up to date before the tests: where
# PYTHONDONTWRITEBYTECODE is set, each of the suite's hundreds of commands and jobs would compile nsl_hpc's modules
# anew (0.31 s of CPU each instead of 0.15).
BYTECODE := $(PY) -m compileall -q nsl_hpc

$(INSTALLED): pyproject.toml
	@echo "make install: a virtual environment in $(VENV) with nsl_hpc and its dependencies (once; a minute or two)"
	$(PYTHON) -m venv $(VENV) || { echo "error: $(PYTHON) -m venv failed; on Debian/Ubuntu: apt-get install python3-venv"; exit 1; }
	@echo "  $(TORCH), the CPU build (about 200 MB; from pip's cache when it has it, else $(TORCH_INDEX))"
	$(PIP) --no-deps --no-index $(TORCH) 2>/dev/null || $(PIP) --no-deps --index-url $(TORCH_INDEX) $(TORCH)
	@echo "  numpy, scipy, submitit, hydra-core, mlflow, pyarrow, matplotlib, tqdm, nonlinear-benchmarks, and pytest, ruff,"
	@echo "  mypy for the tests (a few hundred MB from PyPI, by uv where it installs)"
	{ $(PIP) uv && $(UV) -e '.[test]'; } || $(PIP) -e '.[test]'
	$(BYTECODE)
	touch $@

demo: $(INSTALLED)
	$(PY) -m nsl_hpc.launch +sweep=demo sweep_dir=$(DEMO_DIR)
	$(PY) -m nsl_hpc.report sweep_dir=$(DEMO_DIR)

demo-io: $(INSTALLED)
	$(PY) -m nsl_hpc.launch +sweep=io_demo sweep_dir=$(IO_DEMO_DIR)
	$(PY) -m nsl_hpc.report sweep_dir=$(IO_DEMO_DIR)

repro: data
	$(PY) -m nsl_hpc.launch +sweep=repro sweep_dir=$(REPRO_DIR)/input_state $(REPRO_ARGS)
	$(PY) -m nsl_hpc.report sweep_dir=$(REPRO_DIR)/input_state
	$(PY) -m nsl_hpc.launch +sweep=repro_io sweep_dir=$(REPRO_DIR)/input_output $(REPRO_ARGS)
	$(PY) -m nsl_hpc.report sweep_dir=$(REPRO_DIR)/input_output
	$(PY) -m nsl_hpc.launch +sweep=subnet_compute sweep_dir=$(REPRO_DIR)/subnet_compute
	$(PY) -m nsl_hpc.report sweep_dir=$(REPRO_DIR)/subnet_compute
	$(PY) -m nsl_hpc.launch +sweep=subnet_data sweep_dir=$(REPRO_DIR)/subnet_data
	$(PY) -m nsl_hpc.report sweep_dir=$(REPRO_DIR)/subnet_data
	$(PY) benchmarks/reproduction_status.py root=$(REPRO_DIR)

repro-candidates: data
	$(PY) benchmarks/reproduction_status.py root=$(REPRO_DIR) train=true

mechanisms: $(INSTALLED)
	$(PY) benchmarks/mechanisms.py $(MECHANISMS_ARGS)

# From DATA_SOURCE where that folder exists, else downloaded by the benchmarks' loaders (docs/science.md)
data: $(INSTALLED)
	$(PY) -m nsl_hpc.place_data $(if $(wildcard $(DATA_SOURCE)),source=$(DATA_SOURCE),) data_dir=data

# The SLURM tests need the real single-node clusters; without root they are skipped (under CI=true,
# a cluster that cannot start fails the run).
# pytest-xdist workers: make test runs the SLURM tests (mostly waiting on the scheduler and on jobs that sleep) on two
# workers, one per cluster, each test after another, and a test file at a time on each of two others, filling both
# cores; make test-slow and make test-fast run two (tests/conftest.py's scheduling); more workers only contend for the
# two cores (the tests are CPU-bound).
# TEST_WORKERS=N sets each; TEST_WORKERS=0 runs in this process.
TEST_WORKERS ?=
# The two clusters start (on a fresh machine: the first installs SLURM, munge and MariaDB) while .venv installs;
# their lines follow. The SLURM tests run on both at once (tests/clusters.py).
test:
	@log=$$(mktemp); { bash cluster/up.sh --optional && CLUSTER_INSTANCE=2 bash cluster/up.sh --optional; } \
	  > $$log 2>&1 & up=$$!; \
	  $(MAKE) --no-print-directory install; installed=$$?; \
	  wait $$up; started=$$?; cat $$log; rm -f $$log; \
	  [ $$installed -eq 0 ] && [ $$started -eq 0 ]
	$(BYTECODE)
	$(PY) -m pytest -n $(or $(TEST_WORKERS),4) -m "not slow"

# The slow tier (pyproject.toml's slow marker: no SLURM test is in it): CI runs it after make test (README: its time).
test-slow: $(INSTALLED)
	$(BYTECODE)
	$(PY) -m pytest -n $(or $(TEST_WORKERS),2) -m slow

# Everything but the cluster, the end-to-end and the slow tests: the science, the planning core, fits (README: its time).
test-fast: $(INSTALLED)
	$(BYTECODE)
	$(PY) -m pytest -n $(or $(TEST_WORKERS),2) -m "not slurm and not e2e and not slow" --ignore=tests/cluster

# A PATH of links to everything on PATH but SLURM's client commands: test-fast must pass where SLURM is not installed.
SLURM_COMMANDS := sbatch srun squeue sacct sacctmgr scontrol scancel sinfo salloc sattach sbcast sdiag sprio sreport \
	sshare sstat strigger sview
test-without-slurm: $(INSTALLED)
	@bin=$$(mktemp -d); trap 'rm -rf "$$bin"' EXIT; \
	  for dir in $$(echo "$$PATH" | tr : ' '); do for file in "$$dir"/*; do name=$${file##*/}; \
	    case " $(SLURM_COMMANDS) " in *" $$name "*) ;; *) [ -e "$$bin/$$name" ] || ln -s "$$file" "$$bin/$$name";; esac; \
	  done; done; \
	  for name in $(SLURM_COMMANDS); do if PATH="$$bin" command -v $$name >/dev/null; then echo "error: $$name is still on PATH" >&2; exit 1; fi; done; \
	  PATH="$$bin" $(MAKE) --no-print-directory test-fast

lint: $(INSTALLED)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
