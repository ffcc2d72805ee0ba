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

.PHONY: setup demo test lint bench bench-quick clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q $(TORCH_INDEX_ARG) "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

setup: $(VENV)/.installed

demo: setup
	$(PY) -m slam.run demo

test: setup
	$(PY) -m ruff check .
	$(PY) -m pytest -q

bench-quick: setup
	$(PY) -m benchmarks.run_all --quick

bench: setup
	$(PY) -m benchmarks.run_all

clean:
	rm -rf $(VENV) outputs .pytest_cache
