"""Where Prometheus' ``promtool`` is: on ``PATH``, or in the virtualenv's bin, where scripts/setup.sh puts the
binary it takes out of Debian's ``prometheus`` package (installing the package would also start a server)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

SKIP_REASON = "promtool is not installed: scripts/setup.sh (make setup) puts it in the venv's bin from Debian's " \
    "prometheus package (apt-get download prometheus)"


def promtool() -> str | None:
    found = shutil.which("promtool")
    if found is not None:
        return found
    beside = Path(sys.executable).parent / "promtool"
    return str(beside) if beside.is_file() else None
