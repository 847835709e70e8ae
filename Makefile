# `make demo` and `make test` do all set-up on a fresh machine (scripts/setup.sh, guarded and quick to rerun).
VENV ?= .venv
PY := $(VENV)/bin/python
export RERUN_TELEMETRY_ENABLED := false
export HF_HUB_OFFLINE := 1

.PHONY: setup demo test lint bench up clean compose-smoke

setup:
	@VENV=$(VENV) bash scripts/setup.sh

demo: setup
	$(VENV)/bin/eqa ask

test: setup
	@# the real OpenAI-compatible server of tests/scorer/test_scorer_serve.py in its own venv (~5.5 GB, a few
	@# minutes the first time, then a stamp check): set-up time, not suite time. If it fails, that test skips saying why.
	@bash scripts/setup-serve.sh || echo "setup: transformers serve could not be installed; tests/scorer/test_scorer_serve.py will skip" >&2
	$(PY) -m ruff check .
	$(PY) -m pytest -q -p no:cacheprovider

lint: setup
	$(PY) -m ruff check .

bench: setup
	$(PY) bench/run_all.py

up: setup
	$(VENV)/bin/eqa up

# The compose fleet in podman containers, one question through them (not part of `make test`:
# 8.5 min on a host without podman, about 1.5 min once set up and built; see README "Containers here").
compose-smoke:
	bash scripts/containers.sh setup
	bash scripts/containers.sh build
	python3 scripts/compose_smoke.py

clean:
	rm -rf var .pytest_cache .ruff_cache

# The reliability tests N times each with every core busy, then the recovery figures (not part of `make test`;
# `make stress STRESS_RUNS=3` for a short run; scripts/stress.py --help).
STRESS_RUNS ?= 30
.PHONY: stress
stress: setup
	$(PY) scripts/stress.py --runs $(STRESS_RUNS) $(STRESS_ARGS)
