"""Three hosts as Linux network namespaces on one bridge (made and torn down here), for the fleet-across-hosts
test and its longer bench version.

Layout, on a private /24 (``10.221.<n>.0``): ``h1`` = .1, ``h2`` = .2, ``h3`` = .3, and the machine's own
namespace (the test driver, like an operator's laptop) = .254, all on a bridge inside a fourth namespace, so the
machine's own interfaces and routes are never touched apart from one veth. ``partition(host)`` takes a host's
link down, ``heal(host)`` up again.

Each host runs its share of the fleet with ``eqa up --join tls/10.221.<n>.1:7447 --services ...`` (its own
router with the ``router`` certificate, children as clients with their role's certificate) except ``h1``, which
also runs the fleet's router (``eqa router``). Redis runs on ``h2``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PY = sys.executable


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20, check=check)


def why_not() -> str | None:
    """None when namespaces can be made here, else the reason (the test skips with it)."""
    if sys.platform != "linux" or shutil.which("ip") is None:
        return "needs Linux and iproute2 (`ip`)"
    if os.geteuid() != 0:
        return ("needs root (CAP_NET_ADMIN) to make network namespaces: run "
                "`sudo -E .venv/bin/python -m pytest tests/fleet/test_fleet_netns.py` "
                "(docs/deployment.md, Scaling out)")
    probe = f"e21probe{os.getpid() % 100000}"
    try:
        made = _ip("netns", "add", probe, check=False)
        if made.returncode != 0:
            return f"`ip netns add` failed here: {made.stderr.strip()}"
        bridge = _ip("-n", probe, "link", "add", "br0", "type", "bridge", check=False)
        if bridge.returncode != 0:
            return f"no bridge support in this kernel: {bridge.stderr.strip()}"
    finally:
        _ip("netns", "del", probe, check=False)
    for tool in ("redis-server", "openssl"):
        if shutil.which(tool) is None:
            return f"{tool} is not installed"
    return None


@dataclass
class Hosts:
    tag: str = field(default_factory=lambda: f"{os.getpid() % 10000:04d}")
    subnet: int = field(default_factory=lambda: 100 + os.getpid() % 150)
    names: dict[str, str] = field(default_factory=dict)
    procs: list[subprocess.Popen[bytes]] = field(default_factory=list)

    def addr(self, host: str) -> str:
        return f"10.221.{self.subnet}.{ {'h1': 1, 'h2': 2, 'h3': 3, 'driver': 254}[host] }"

    def ns(self, host: str) -> str:
        return self.names[host]

    def dev(self, host: str) -> str:
        return f"e21{self.tag}{host}"

    def create(self) -> Hosts:
        sw = self.names["sw"] = f"eqa21-{self.tag}-sw"
        _ip("netns", "add", sw)
        _ip("-n", sw, "link", "add", "br0", "type", "bridge")
        _ip("-n", sw, "link", "set", "br0", "up")
        for host in ("h1", "h2", "h3", "driver"):
            dev, peer = self.dev(host), f"e21{self.tag}{host}s"
            _ip("link", "add", dev, "type", "veth", "peer", "name", peer)
            _ip("link", "set", peer, "netns", sw)
            _ip("-n", sw, "link", "set", peer, "master", "br0", "up")
            if host == "driver":
                _ip("addr", "add", f"{self.addr(host)}/24", "dev", dev)
                _ip("link", "set", dev, "up")
                continue
            ns = self.names[host] = f"eqa21-{self.tag}-{host}"
            _ip("netns", "add", ns)
            _ip("link", "set", dev, "netns", ns)
            _ip("-n", ns, "addr", "add", f"{self.addr(host)}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        return self

    def partition(self, host: str) -> None:
        _ip("-n", self.ns(host), "link", "set", self.dev(host), "down")

    def heal(self, host: str) -> None:
        _ip("-n", self.ns(host), "link", "set", self.dev(host), "up")

    def run(self, host: str, argv: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
        with open(log, "ab") as out:
            proc = subprocess.Popen(["ip", "netns", "exec", self.ns(host), *argv], env=env, cwd=REPO,
                                    stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append(proc)
        return proc

    def children(self, proc: subprocess.Popen[bytes], module: str) -> list[int]:
        """Pids of the processes started by ``proc`` (an ``eqa up``) that run ``python -m module``."""
        found = []
        for pid in _descendants(proc.pid):
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"-m" in cmd and module.encode() in cmd:
                found.append(pid)
        return found

    def destroy(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 15
        for proc in self.procs:
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)
        _ip("link", "del", self.dev("driver"), check=False)
        for name in self.names.values():
            _ip("netns", "del", name, check=False)


def _descendants(root: int) -> list[int]:
    kids: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        kids.setdefault(ppid, []).append(int(entry))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        for k in kids.get(pid, []):
            out.append(k)
            todo.append(k)
    return out
