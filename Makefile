# `make demo` and `make test` do all set-up on a fresh machine (scripts/setup.sh, guarded and quick to rerun).
VENV ?= .venv
PY := $(VENV)/bin/python
export RERUN_TELEMETRY_ENABLED := false
export HF_HUB_OFFLINE := 1
# Selenium Manager posts usage statistics to an analytics host unless told not to (tests/support/browser.py sets
# these for the browser it starts; here for anything else that runs Selenium under make)
export SE_AVOID_STATS := true
export SE_OFFLINE := true

.PHONY: setup demo test test-servers lint bench up clean compose-smoke kube-smoke

setup:
	@VENV=$(VENV) bash scripts/setup.sh

demo: setup
	$(VENV)/bin/eqa ask

test: setup
	@# the real OpenAI-compatible server with logprobs of tests/scorer/test_scorer_llamacpp.py: llama.cpp's llama-server,
	@# built from source into ~/.cache/eqa/llama-cpp (a 37 MB download and 6-25 minutes on 2 cores the first
	@# time, then a stamp check): set-up time, not suite time. If it cannot be built, that test skips saying why.
	@bash scripts/setup-llama.sh >/dev/null || echo "setup: llama-server could not be set up; tests/scorer/test_scorer_llamacpp.py will skip or fail saying why" >&2
	$(PY) -m ruff check .
	$(PY) -m pytest -q -p no:cacheprovider

# The real model servers' tests only, `transformers serve` included: its own venv (var/venv-serve, ~5.5 GB, a few
# minutes the first time), so it is not part of `make test`.
test-servers: setup
	@bash scripts/setup-serve.sh
	@bash scripts/setup-llama.sh >/dev/null
	TEST_SERVERS=1 $(PY) -m pytest -q -p no:cacheprovider tests/scorer/test_scorer_serve.py tests/scorer/test_scorer_llamacpp.py

lint: setup
	$(PY) -m ruff check .

bench: setup
	$(PY) -m eqa_app.benches

up: setup
	$(VENV)/bin/eqa up

# The compose fleet in podman containers, one question through them (not part of `make test`:
# 8.5 min on a host without podman, about 1.5 min once set up and built; see README "Containers here").
compose-smoke:
	bash scripts/containers.sh setup
	bash scripts/containers.sh build
	python3 scripts/compose_smoke.py

# The Kubernetes base deploy/k8s played with `podman kube play`, one question through it (not part of `make test`:
# the image build of compose-smoke, then about 2 min; docs/deployment.md "Kubernetes"). podman needs catatonit
# for the pods' infra containers (no pause image can be pulled here).
kube-smoke: setup
	bash scripts/containers.sh setup
	@bash -c '. scripts/apt.sh; command -v catatonit >/dev/null 2>&1 || apt_install kube-smoke catatonit'
	bash scripts/containers.sh build
	$(PY) scripts/kube_smoke.py

clean:
	rm -rf var .pytest_cache .ruff_cache

# The reliability tests N times each with every core busy, then the recovery figures (not part of `make test`;
# `make stress STRESS_RUNS=3` for a short run; scripts/stress.py --help).
STRESS_RUNS ?= 30
.PHONY: stress
stress: setup
	$(PY) scripts/stress.py --runs $(STRESS_RUNS) $(STRESS_ARGS)
