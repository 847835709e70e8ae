#!/usr/bin/env bash
# A separate virtualenv with `transformers serve` (transformers[serving]), the real OpenAI-compatible server the
# remote-scorer test drives (tests/scorer/test_scorer_serve.py). Separate because it needs torch==2.14.1 with
# torchvision==0.29.1 (the Qwen2-VL processor loads a video processor that needs torchvision, and the only
# torchvision wheels on the registries are CUDA builds matching a CUDA torch): about 5.5 GB, while the project's
# .venv keeps the CPU torch 2.13.0. The CPU torch 2.13.0 with torchvision 0.28.0 makes a 1.3 GB venv, but that
# torchvision's _C.so needs libc10_cuda.so and libtorch_cuda.so, so `import torchvision` fails ("operator
# torchvision::nms does not exist") and without torchvision transformers refuses Qwen2VLVideoProcessor; and the
# CUDA torch's libtorch_cuda.so links cuBLAS, cuDNN, NCCL, cuFFT ... (about 2.2 GB of nvidia-* wheels).
# Guarded by a stamp: a second run takes a moment.
# Usage: bash scripts/setup-serve.sh   (VENV_SERVE=path to put it elsewhere; default var/venv-serve)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV_SERVE=${VENV_SERVE:-var/venv-serve}
PINS=("torch==2.14.1" "torchvision==0.29.1" "transformers[serving]==5.23.0" "pillow")
stamp="$VENV_SERVE/.serve-installed-$(printf '%s ' "${PINS[@]}" | sha1sum | cut -c1-12)"
[ -f "$stamp" ] && exit 0
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || { echo "setup-serve: needs $PY (set PYTHON=)" >&2; exit 1; }
echo "setup-serve: installing transformers serve into $VENV_SERVE (${PINS[*]}; about 5.5 GB, a few minutes)"
t0=$(date +%s)
[ -x "$VENV_SERVE/bin/python" ] || "$PY" -m venv "$VENV_SERVE"
"$VENV_SERVE/bin/python" -m pip install -q "${PINS[@]}" 2>&1 | grep -v '^WARNING: Location' || true
"$VENV_SERVE/bin/python" -c 'import torch, torchvision, fastapi, uvicorn, transformers.cli.serve' \
  || { echo "setup-serve: the install did not complete (see pip output above)" >&2; exit 1; }
rm -f "$VENV_SERVE"/.serve-installed-*
touch "$stamp"
echo "setup-serve: done in $(( $(date +%s) - t0 )) s"
