"""Merging the per-service ``.rrd`` files of one episode into one recording with the pinned Rerun CLI.

Each service writes ``{data_dir}/recordings/{episode_id}/{service}.rrd`` with the same recording id (the
episode id). Plain concatenation of ``.rrd`` files is not a valid file for rerun 0.41 (``rerun rrd verify``
reports "More than one RRD manifest"), so the gateway runs ``rerun rrd merge`` and caches the result as
``merged.rrd`` until a part changes.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

from eqa.recording import recording_dir
from eqa.settings import SettingsGroup

MERGED = "merged.rrd"
_lock = threading.Lock()


class RecordingError(RuntimeError):
    pass


def rerun_cli() -> str:
    """The ``rerun`` executable of this environment (next to the Python interpreter first)."""
    local = Path(sys.executable).with_name("rerun")
    if local.exists():
        return str(local)
    found = shutil.which("rerun")
    if found is None:
        raise RecordingError("the rerun CLI is not installed (pip install rerun-sdk==0.41.0)")
    return found


def _rrd(*args: str, timeout_s: float) -> subprocess.CompletedProcess[str]:
    """``rerun rrd <args>``, its output captured as text, without telemetry; a failure is the caller's to read."""
    return subprocess.run(
        [rerun_cli(), "rrd", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env={**os.environ, "RERUN_TELEMETRY_ENABLED": "false"},
        check=False,
    )


def parts(settings: SettingsGroup, episode_id: str) -> list[Path]:
    d = recording_dir(settings, episode_id)
    return sorted(p for p in d.glob("*.rrd") if p.name != MERGED and p.stat().st_size > 0) if d.is_dir() else []


def merge(settings: SettingsGroup, episode_id: str, timeout_s: float = 120.0) -> Path:
    """Path of the merged recording of an episode (re-merged when a part is newer than the cache)."""
    files = parts(settings, episode_id)
    if not files:
        raise FileNotFoundError(f"no recording for episode {episode_id}")
    out = recording_dir(settings, episode_id) / MERGED
    with _lock:
        if out.exists() and out.stat().st_mtime >= max(p.stat().st_mtime for p in files):
            return out
        tmp = out.with_suffix(".tmp.rrd")
        proc = _rrd("merge", "--continue-on-error", *map(str, files), "-o", str(tmp), timeout_s=timeout_s)
        if proc.returncode != 0 or not tmp.exists():
            tmp.unlink(missing_ok=True)
            raise RecordingError(f"rerun rrd merge failed: {proc.stderr.strip()[-500:]}")
        tmp.replace(out)
    return out


def verify(path: Path, timeout_s: float = 120.0) -> tuple[bool, str]:
    """``rerun rrd verify``: (ok, message)."""
    proc = _rrd("verify", str(path), timeout_s=timeout_s)
    return proc.returncode == 0, (proc.stdout + proc.stderr).strip()


def entity_paths(path: Path, timeout_s: float = 120.0) -> set[str]:
    """Entity paths that hold data in a recording (from ``rerun rrd print``)."""
    proc = _rrd("print", str(path), timeout_s=timeout_s)
    if proc.returncode != 0:
        raise RecordingError(f"rerun rrd print failed: {proc.stderr.strip()[-500:]}")
    found = set()
    for line in proc.stdout.splitlines():
        # "Chunk(chunk_...) with 3 rows (2.3 KiB) - /world/sim/pts - data columns: [...]"
        if line.startswith("Chunk(") and " - /" in line:
            found.add(line.split(" - ")[1].strip())
    return found
