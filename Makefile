# Two entry points (see README Quickstart): `make demo` and `make test`.
# Both create .venv on first use. TORCH pins the CPU wheel so a fresh install does not
# pull gigabytes of CUDA packages; on a GPU host set TORCH= to keep the installed build.
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
