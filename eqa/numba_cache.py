"""Where numba's machine-code cache goes (every ``cache=True`` kernel module calls :func:`choose_cache_dir`
before its ``njit`` definitions).

Never into the source tree (a read-only install cannot write there, a checkout would get dirty):
``NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/eqa/numba`` (``~/.cache/eqa/numba``), else
``<temp dir>/eqa-numba-cache-<uid>`` (with none of them writable, numba's own fallbacks apply).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numba


def cache_dir_candidates() -> list[Path]:
    """Where numba's cache may go, in order of preference (never next to the source)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    uid = os.getuid() if hasattr(os, "getuid") else 0
    return [Path(base) / "eqa" / "numba", Path(tempfile.gettempdir()) / f"eqa-numba-cache-{uid}"]


def choose_cache_dir() -> None:
    """Point numba's cache at the first writable candidate, unless ``NUMBA_CACHE_DIR`` already says where.

    numba looks for a user-provided directory first and then falls back to ``__pycache__`` beside the source;
    setting ``numba.config.CACHE_DIR`` before a module's ``njit`` calls keeps it out of the tree."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    for target in cache_dir_candidates():
        try:
            target.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(target, os.W_OK):
            numba.config.CACHE_DIR = str(target.resolve())
            return
