"""The gateway through real HTTP (uvicorn on a free port) with a real Redis and real Zenoh.

The services' side is played by :class:`gateway.scripted_fleet.ScriptedFleet` (real messages over real
Zenoh) until the real services run end to end; ``test_recording_fleet.py`` holds the full-fleet test.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import httpx
import pytest

from eqa.settings import Settings
from eqa.store import RedisStore
from gateway.harness import GatewayThread, sse_events
from gateway.scripted_fleet import FleetScript, ScriptedFleet

TOKEN = "test-token-1"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
Q = {
    "question": "Where is the black suitcase?",
    "choices": ["bedroom", "hallway", "storage room", "living room"],
    "scene": "house-1",
    "max_steps": 10,
}


@pytest.fixture
def gw_settings(settings: Settings, redis_url: str) -> Settings:
    with RedisStore(redis_url) as s:
        s._r.flushdb()  # type: ignore[attr-defined]
    return settings.model_copy(
        update={
            "redis_url": redis_url,
            "api_tokens": [TOKEN],
            "rate_limit_per_s": 1000.0,
            "episode_timeout_s": 10.0,
        }
    )


def wait_for(pred, timeout: float = 10.0, every: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(every)
    return False


def client_for(gw: GatewayThread) -> httpx.Client:
    return httpx.Client(base_url=gw.url, headers=AUTH, timeout=30)


def ready(c: httpx.Client) -> bool:
    return c.get("/v1/ready").status_code == 200


@pytest.fixture
def running(
    gw_settings: Settings, hub_settings: Settings
) -> Iterator[tuple[ScriptedFleet, GatewayThread, httpx.Client]]:
    with (
        ScriptedFleet(hub_settings.model_copy(update={"redis_url": gw_settings.redis_url})) as fleet,
        GatewayThread(gw_settings) as gw,
        client_for(gw) as c,
    ):
        assert wait_for(lambda: ready(c)), c.get("/v1/ready").text
        yield fleet, gw, c


def test_submit_stream_and_result(running) -> None:
    _fleet, _gw, c = running
    r = c.post("/v1/questions", json=Q)
    assert r.status_code == 202, r.text
    sub = r.json()
    assert sub["state"] == "running" and sub["robot"] == "robot0" and sub["max_steps"] == 10
    eid = sub["episode_id"]
    events = list(sse_events(c, f"/v1/episodes/{eid}/events"))
    kinds = [e["kind"] for _, e in events]
    assert kinds[0] == "episode_start" and kinds[-1] == "episode_end" and kinds.count("episode_end") == 1
    assert {"frame", "map_update", "step_scores", "decision", "goal"} <= set(kinds)
    ids = [i for i, _ in events]
    assert len(set(ids)) == len(ids) and ids == sorted(ids, key=lambda s: tuple(map(int, s.split("-"))))
    frame = next(e for _, e in events if e["kind"] == "frame")
    assert frame["episode_id"] == eid and frame["step"] == 0 and "rgb" not in frame and "b64" not in str(frame)
    st = c.get(f"/v1/episodes/{eid}").json()
    # 4 choices: the scripted stopper drops one letter per step from step 1 -> one left at step 3.
    assert st["state"] == "stopped" and st["answer"] == "A" and st["answer_text"] == "bedroom"
    assert st["prediction_set"] == ["A"] and st["steps"] == 4 and st["normalized_steps"] == pytest.approx(0.4)
    assert st["stop_reason"] == "one answer left"
    listed = c.get("/v1/episodes").json()["episodes"]
    assert [e["episode_id"] for e in listed] == [eid]
    assert c.get("/v1/episodes", params={"state": "running"}).json()["episodes"] == []
    # A finished stream replays from any point and then closes.
    tail = list(sse_events(c, f"/v1/episodes/{eid}/events", last_event_id=ids[-3]))
    assert [i for i, _ in tail] == ids[-2:]


def test_auth_and_rate_limit(gw_settings: Settings, hub_settings: Settings) -> None:
    s = gw_settings.model_copy(update={"rate_limit_per_s": 3.0, "api_tokens": [TOKEN, "second-token"]})
    with ScriptedFleet(hub_settings), GatewayThread(s) as gw, httpx.Client(base_url=gw.url, timeout=10) as c:
        assert c.get("/v1/health").status_code == 200
        assert c.get("/v1/ready").status_code in (200, 503)
        for method, path in [
            ("POST", "/v1/questions"),
            ("GET", "/v1/episodes"),
            ("GET", "/v1/episodes/ep-x"),
            ("DELETE", "/v1/episodes/ep-x"),
            ("GET", "/v1/episodes/ep-x/events"),
            ("GET", "/v1/episodes/ep-x/recording"),
        ]:
            r = c.request(method, path, json=Q if method == "POST" else None)
            assert r.status_code == 401, (method, path, r.text)
            assert r.headers["www-authenticate"] == "Bearer"
            r = c.request(method, path, headers={"Authorization": "Bearer wrong"})
            assert r.status_code == 401 and r.json()["detail"] == "invalid bearer token"
        responses = [c.get("/v1/episodes/ep-none", headers=AUTH) for _ in range(8)]
        codes = [r.status_code for r in responses]
        assert codes[0] == 404 and 429 in codes, codes
        limited = next(r for r in responses if r.status_code == 429)
        assert int(limited.headers["retry-after"]) >= 1 and "rate limit of 3 requests/s" in limited.json()["detail"]
        other = c.get("/v1/episodes/ep-none", headers={"Authorization": "Bearer second-token"})
        assert other.status_code == 404  # the limit is per token


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({k: v for k, v in Q.items() if k != "question"}, "question"),
        ({**Q, "choices": ["only one"]}, "choices"),
        ({**Q, "choices": [f"c{i}" for i in range(27)]}, "choices"),
        ({**Q, "eps": 1.5}, "eps"),
        ({**Q, "strategy": "teleport"}, "strategy"),
        ({**Q, "question": "x" * 1_000_000}, "question"),
        ({**Q, "max_steps": 0}, "max_steps"),
        ({**Q, "start_pose": {"x": "nan", "y": 0}}, "start_pose"),
        ({**Q, "robot": "no/such robot"}, "robot"),
        ({**Q, "robot": "robot9"}, "robot"),
    ],
)
def test_invalid_bodies_give_field_level_422(running, body: dict, field: str) -> None:
    _fleet, _gw, c = running
    r = c.post("/v1/questions", json=body)
    assert r.status_code == 422, r.text[:300]
    assert len(r.content) < 10_000  # the 1 MB input is not echoed back
    detail = r.json()["detail"]
    assert any(field in [str(p) for p in d["loc"]] for d in detail), detail
    assert all(d["msg"] for d in detail)


def test_needs_scene_or_robot(running) -> None:
    _fleet, _gw, c = running
    r = c.post("/v1/questions", json={"question": "Is the stove on?"})
    assert r.status_code == 422 and "scene, a robot id" in r.text
    assert (
        c.post("/v1/questions", content=b"{not json", headers={"Content-Type": "application/json"}).status_code == 422
    )
    assert c.get("/v1/episodes/bad*id").status_code == 422
    assert c.get("/v1/episodes/ep-none/events", headers={"Last-Event-ID": "yesterday"}).status_code == 422


def test_busy_robot_queue_then_run(gw_settings: Settings, hub_settings: Settings) -> None:
    gate = __import__("threading").Event()
    with (
        ScriptedFleet(hub_settings, FleetScript(end_gate=gate)),
        GatewayThread(gw_settings) as gw,
        client_for(gw) as c,
    ):
        assert wait_for(lambda: ready(c))
        first = c.post("/v1/questions", json=Q).json()
        dropped = c.post("/v1/questions", json=Q).json()
        second = c.post("/v1/questions", json=Q).json()
        assert first["state"] == "running" and dropped["state"] == "queued" and dropped["queue_position"] == 1
        assert second["state"] == "queued" and second["queue_position"] == 2
        # Cancelling a queued episode does not start the next one on the busy robot.
        assert c.delete(f"/v1/episodes/{dropped['episode_id']}").json()["state"] == "cancelled"
        assert c.get(f"/v1/episodes/{second['episode_id']}").json()["state"] == "queued"
        assert c.get("/v1/ready").json()["robots"] == {"robot0": first["episode_id"]}
        assert "gateway" in c.get("/v1/ready").json()["services"]  # the gateway's own liveliness token
        assert c.get(f"/v1/episodes/{second['episode_id']}").json()["state"] == "queued"
        gate.set()
        assert wait_for(lambda: c.get(f"/v1/episodes/{second['episode_id']}").json()["state"] == "stopped", 15)
        assert c.get(f"/v1/episodes/{first['episode_id']}").json()["state"] == "stopped"
        evs = [e["kind"] for _, e in sse_events(c, f"/v1/episodes/{second['episode_id']}/events")]
        assert evs[0] == "queued" and evs[1] == "episode_start" and evs[-1] == "episode_end"


def test_busy_robot_refused_and_two_robots(gw_settings: Settings, hub_settings: Settings) -> None:
    gate = __import__("threading").Event()
    s = gw_settings.model_copy(update={"busy_policy": "refuse", "robots": ["r1", "r2"]})
    with ScriptedFleet(hub_settings, FleetScript(end_gate=gate)), GatewayThread(s) as gw, client_for(gw) as c:
        assert wait_for(lambda: ready(c))
        a = c.post("/v1/questions", json=Q).json()
        b = c.post("/v1/questions", json=Q).json()
        assert {a["robot"], b["robot"]} == {"r1", "r2"} and a["state"] == b["state"] == "running"
        r = c.post("/v1/questions", json=Q)
        assert r.status_code == 409 and "busy" in r.json()["detail"] and "refuse" in r.json()["detail"]
        r = c.post("/v1/questions", json={**Q, "robot": "r1"})
        assert r.status_code == 409
        gate.set()
        for e in (a, b):
            assert wait_for(lambda e=e: c.get(f"/v1/episodes/{e['episode_id']}").json()["state"] == "stopped", 15)
        assert c.post("/v1/questions", json={**Q, "robot": "r2"}).json()["robot"] == "r2"


def test_cancel(running) -> None:
    fleet, _gw, c = running
    gate = __import__("threading").Event()
    fleet.script.end_gate = gate
    eid = c.post("/v1/questions", json=Q).json()["episode_id"]
    assert wait_for(lambda: c.get(f"/v1/episodes/{eid}").json()["step"] >= 1)
    r = c.delete(f"/v1/episodes/{eid}")
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    assert wait_for(lambda: eid in fleet._cancelled)  # the services got EpisodeCancel over Zenoh
    assert c.delete(f"/v1/episodes/{eid}").status_code == 409
    assert c.delete("/v1/episodes/ep-none").status_code == 404
    last = list(sse_events(c, f"/v1/episodes/{eid}/events"))[-1][1]
    assert last["kind"] == "episode_end" and last["state"] == "cancelled"
    gate.set()


def test_watchdog_names_dead_services_and_sim_refusal(gw_settings: Settings, hub_settings: Settings) -> None:
    s = gw_settings.model_copy(update={"episode_timeout_s": 0.8})
    with ScriptedFleet(hub_settings) as fleet, GatewayThread(s) as gw, client_for(gw) as c:
        assert wait_for(lambda: ready(c))
        fleet.drop_service("planner")
        assert wait_for(lambda: c.get("/v1/ready").json()["missing"] == ["planner"])
        assert c.get("/v1/ready").status_code == 503
        eid = c.post("/v1/questions", json={**Q, "scene": "silent"}).json()["episode_id"]
        assert wait_for(lambda: c.get(f"/v1/episodes/{eid}").json()["state"] == "failed", 10)
        reason = c.get(f"/v1/episodes/{eid}").json()["stop_reason"]
        assert "no message for 0.8 s" in reason and "planner" in reason and "sim" not in reason.split(":")[-1]
        eid = c.post("/v1/questions", json={**Q, "scene": "missing"}).json()["episode_id"]
        assert wait_for(lambda: c.get(f"/v1/episodes/{eid}").json()["state"] == "failed", 10)
        assert "sim refused the episode: unknown scene 'missing'" in c.get(f"/v1/episodes/{eid}").json()["stop_reason"]


def test_openapi_examples_and_cors(gw_settings: Settings, hub_settings: Settings) -> None:
    with GatewayThread(gw_settings) as gw, httpx.Client(base_url=gw.url) as c:
        spec = c.get("/openapi.json").json()
        schema = spec["components"]["schemas"]["QuestionRequest"]
        assert schema["examples"][0]["question"]
        assert "/v1/episodes/{episode_id}/events" in spec["paths"]
        r = c.options("/v1/episodes", headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "GET"})
        assert "access-control-allow-origin" not in r.headers
    s = gw_settings.model_copy(update={"cors_origins": ["http://ui.example"]})
    with GatewayThread(s) as gw, httpx.Client(base_url=gw.url) as c:
        r = c.options("/v1/episodes", headers={"Origin": "http://ui.example", "Access-Control-Request-Method": "GET"})
        assert r.headers["access-control-allow-origin"] == "http://ui.example"


def test_step_budget_from_scene_area(running) -> None:
    from services.sim.scene import load_or_generate

    _fleet, gw, c = running
    area = load_or_generate("gen-00001", gw.settings.scenes_path).floor_area_m2
    r = c.post("/v1/questions", json={"question": "Is the oven on?", "scene": "gen-00001"})
    assert r.status_code == 202 and r.json()["max_steps"] == int(3 * area**0.5)
    r = c.post("/v1/questions", json={"question": "Is the oven on?", "scene": "no-such-scene"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "scene"]
    assert "unknown scene" in r.json()["detail"][0]["msg"]


def test_embedded_store_without_redis(settings: Settings, hub_settings: Settings) -> None:
    """With no EQA_REDIS_URL the same gateway runs on the embedded SQLite store."""
    with ScriptedFleet(hub_settings), GatewayThread(settings) as gw, httpx.Client(base_url=gw.url, timeout=30) as c:
        assert wait_for(lambda: ready(c))
        eid = c.post("/v1/questions", json=Q).json()["episode_id"]
        kinds = [e["kind"] for _, e in sse_events(c, f"/v1/episodes/{eid}/events")]
        assert kinds[0] == "episode_start" and kinds[-1] == "episode_end"
        assert c.get(f"/v1/episodes/{eid}").json()["state"] == "stopped"
    assert (settings.data_dir / "store.sqlite").exists()
