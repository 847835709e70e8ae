"""numba's machine code for the TSDF kernel is cached outside the source tree (a read-only install cannot
write there; a clean checkout stays clean)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import services.mapper.tsdf_kernel as tsdf_kernel

SRC = Path(tsdf_kernel.__file__).resolve().parent


def _numba_files(root: Path) -> set[str]:
    return {p.name for p in root.rglob("*") if p.suffix in (".nbi", ".nbc")}


def test_the_kernel_cache_goes_to_the_user_cache_dir_not_the_source_tree(tmp_path: Path) -> None:
    before = _numba_files(SRC)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    out = subprocess.run(
        [sys.executable, "-c", "import numba, services.mapper.tsdf_kernel; print(numba.config.CACHE_DIR)"],
        env=env, capture_output=True, text=True, timeout=300, check=True,
    )
    target = tmp_path / "eqa" / "numba"
    assert out.stdout.strip() == str(target.resolve())
    assert _numba_files(target), "compiling the kernel wrote no cache index into the user cache dir"
    assert _numba_files(SRC) == before, "numba wrote its cache next to the source"


def test_numba_cache_dir_from_the_environment_wins(tmp_path: Path) -> None:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "explicit"), XDG_CACHE_HOME=str(tmp_path / "xdg"))
    subprocess.run([sys.executable, "-c", "import services.mapper.tsdf_kernel"], env=env, timeout=300, check=True)
    assert _numba_files(tmp_path / "explicit")
    assert not (tmp_path / "xdg" / "eqa").exists()
