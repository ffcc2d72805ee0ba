# Two commands on a fresh machine:  `make demo`  and  `make test`.
# Both create .venv on first use. Torch is installed first on its own so that a CPU build can be
# chosen: here `torch==2.13.0` resolves to the local CPU wheel; elsewhere pass e.g.
#   make demo TORCH_INDEX=https://download.pytorch.org/whl/cpu
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
TORCH_SPEC ?= torch==2.13.0
TORCH_INDEX ?=
TORCH_INDEX_ARG := $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX),)
# KISS-SLAM, the benchmarks' reference system, lives in its own environment (it pins its own
# kiss-icp and needs open3d); benchmarks find it through BENCH_KISS_SLAM_VENV.
KISS_SLAM_VENV ?= .venv-kiss-slam
# kiss-slam 0.0.2 imports PIL, and kiss-icp's pipeline matplotlib at the end of a run, without
# declaring them.
KISS_SLAM_SPEC ?= kiss-slam==0.0.2 pillow matplotlib
KISS_SLAM_LOG := benchmarks/out/kiss-slam-env.log
# `make bench BEFORE=REV`: the benchmarks that can also measure REV (checked out beside this tree)
# put it in the same tables, in the same invocation.
BEFORE ?=
# BEFORE_IN=NAMES: only these benchmarks measure REV (see `python -m benchmarks.run_all --help`).
BEFORE_IN ?=
BENCH_ARGS := $(if $(BEFORE),--before $(BEFORE),) $(if $(BEFORE_IN),--before-in $(BEFORE_IN),)
BEFORE_LABEL := $(if $(BEFORE), BEFORE=$(BEFORE),)$(if $(BEFORE_IN), BEFORE_IN='$(BEFORE_IN)',)

.PHONY: setup demo test lint bench bench-quick kiss-slam-env clean

# --no-compile: Python compiles what a run imports on first use; compiling every module of torch,
# ray and sympy at install time is CPU a 2-core machine spends before the first test.
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q --no-compile $(TORCH_INDEX_ARG) "$(TORCH_SPEC)"
	$(PY) -m pip install -q --no-compile -e ".[dev]"
	touch $@

setup: $(VENV)/.installed

demo: setup
	$(PY) -m slam.run demo

# pytest-xdist: one test file per worker (module fixtures are built once); CI has 2 cores.
TEST_WORKERS ?= 2

# Each test process (the two workers, every command a test starts, every Ray task of the fleet
# tests) imports torch and the product afresh. Where PYTHONDONTWRITEBYTECODE is set (some shells
# and containers set it) nothing compiled is cached and each of them compiled it all again: about
# 3 s of CPU apiece. Unset, the first process to import a module caches its bytecode for the rest.
test: setup
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	env -u PYTHONDONTWRITEBYTECODE \
		$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

$(KISS_SLAM_VENV)/.installed:
	mkdir -p $(dir $(KISS_SLAM_LOG))
	{ $(PYTHON) -m venv $(KISS_SLAM_VENV) && \
	  $(KISS_SLAM_VENV)/bin/python -m pip install $(KISS_SLAM_SPEC); } > $(KISS_SLAM_LOG) 2>&1 \
	  || { tail -n 1 $(KISS_SLAM_LOG); exit 1; }
	@# open3d (a KISS-SLAM dependency) links the system's libusb-1.0; without it nothing imports.
	$(KISS_SLAM_VENV)/bin/python -c "import kiss_slam.pipeline" >> $(KISS_SLAM_LOG) 2>&1 \
	  || { echo "KISS-SLAM does not import: $$(tail -n 1 $(KISS_SLAM_LOG))" \
	       "(if it names libusb-1.0.so: apt install libusb-1.0-0)" | tee -a $(KISS_SLAM_LOG); exit 1; }
	touch $@

kiss-slam-env: $(KISS_SLAM_VENV)/.installed

# Regenerate BENCHMARKS.md and benchmarks/results/ (quick: < 35 min on 2 cores, no KISS-SLAM).
# A KISS-SLAM environment that cannot be created makes its rows say "skipped: <reason>".
bench-quick: setup
	BENCH_INVOKED_AS="make bench-quick$(BEFORE_LABEL)" $(PY) -m benchmarks.run_all --quick $(BENCH_ARGS)

bench: setup
	-$(MAKE) kiss-slam-env
	BENCH_INVOKED_AS="make bench$(BEFORE_LABEL)" BENCH_KISS_SLAM_VENV="$(abspath $(KISS_SLAM_VENV))" \
	  $(PY) -m benchmarks.run_all $(BENCH_ARGS)

clean:
	rm -rf $(VENV) $(KISS_SLAM_VENV) outputs .pytest_cache
