"""Shared fixtures: free ports, a private redis-server, real Zenoh settings on loopback, both stores, and the
gateway tests' fleet."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

from support.fleet import clear_gateway_state, fleet_settings
from support.gateway import SCENE, TOKEN

from eqa.launcher import Fleet, free_port
from eqa.settings import SettingOutsideGroupsError, Settings, SettingsView
from eqa.store import EmbeddedStore, RedisStore, Store

REPO = Path(__file__).resolve().parents[1]


def wait_port(port: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port}")


@pytest.fixture(autouse=True)
def settings_outside_groups(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """Every test fails when a component read a setting outside the groups it declares (eqa.settings.view), also
    where the AttributeError was caught on the way (a handler's error is logged, a getattr has a default). A test
    that reads one on purpose clears the list it yields."""
    outside: list[str] = []
    read = SettingsView.__getattr__

    def recording(self: SettingsView, name: str) -> object:
        try:
            return read(self, name)
        except SettingOutsideGroupsError as exc:
            outside.append(str(exc))
            raise

    monkeypatch.setattr(SettingsView, "__getattr__", recording)
    yield outside
    assert not outside, f"settings read outside the groups declared: {sorted(set(outside))}"


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A private redis-server on a free port for this test session (never the machine's shared one)."""
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.fail("redis-server is not installed: run `make test` (it installs it) or apt-get install redis-server")
    port = free_port()
    workdir = tmp_path_factory.mktemp("redis")
    proc = subprocess.Popen(
        [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no", "--dir", str(workdir)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_port(port)
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.fixture
def zenoh_port() -> int:
    return free_port()


@pytest.fixture
def settings(tmp_path: Path, zenoh_port: int) -> Settings:
    """Settings for one test: a private data dir and a private Zenoh 'hub' port.

    The first bus opened with ``hub_settings`` listens on the port; every other one (``settings``) connects
    to it. Multicast scouting is off, so tests never see each other's traffic.
    """
    return Settings(
        data_dir=tmp_path / "var",
        zenoh_mode="peer",
        zenoh_listen=["tcp/127.0.0.1:0"],
        zenoh_connect=[f"tcp/127.0.0.1:{zenoh_port}"],
        zenoh_multicast=False,
        record=False,
        sim_width=160,
        sim_height=120,
    )


@pytest.fixture
def hub_settings(settings: Settings, zenoh_port: int) -> Settings:
    """The same as ``settings`` but listening on the hub port (open one Bus with it first)."""
    return settings.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{zenoh_port}"], "zenoh_connect": []})


@pytest.fixture(params=["embedded", "redis"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Store]:
    """Each store test runs against both backends."""
    if request.param == "embedded":
        s: Store = EmbeddedStore(tmp_path / "store.sqlite")
    else:
        url = request.getfixturevalue("redis_url")
        s = RedisStore(url)
        s._r.flushdb()  # type: ignore[attr-defined]
    try:
        yield s
    finally:
        s.close()


# ---- the gateway tests: one fleet per test module (real services over Zenoh, real Redis) ----------


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[Fleet]:
    from services.sim.library import load_or_generate

    s = fleet_settings(tmp_path_factory.mktemp("gw-fleet"), redis_url)
    load_or_generate(SCENE, s.scenes_path)  # made once, before the sim and the gateway both want it
    with Fleet(s, scorers=1, restart=False) as f:
        yield f


@pytest.fixture
def gw_settings(fleet: Fleet) -> Settings:
    s = fleet.client_settings().model_copy(
        update={"api_tokens": [TOKEN], "rate_limit_per_s": 1000.0, "episode_timeout_s": 60.0}
    )
    clear_gateway_state(s)
    return s
