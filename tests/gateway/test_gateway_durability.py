"""The store going away under the gateway (a real redis-server on a free port that the test stops, kills and
starts again): status answers 503 while it is away, never 404; with Redis' append-only file (the compose
settings, docs/durability.md) nothing stored is lost across a restart or a kill -9; a Redis that comes back
empty (no persistence) is reported as lost data (503), not as episodes that never existed.

The gateway runs in this process with no services (episodes it starts stay "running").
"""

from __future__ import annotations

import shutil
import signal
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from support.fleet import GatewayThread, tenant_gateway_settings, wait_for
from support.gateway import A, Q

from eqa.launcher import free_port
from eqa.store import RedisStore
from gateway.manager import ev_key

PERSISTENT = ["--appendonly", "yes", "--appendfsync", "always"]  # docker-compose*.yml's redis
EPHEMERAL = ["--appendonly", "no", "--save", ""]


class Redis:
    def __init__(self, workdir: Path) -> None:
        self.port = free_port()
        self.workdir = workdir
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, persistence: list[str], workdir: Path | None = None) -> None:
        exe = shutil.which("redis-server")
        assert exe, "redis-server is not installed"
        self.proc = subprocess.Popen([exe, "--port", str(self.port), "--bind", "127.0.0.1", *persistence,
                                      "--dir", str(workdir or self.workdir)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        assert wait_for(lambda: socket.socket().connect_ex(("127.0.0.1", self.port)) == 0, 10)

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=10)
            self.proc = None


@pytest.fixture
def redis(tmp_path: Path) -> Iterator[Redis]:
    r = Redis(tmp_path / "redis")
    r.workdir.mkdir()
    r.start(PERSISTENT)
    try:
        yield r
    finally:
        r.stop(signal.SIGKILL)


def _status(c: httpx.Client, eid: str) -> int:
    return c.get(f"/v1/episodes/{eid}", headers=A).status_code


def test_status_is_503_while_redis_restarts_and_nothing_is_lost(tmp_path: Path, redis: Redis) -> None:
    s = tenant_gateway_settings(tmp_path, redis_url=redis.url, queue_max_per_robot=10, queue_max_per_token=10)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
        ended = []
        for _ in range(3):
            eid = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
            assert c.delete(f"/v1/episodes/{eid}", headers=A).json()["state"] == "cancelled"
            ended.append(eid)
        running = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
        with RedisStore(redis.url) as store:
            events_before = {e: store.stream_len(ev_key(e)) for e in [*ended, running]}
        assert all(events_before.values()), events_before

        redis.stop()  # a clean shutdown (restart of the container)
        assert _status(c, ended[0]) == 503 and _status(c, "ep-never") == 503  # away: 503, never 404
        r = c.get(f"/v1/episodes/{ended[0]}", headers=A)
        assert int(r.headers["retry-after"]) >= 1 and "store is unavailable" in r.json()["detail"]
        assert _status(c, running) == 200  # a running episode's status comes from memory
        redis.start(PERSISTENT)
        assert wait_for(lambda: _status(c, ended[0]) == 200, 15)
        assert c.get(f"/v1/episodes/{ended[0]}", headers=A).json()["state"] == "cancelled"
        assert _status(c, "ep-never") == 404  # back: an episode that never existed is 404 again

        redis.stop(signal.SIGKILL)  # a crash: the append-only file has every acknowledged write
        assert _status(c, ended[1]) == 503
        redis.start(PERSISTENT)
        assert wait_for(lambda: _status(c, ended[1]) == 200, 15)
        with RedisStore(redis.url) as store:
            events_after = {e: store.stream_len(ev_key(e)) for e in [*ended, running]}
        assert events_after == events_before  # no event lost

        redis.stop(signal.SIGKILL)  # back without persistence: the data is gone, and the gateway says so
        empty = tmp_path / "empty"
        empty.mkdir()
        redis.start(EPHEMERAL, workdir=empty)
        r = c.get(f"/v1/episodes/{ended[2]}", headers=A)
        assert r.status_code == 503 and "lost" in r.json()["detail"], r.text


def test_compose_files_run_redis_with_the_documented_persistence() -> None:
    root = Path(__file__).resolve().parents[2]
    for name in ("docker-compose.yml", "docker-compose.fleet.yml", "docker-compose.podman.yml"):
        text = (root / name).read_text()
        command = next(line for line in text.splitlines() if '["redis-server"' in line)
        assert '"--appendonly", "yes", "--appendfsync", "always"' in command, (name, command)
    assert "--appendfsync always" in (root / "docs" / "durability.md").read_text()
