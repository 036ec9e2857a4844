# Two entry points (see README Quickstart): `make demo` and `make test`.
# Both create .venv on first use. TORCH pins torch's version, installed before the rest. It is
# the CPU build only where pip can see that wheel (a local wheel directory, or
# PIP_EXTRA_INDEX_URL=https://download.pytorch.org/whl/cpu: torch==2.13.0 then resolves to
# 2.13.0+cpu); PyPI's own Linux wheel pulls gigabytes of CUDA packages. On a GPU host set
# TORCH= to keep the installed build.
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
BIN := $(VENV)/bin

.PHONY: setup demo test test-gpu clean

$(BIN)/robion: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	@if [ -n "$(TORCH)" ]; then $(BIN)/pip install -q "$(TORCH)"; fi
	$(BIN)/pip install -q -e '.[test]'
	@touch $@

setup: $(BIN)/robion

demo: setup
	$(BIN)/robion demo

test: setup
	$(BIN)/python -m pytest -q

test-gpu: setup
	$(BIN)/python -m pytest -q -m gpu

clean:
	rm -rf $(VENV)
