"""Restarting the gateway process (SIGKILL) while an episode runs: no episode and no stored event is lost,
a client resuming with Last-Event-ID gets every event exactly once, and an end missed while the gateway was
down is turned into a stated failure by the watchdog. Real HTTP, real Redis, real Zenoh; the services'
side is the scripted fleet (move to the real fleet once it runs end to end)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest

from eqa.settings import Settings
from eqa.store import RedisStore
from gateway.harness import GatewayProcess, sse_events
from gateway.scripted_fleet import FleetScript, ScriptedFleet

TOKEN = "restart-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
CHOICES = [f"room {i}" for i in range(8)]  # the scripted stopper needs 8 steps to get down to one letter


@pytest.fixture
def gw_settings(settings: Settings, redis_url: str) -> Settings:
    with RedisStore(redis_url) as s:
        s._r.flushdb()  # type: ignore[attr-defined]
    return settings.model_copy(
        update={"redis_url": redis_url, "api_tokens": [TOKEN], "rate_limit_per_s": 1000.0, "episode_timeout_s": 30.0}
    )


def _wait(pred, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return False


def _key(i: str) -> tuple[int, int]:
    a, b = i.split("-")
    return int(a), int(b)


def test_restart_mid_episode_and_resume_stream(gw_settings: Settings, hub_settings: Settings, tmp_path: Path) -> None:
    gate = threading.Event()
    with ScriptedFleet(hub_settings, FleetScript(step_delay_s=0.15, end_gate=gate)):
        gw = GatewayProcess(gw_settings, log_path=tmp_path / "gateway.log").start()
        try:
            with httpx.Client(base_url=gw.url, headers=AUTH, timeout=30) as c:
                assert _wait(lambda: c.get("/v1/ready").status_code == 200)
                eid = c.post(
                    "/v1/questions",
                    json={"question": "Where is the cat?", "choices": CHOICES, "scene": "house-2", "max_steps": 20},
                ).json()["episode_id"]
                first = list(sse_events(c, f"/v1/episodes/{eid}/events", limit=6))
                assert [e["kind"] for _, e in first][:2] == ["episode_start", "frame"]
            gw.kill()  # crash while the episode runs
            gw.start()
            with httpx.Client(base_url=gw.url, headers=AUTH, timeout=30) as c:
                st = c.get(f"/v1/episodes/{eid}").json()
                assert st["state"] == "running"  # the episode survived the crash
                gate.set()
                rest = list(sse_events(c, f"/v1/episodes/{eid}/events", last_event_id=first[-1][0]))
                full = list(sse_events(c, f"/v1/episodes/{eid}/events"))
                st = c.get(f"/v1/episodes/{eid}").json()
        finally:
            gw.stop()
    got = [i for i, _ in first + rest]
    assert got == [i for i, _ in full]  # every stored event, once, in order
    assert len(set(got)) == len(got) and got == sorted(got, key=_key)
    kinds = [e["kind"] for _, e in rest]
    assert "gateway_restart" in kinds and kinds[-1] == "episode_end"
    assert st["state"] == "stopped" and st["answer"] == "A" and st["prediction_set"] == ["A"]


@pytest.mark.parametrize("stored_end", [True, False], ids=["end-stored-by-stopper", "no-stored-end"])
def test_end_missed_while_down(gw_settings: Settings, hub_settings: Settings, tmp_path: Path, stored_end: bool) -> None:
    """The EpisodeEnd goes out while no gateway listens. With the stopper's stored copy the restarted gateway
    ends the episode with the stopper's answer; without it the watchdog fails it with a stated reason."""
    gate = threading.Event()
    s = gw_settings.model_copy(update={"episode_timeout_s": 1.0})
    store = RedisStore(gw_settings.redis_url or "") if stored_end else None
    with ScriptedFleet(hub_settings, FleetScript(step_delay_s=0.02, end_gate=gate), store=store):
        gw = GatewayProcess(s, log_path=tmp_path / "gateway.log").start()
        try:
            with httpx.Client(base_url=gw.url, headers=AUTH, timeout=30) as c:
                assert _wait(lambda: c.get("/v1/ready").status_code == 200)
                body = {"question": "Is the tv on?", "choices": ["yes", "no"], "scene": "house-3", "max_steps": 20}
                eid = c.post("/v1/questions", json=body).json()["episode_id"]
                assert _wait(lambda: c.get(f"/v1/episodes/{eid}").json()["step"] >= 1)
            gw.kill()
            gate.set()  # the stopper's EpisodeEnd goes out while no gateway listens
            time.sleep(0.3)
            gw.start()
            with httpx.Client(base_url=gw.url, headers=AUTH, timeout=30) as c:
                assert _wait(lambda: c.get(f"/v1/episodes/{eid}").json()["state"] in ("failed", "stopped"), 15)
                st = c.get(f"/v1/episodes/{eid}").json()
                events = list(sse_events(c, f"/v1/episodes/{eid}/events"))
        finally:
            gw.stop()
            if store is not None:
                store.close()
    last = events[-1][1]
    assert last["kind"] == "episode_end" and [e["kind"] for _, e in events].count("episode_end") == 1
    if stored_end:
        assert st["state"] == "stopped" and st["answer"] == "A" and st["stop_reason"] == "one answer left"
        assert "recovered" in last
    else:
        assert st["state"] == "failed" and last["state"] == "failed"
        assert "no message for 1 s" in st["stop_reason"] and "gateway restarted" in st["stop_reason"]


def test_stopper_end_key_matches_the_stopper() -> None:
    from gateway.manager import STOPPER_END_PREFIX
    from services.stopper.service import END_PREFIX

    assert END_PREFIX == STOPPER_END_PREFIX
