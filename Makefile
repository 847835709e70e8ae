# `make demo` and `make test` do all set-up on a fresh machine (scripts/setup.sh, guarded and quick to rerun).
VENV ?= .venv
PY := $(VENV)/bin/python
export RERUN_TELEMETRY_ENABLED := false
export HF_HUB_OFFLINE := 1

.PHONY: setup demo test lint bench up clean

setup:
	@VENV=$(VENV) bash scripts/setup.sh

demo: setup
	$(VENV)/bin/eqa ask

test: setup
	$(PY) -m ruff check .
	$(PY) -m pytest -q -p no:cacheprovider

lint: setup
	$(PY) -m ruff check .

bench: setup
	$(PY) bench/run_all.py

up: setup
	$(VENV)/bin/eqa up

clean:
	rm -rf var .pytest_cache .ruff_cache
