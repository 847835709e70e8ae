"""A killed launcher leaves no orphaned services (EQA_PARENT_PID): its children stop on their own.

Seen before: interrupting ``eqa bench explore`` (fleet runner) left the five services running, because each
child runs in its own session (so a Ctrl-C in a terminal does not kill them before the launcher stops them).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

SCRIPT = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from eqa.launcher import Fleet, free_port
    from eqa.settings import Settings
    data = Path(sys.argv[1])
    settings = Settings(data_dir=data, zenoh_listen=[], zenoh_connect=[], record=False, gateway_port=free_port())
    fleet = Fleet(settings, services=["planner", "stopper", "gateway"], scorers=0)
    fleet.start()
    print(" ".join(str(c.proc.pid) for c in fleet.children), flush=True)
    time.sleep(600)
    """
)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (not reaped yet) counts as gone
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().split(") ")[-1][:1] != "Z"


def test_services_exit_when_their_launcher_is_killed(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        pids = [int(p) for p in line.split()]
        assert len(pids) == 3, f"launcher printed {line!r}; logs in {tmp_path / 'logs'}"
        assert all(_alive(p) for p in pids)
        proc.send_signal(signal.SIGKILL)  # no cleanup at all in the launcher
        proc.wait(timeout=10)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and any(_alive(p) for p in pids):
            time.sleep(0.2)
        left = [p for p in pids if _alive(p)]
        assert not left, f"orphaned services still running: {left}"
    finally:
        if proc.poll() is None:
            proc.kill()
        for p in pids if "pids" in locals() else []:
            if _alive(p):
                os.killpg(p, signal.SIGKILL)
