#!/usr/bin/env bash
# One-time (and cheap to repeat) set-up: Debian packages, a Python 3.11 virtualenv, the project and its
# pinned dependencies. Every step is guarded, so a second run takes about a second.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}

need_apt=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || need_apt+=(libusb-1.0-0)   # open3d imports it
command -v redis-server >/dev/null 2>&1 || need_apt+=(redis-server)                 # tests run a private one
command -v chromium >/dev/null 2>&1 || need_apt+=(chromium)                         # browser tests (docs, console)
command -v chromedriver >/dev/null 2>&1 || need_apt+=(chromium-driver)              # ... driven by selenium
. scripts/apt.sh
apt_install setup "${need_apt[@]}"

PY=${PYTHON:-}
if [ -z "$PY" ]; then
  for cand in python3.11 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      PY=$cand; break
    fi
  done
fi
[ -n "$PY" ] || { echo "setup: Python 3.11 is required (set PYTHON=/path/to/python3.11)" >&2; exit 1; }

[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
stamp="$VENV/.eqa-installed-$(cat pyproject.toml | sha1sum | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  echo "setup: installing the project into $VENV (torch is pinned to the CPU build)"
  "$VENV/bin/python" -m pip install -q --upgrade pip 2>&1 | grep -v '^WARNING: Location' || true
  # torch first and pinned, so nothing pulls a CUDA build. PyPI's Linux torch 2.13.0 is the CUDA build (527 MB
  # plus 2.2 GB of nvidia-* and triton wheels); PyTorch's CPU index has 2.13.0+cpu (192 MB), which pip prefers
  # (a local version sorts above the plain one) and which still satisfies torch==2.13.0. Where that index cannot
  # be reached pip falls back to the CUDA build (or to a wheel in a configured find-links directory); it is probed
  # first because pip asks an extra index for every package and retries an unreachable one for each (a minute).
  torch_index=()
  "$VENV/bin/python" -c 'import urllib.request as u; u.urlopen("https://download.pytorch.org/whl/cpu/torch/", timeout=10)' \
    >/dev/null 2>&1 && torch_index=(--extra-index-url https://download.pytorch.org/whl/cpu)
  "$VENV/bin/python" -m pip install -q "torch==2.13.0" "${torch_index[@]}" 2>&1 | grep -v '^WARNING: Location' || true
  "$VENV/bin/python" -m pip install -q -e '.[dev]' 2>&1 | grep -v '^WARNING: Location' || true
  "$VENV/bin/python" -c 'import open3d, zenoh, rerun, torch, transformers' \
    || { echo "setup: the install did not complete (see pip output above)" >&2; exit 1; }
  rm -f "$VENV"/.eqa-installed-*
  touch "$stamp"
fi

# promtool (tests/fleet/test_prometheus_rules.py, tests/fleet/test_compose.py): the binary alone, taken out of
# Debian's prometheus package into the venv's bin. Installing the package would also install and start a
# Prometheus server (its init script), which a test machine does not want.
if ! command -v promtool >/dev/null 2>&1 && [ ! -x "$VENV/bin/promtool" ]; then
  tmp=$(mktemp -d)
  if ! (cd "$tmp" && apt-get download -qq prometheus >/dev/null 2>&1) && [ "$(id -u)" = 0 ]; then
    apt-get update -qq && (cd "$tmp" && apt-get download -qq prometheus >/dev/null 2>&1) || true
  fi
  deb=$(ls "$tmp"/prometheus_*.deb 2>/dev/null | head -1)
  if [ -n "$deb" ] && dpkg-deb --fsys-tarfile "$deb" | tar -x -C "$tmp" ./usr/bin/promtool; then
    install -m 0755 "$tmp/usr/bin/promtool" "$VENV/bin/promtool"
    echo "setup: promtool $("$VENV/bin/promtool" --version 2>&1 | sed -n '1s/^promtool, version \([^ ]*\).*/\1/p') from Debian's prometheus package in $VENV/bin"
  else
    echo "setup: promtool could not be fetched (apt-get download prometheus); the rules tests will skip saying why" >&2
  fi
  rm -rf "$tmp"
fi
