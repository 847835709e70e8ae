"""Running the gateway on a free loopback port, in a thread or as a ``python -m gateway`` process, next to a
fleet of real services started by :class:`eqa.launcher.Fleet`; a small SSE client. Used by the gateway
tests and ``eqa_app/benches/gateway.py``."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import uvicorn

from eqa.launcher import free_port
from eqa.messages import EpisodeEnd
from eqa.settings import Settings
from eqa.store import episode_end_key, open_store
from gateway.app import create_app
from gateway.cli import uvicorn_options
from services.sim.library import floor_area
from support.gateway import TOKENS

if TYPE_CHECKING:
    from eqa.launcher import Fleet


def fleet_settings(data_dir: Path, redis_url: str | None = None, **update: Any) -> Settings:
    """Settings of a small pipeline fleet for tests and benches: 160x120 images, no recording, multicast
    scouting off, the launcher's router on a free loopback port (``zenoh_listen`` empty). Services and
    gateway share ``redis_url`` (the stopper's stored ``EpisodeEnd`` is read by a restarted gateway)."""
    base: dict[str, Any] = {
        "data_dir": Path(data_dir),
        "redis_url": redis_url,
        "zenoh_mode": "peer",
        "zenoh_listen": [],
        "zenoh_connect": [],
        "zenoh_multicast": False,
        "sim_width": 160,
        "sim_height": 120,
        "record": False,
    }
    return Settings(**{**base, **update})


def lone_gateway_settings(data_dir: Path, tokens: list[str], **update: Any) -> Settings:
    """Settings of a gateway run without a fleet (API, auth and limits tests): its own Zenoh port on loopback,
    multicast scouting off, no recording, ``tokens``, 1000 requests/s per token unless ``update`` says else."""
    base: dict[str, Any] = {
        "data_dir": Path(data_dir),
        "zenoh_mode": "peer",
        "zenoh_listen": [f"tcp/127.0.0.1:{free_port()}"],
        "zenoh_connect": [],
        "zenoh_multicast": False,
        "record": False,
        "api_tokens": tokens,
        "rate_limit_per_s": 1000.0,
    }
    return Settings(**{**base, **update})


def tenant_gateway_settings(tmp: Path, **update: Any) -> Settings:
    """A fleet-less gateway with the four tenants of ``support.gateway.TOKENS`` (two submitters, an admin, a
    reader) and an episode timeout long enough that its episodes, which nothing runs, stay "running"."""
    return lone_gateway_settings(tmp / "var", TOKENS, **{"episode_timeout_s": 3600.0, **update})


def clear_gateway_state(settings: Settings) -> int:
    """Delete the gateway's records (``gw:*``: episodes, event streams, robot locks, queues) from the store of
    ``settings``, leaving the services' keys alone; returns how many keys went."""
    with open_store(settings) as store:
        found = store.keys("gw:")
        for key in found:
            store.delete(key)
    return len(found)


def wait_for(pred: Callable[[], bool], timeout: float = 30.0, every: float = 0.05) -> bool:
    """Poll ``pred`` until it is true (True) or ``timeout`` seconds passed (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(every)
    return bool(pred())


def stored_end(settings: Settings, episode_id: str) -> EpisodeEnd | None:
    """The ``EpisodeEnd`` the stopper stored for an episode (it stores it before it publishes it), if any."""
    with open_store(settings) as store:
        raw = store.get(episode_end_key(episode_id))
    return None if raw is None else EpisodeEnd.model_validate_json(raw)


@contextlib.contextmanager
def paused(fleet: Fleet, service: str, index: int = 0) -> Iterator[None]:
    """SIGSTOP one service process of ``fleet`` (it holds its state and its connections but does nothing),
    SIGCONT it on exit. Keep the pause well under Zenoh's 10 s lease, or the peers drop its session."""
    child = fleet.child(service, index)
    if child.proc is None or child.proc.poll() is not None:
        raise RuntimeError(f"{service} is not running")
    pgid = child.proc.pid  # the launcher starts each child in its own session: pid == process group
    os.killpg(pgid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.killpg(pgid, signal.SIGCONT)


def wait_ready(url: str, timeout: float = 30.0, proc: subprocess.Popen[bytes] | None = None) -> None:
    """Wait until ``GET /v1/health`` answers 200."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"gateway process exited with {proc.returncode}")
        try:
            if httpx.get(f"{url}/v1/health", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.05)
    raise TimeoutError(f"gateway at {url} not up after {timeout} s")


class GatewayThread:
    """uvicorn serving :func:`create_app` in a background thread (context manager)."""

    def __init__(self, settings: Settings, port: int | None = None) -> None:
        self.port = port or free_port()
        self.settings = settings.model_copy(update={"gateway_host": "127.0.0.1", "gateway_port": self.port})
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(
            create_app(self.settings, scene_area=floor_area),
            log_level="warning",
            lifespan="on",
            **uvicorn_options(self.settings),
        )
        self.server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self.server.run, name="gateway-uvicorn", daemon=True)

    def __enter__(self) -> GatewayThread:
        self._thread.start()
        wait_ready(self.url)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self._thread.join(timeout=15)

    def crash(self) -> None:
        """Stop at once as a killed process would: every open connection is aborted (its clients see the
        drop now), then the server exits without a graceful shutdown. uvicorn's own shutdown leaves a
        response still streaming (an event stream) open, and its socket lingers until garbage collection."""
        for conn in list(self.server.server_state.connections):
            transport = getattr(conn, "transport", None)
            if transport is not None:
                conn.loop.call_soon_threadsafe(transport.abort)
        self.server.force_exit = True
        self.__exit__(None, None, None)


class GatewayProcess:
    """``python -m gateway`` as a child process with the settings as ``EQA_*`` variables."""

    def __init__(self, settings: Settings, port: int | None = None, log_path: Path | None = None) -> None:
        self.port = port or free_port()
        self.settings = settings.model_copy(update={"gateway_host": "127.0.0.1", "gateway_port": self.port})
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None
        self._n = 0

    def start(self) -> GatewayProcess:
        self._n += 1
        env = {**os.environ, **self.settings.env(), "EQA_INSTANCE": f"gw-{os.getpid()}-{self._n}"}
        out = open(self.log_path, "ab") if self.log_path else subprocess.DEVNULL  # noqa: SIM115
        self.proc = subprocess.Popen([sys.executable, "-m", "gateway"], env=env, stdout=out, stderr=out)
        try:
            wait_ready(self.url, timeout=120.0, proc=self.proc)  # a process start imports much: slow when loaded
        except BaseException:
            self.kill()  # a gateway that never answered is not left running after the test
            raise
        return self

    def kill(self) -> None:
        """SIGKILL: no graceful shutdown, as in a crash."""
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(timeout=10)
            self.proc = None

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
            self.proc = None

    def __enter__(self) -> GatewayProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def sse_events(
    client: httpx.Client,
    path: str,
    last_event_id: str | None = None,
    limit: int | None = None,
    timeout: float = 30.0,
) -> Iterator[tuple[str, dict[str, Any]]]:
    """``(id, data)`` of each event of an SSE stream, until it closes or ``limit`` events were read."""
    headers = {"Last-Event-ID": last_event_id} if last_event_id else {}
    n = 0
    with client.stream("GET", path, headers=headers, timeout=timeout) as r:
        r.raise_for_status()
        eid: str | None = None
        data: list[str] = []
        for line in r.iter_lines():
            if line.startswith("id: "):
                eid = line[4:]
            elif line.startswith("data: "):
                data.append(line[6:])
            elif line == "" and data:
                yield eid or "", json.loads("\n".join(data))
                n += 1
                eid, data = None, []
                if limit is not None and n >= limit:
                    return
