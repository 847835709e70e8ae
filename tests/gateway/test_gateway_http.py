"""The gateway through real HTTP (uvicorn on a free port) with a real Redis, in front of the real services.

One pipeline fleet per module (sim, mapper, vlm_scorer, planner, stopper as processes, :mod:`eqa.launcher`)
shares the Redis with the gateway under test, which runs in this process (a thread) as another peer of the
fleet. Episodes are small (160x120 images, budgets of a few steps) with stop rules that need no calibration
table. The watchdog test kills the planner, so it is the last test of the module (the fleet does not restart
services: ``restart=False``).
"""

from __future__ import annotations

import base64
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from support.fleet import (
    GatewayThread,
    sse_events,
    stored_end,
    wait_for,
)
from support.gateway import AUTH, EPISODE_S, SCENE, TOKEN

from eqa import keys
from eqa.bus import Bus
from eqa.launcher import Fleet
from eqa.messages import Frame
from eqa.settings import Settings

CHOICES = ["bedroom", "hallway", "storage room", "living room"]
# A short episode: runs to its step limit of 4 (no calibration table needed).
Q = {
    "question": "Where is the black suitcase?",
    "choices": CHOICES,
    "scene": SCENE,
    "max_steps": 4,
    "stop_rule": "max_steps",
    "record": False,
}
# An episode that keeps running until it is cancelled: in this house the planner runs out of frontiers only
# after 100+ steps (tens of seconds).
LONG = {**Q, "max_steps": 400}


def client_for(gw: GatewayThread, **kw: object) -> httpx.Client:
    return httpx.Client(base_url=gw.url, headers=AUTH, timeout=30, **kw)  # type: ignore[arg-type]


def ready(c: httpx.Client) -> bool:
    return c.get("/v1/ready").status_code == 200


def state_of(c: httpx.Client, eid: str) -> str:
    return c.get(f"/v1/episodes/{eid}").json()["state"]


def cancel_unfinished(c: httpx.Client) -> None:
    """Leave no episode running on the fleet for the next test."""
    for ep in c.get("/v1/episodes").json()["episodes"]:
        if ep["state"] in ("queued", "running"):
            c.delete(f"/v1/episodes/{ep['episode_id']}")


@pytest.fixture
def gateway(gw_settings: Settings) -> Iterator[tuple[GatewayThread, httpx.Client]]:
    with GatewayThread(gw_settings) as gw, client_for(gw) as c:
        assert wait_for(lambda: ready(c)), c.get("/v1/ready").text
        yield gw, c
        cancel_unfinished(c)


def test_submit_stream_and_result(gateway, gw_settings: Settings) -> None:
    _gw, c = gateway
    r = c.post("/v1/questions", json=Q)
    assert r.status_code == 202, r.text
    sub = r.json()
    assert sub["state"] == "running" and sub["robot"] == "robot0" and sub["max_steps"] == 4
    eid = sub["episode_id"]
    events = list(sse_events(c, f"/v1/episodes/{eid}/events", timeout=EPISODE_S))
    kinds = [e["kind"] for _, e in events]
    assert kinds[0] == "episode_start" and kinds[-1] == "episode_end" and kinds.count("episode_end") == 1
    assert {"frame", "map_update", "step_scores", "decision", "goal"} <= set(kinds)
    # The real services: one frame, map, scores and decision per step; a goal after every step but the last.
    for kind in ("frame", "map_update", "step_scores", "decision"):
        assert sorted(e["step"] for _, e in events if e["kind"] == kind) == [0, 1, 2, 3], kind
    # (a goal the sim refuses is re-planned within its step, so a step may carry two goals)
    assert sorted({e["step"] for _, e in events if e["kind"] == "goal"}) == [0, 1, 2]
    ids = [i for i, _ in events]
    assert len(set(ids)) == len(ids) and ids == sorted(ids, key=lambda s: tuple(map(int, s.split("-"))))
    frame = next(e for _, e in events if e["kind"] == "frame")
    assert frame["episode_id"] == eid and frame["step"] == 0 and "rgb" not in frame and "b64" not in str(frame)
    st = c.get(f"/v1/episodes/{eid}").json()
    assert st["state"] == "stopped" and st["steps"] == 4 and st["normalized_steps"] == pytest.approx(1.0)
    assert st["stop_reason"].startswith("step limit reached (4 steps)")
    assert st["answer"] in "ABCD" and st["answer_text"] == CHOICES["ABCD".index(st["answer"])]
    end = stored_end(gw_settings, eid)  # what the stopper decided is what the gateway reports
    assert end is not None and (end.answer, end.reason, end.steps) == (st["answer"], st["stop_reason"], 4)
    listed = c.get("/v1/episodes").json()["episodes"]
    assert [e["episode_id"] for e in listed] == [eid]
    assert c.get("/v1/episodes", params={"state": "running"}).json()["episodes"] == []
    # A finished stream replays from any point and then closes.
    tail = list(sse_events(c, f"/v1/episodes/{eid}/events", last_event_id=ids[-3]))
    assert [i for i, _ in tail] == ids[-2:]


PROTECTED = [
    ("POST", "/v1/questions"),
    ("GET", "/v1/episodes"),
    ("GET", "/v1/episodes/ep-x"),
    ("DELETE", "/v1/episodes/ep-x"),
    ("GET", "/v1/episodes/ep-x/events"),
    ("GET", "/v1/episodes/ep-x/recording"),
]
DOCS = ["/docs", "/redoc", "/openapi.json"]


def test_auth_and_rate_limit(gw_settings: Settings) -> None:
    s = gw_settings.model_copy(update={"rate_limit_per_s": 3.0, "api_tokens": [TOKEN, "second-token"]})
    with GatewayThread(s) as gw, httpx.Client(base_url=gw.url, timeout=10) as c:
        assert c.get("/v1/health").status_code == 200
        assert c.get("/v1/ready").status_code in (200, 503)
        for method, path in [*PROTECTED, *(("GET", d) for d in DOCS)]:
            r = c.request(method, path, json=Q if method == "POST" else None)
            assert r.status_code == 401, (method, path, r.text)
            assert r.headers["www-authenticate"].startswith("Bearer")
            r = c.request(method, path, headers={"Authorization": "Bearer wrong"})
            assert r.status_code == 401 and r.json()["detail"] == "invalid bearer token"
        responses = [c.get("/v1/episodes/ep-none", headers=AUTH) for _ in range(8)]
        codes = [r.status_code for r in responses]
        assert codes[0] == 404 and 429 in codes, codes
        limited = next(r for r in responses if r.status_code == 429)
        assert int(limited.headers["retry-after"]) >= 1 and "rate limit of 3 requests/s" in limited.json()["detail"]
        other = c.get("/v1/episodes/ep-none", headers={"Authorization": "Bearer second-token"})
        assert other.status_code == 404  # the limit is per token


def _basic(password: str) -> dict[str, str]:
    return {"Authorization": "Basic " + base64.b64encode(f"anyone:{password}".encode()).decode()}


def test_docs_need_the_token_when_tokens_are_configured(gw_settings: Settings) -> None:
    with GatewayThread(gw_settings) as gw, httpx.Client(base_url=gw.url, timeout=10) as c:
        for path in DOCS:
            r = c.get(path)
            assert r.status_code == 401 and r.json()["detail"] == "missing bearer token", path
            assert "Basic" in r.headers["www-authenticate"]  # a browser asks for the token
            assert c.get(path, headers=_basic("wrong")).status_code == 401
            assert c.get(path, headers={"Authorization": "Basic !!not-base64"}).status_code == 401
            for headers in (AUTH, _basic(TOKEN)):
                r = c.get(path, headers=headers)
                assert r.status_code == 200, (path, headers, r.text[:200])
        page = c.get("/docs", headers=AUTH).text
        assert "swagger-ui" in page.lower() and "cdn." not in page  # Swagger UI works offline
        for asset in re.findall(r'(?:src|href)="(/docs/assets/[^"]+)"', page):
            r = c.get(asset)  # a public JS library: served without the token
            assert r.status_code == 200 and len(r.content) > 100, asset
        assert len(re.findall(r'"/docs/assets/', page)) >= 2
        assert "redoc" in c.get("/redoc", headers=AUTH).text.lower()
        spec = c.get("/openapi.json", headers=AUTH).json()
        assert spec["components"]["securitySchemes"]["bearerAuth"]["scheme"] == "bearer"
        assert spec["paths"]["/v1/questions"]["post"]["security"] == [{"bearerAuth": []}]
        assert "security" not in spec["paths"]["/v1/health"]["get"]
        assert not {"/docs", "/redoc", "/openapi.json"} & set(spec["paths"])
        # The API routes take only the bearer form.
        assert c.get("/v1/episodes", headers=_basic(TOKEN)).status_code == 401
        assert c.get("/v1/health").status_code == 200


def test_openapi_examples_and_cors(gw_settings: Settings) -> None:
    open_settings = gw_settings.model_copy(update={"api_tokens": []})  # no tokens: the docs are open
    with GatewayThread(open_settings) as gw, httpx.Client(base_url=gw.url) as c:
        spec = c.get("/openapi.json").json()
        schema = spec["components"]["schemas"]["QuestionRequest"]
        assert schema["examples"][0]["question"]
        assert "/v1/episodes/{episode_id}/events" in spec["paths"]
        assert "securitySchemes" not in spec["components"]
        assert c.get("/docs").status_code == 200 and c.get("/redoc").status_code == 200
        r = c.options("/v1/episodes", headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "GET"})
        assert "access-control-allow-origin" not in r.headers
    s = gw_settings.model_copy(update={"cors_origins": ["http://ui.example"]})
    with GatewayThread(s) as gw, httpx.Client(base_url=gw.url) as c:
        r = c.options("/v1/episodes", headers={"Origin": "http://ui.example", "Access-Control-Request-Method": "GET"})
        assert r.headers["access-control-allow-origin"] == "http://ui.example"
        assert c.get("/openapi.json", headers=AUTH).json()["components"]["schemas"]["QuestionRequest"]["examples"]


INVALID = [
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
    ({**Q, "question_id": "a/b"}, "question_id"),
]


def test_invalid_bodies_give_field_level_422(gateway) -> None:
    _gw, c = gateway
    for body, field in INVALID:
        r = c.post("/v1/questions", json=body)
        assert r.status_code == 422, (field, r.text[:300])
        assert len(r.content) < 10_000  # the 1 MB input is not echoed back
        detail = r.json()["detail"]
        assert any(field in [str(p) for p in d["loc"]] for d in detail), (field, detail)
        assert all(d["msg"] for d in detail)
    assert c.get("/v1/episodes").json()["episodes"] == []  # none of them started anything


def test_needs_scene_or_robot(gateway) -> None:
    _gw, c = gateway
    r = c.post("/v1/questions", json={"question": "Is the stove on?"})
    assert r.status_code == 422 and "scene, a robot id" in r.text
    assert (
        c.post("/v1/questions", content=b"{not json", headers={"Content-Type": "application/json"}).status_code == 422
    )
    assert c.get("/v1/episodes/bad*id").status_code == 422
    assert c.get("/v1/episodes/ep-none/events", headers={"Last-Event-ID": "yesterday"}).status_code == 422


def test_step_budget_from_scene_area(gateway) -> None:
    from services.sim.library import load_or_generate

    gw, c = gateway
    area = load_or_generate(SCENE, gw.settings.scenes_path).floor_area_m2
    # entropy with a threshold above log(4): the stopper stops after the first step
    body = {"question": "Is the oven on?", "choices": ["yes", "no"], "scene": SCENE, "stop_rule": "entropy",
            "threshold": 5.0, "record": False, "question_id": "bench-q-1"}
    r = c.post("/v1/questions", json=body)
    assert r.status_code == 202 and r.json()["max_steps"] == int(3 * area**0.5)
    eid = r.json()["episode_id"]
    assert wait_for(lambda: state_of(c, eid) == "stopped", EPISODE_S)
    st = c.get(f"/v1/episodes/{eid}").json()
    assert st["steps"] == 1 and st["max_steps"] == int(3 * area**0.5) and "threshold 5" in st["stop_reason"]
    assert st["question"]["id"] == "bench-q-1"  # the client's question id is kept
    r = c.post("/v1/questions", json={"question": "Is the oven on?", "scene": "no-such-scene"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "scene"]
    assert "unknown scene" in r.json()["detail"][0]["msg"]


def test_busy_robot_queue_then_run(gateway) -> None:
    _gw, c = gateway
    first = c.post("/v1/questions", json=LONG).json()
    dropped = c.post("/v1/questions", json=Q).json()
    second = c.post("/v1/questions", json=Q).json()
    assert first["state"] == "running" and dropped["state"] == "queued" and dropped["queue_position"] == 1
    assert second["state"] == "queued" and second["queue_position"] == 2
    # Cancelling a queued episode does not start the next one on the busy robot.
    assert c.delete(f"/v1/episodes/{dropped['episode_id']}").json()["state"] == "cancelled"
    assert state_of(c, second["episode_id"]) == "queued"
    readiness = c.get("/v1/ready").json()
    assert readiness["robots"] == {"robot0": first["episode_id"]}
    assert "gateway" in readiness["services"]  # the gateway's own liveliness token
    assert wait_for(lambda: c.get(f"/v1/episodes/{first['episode_id']}").json()["step"] >= 1, EPISODE_S)
    assert state_of(c, second["episode_id"]) == "queued"
    # The robot frees up when the first episode ends: the queued one runs to its end.
    assert c.delete(f"/v1/episodes/{first['episode_id']}").json()["state"] == "cancelled"
    assert wait_for(lambda: state_of(c, second["episode_id"]) == "stopped", EPISODE_S)
    st = c.get(f"/v1/episodes/{second['episode_id']}").json()
    assert st["steps"] == 4 and st["stop_reason"].startswith("step limit reached")
    evs = [e["kind"] for _, e in sse_events(c, f"/v1/episodes/{second['episode_id']}/events")]
    assert evs[0] == "queued" and evs[1] == "episode_start" and evs[-1] == "episode_end" and "frame" in evs
    assert [e["kind"] for _, e in sse_events(c, f"/v1/episodes/{dropped['episode_id']}/events")] == [
        "queued",
        "episode_end",
    ]


def test_busy_robot_refused_and_two_robots(gw_settings: Settings) -> None:
    s = gw_settings.model_copy(update={"busy_policy": "refuse", "robots": ["r1", "r2"]})
    with GatewayThread(s) as gw, client_for(gw) as c:
        assert wait_for(lambda: ready(c)), c.get("/v1/ready").text
        try:
            a = c.post("/v1/questions", json=LONG).json()
            b = c.post("/v1/questions", json=LONG).json()
            assert {a["robot"], b["robot"]} == {"r1", "r2"} and a["state"] == b["state"] == "running"
            # the fleet runs both robots at once
            for e in (a, b):
                assert wait_for(lambda e=e: c.get(f"/v1/episodes/{e['episode_id']}").json()["step"] >= 1, EPISODE_S)
            r = c.post("/v1/questions", json=Q)
            assert r.status_code == 409 and "busy" in r.json()["detail"] and "refuse" in r.json()["detail"]
            r = c.post("/v1/questions", json={**Q, "robot": "r1"})
            assert r.status_code == 409
            c.delete(f"/v1/episodes/{b['episode_id']}")
            again = c.post("/v1/questions", json={**Q, "robot": b["robot"]}).json()
            assert again["robot"] == b["robot"] and again["state"] == "running"
            assert wait_for(lambda: state_of(c, again["episode_id"]) == "stopped", EPISODE_S)
            assert state_of(c, a["episode_id"]) == "running"
        finally:
            cancel_unfinished(c)


def test_cancel(gateway, gw_settings: Settings) -> None:
    _gw, c = gateway
    frames: list[tuple[float, str]] = []
    with Bus(gw_settings, "probe", f"probe-{time.monotonic_ns()}") as probe:
        lock = threading.Lock()

        def on_frame(_key: str, msg: Frame) -> None:
            with lock:
                frames.append((time.monotonic(), msg.episode_id))

        probe.subscribe(keys.stream("robot0", keys.SIM_FRAME), Frame, on_frame)
        eid = c.post("/v1/questions", json=LONG).json()["episode_id"]
        assert wait_for(lambda: c.get(f"/v1/episodes/{eid}").json()["step"] >= 1, EPISODE_S)
        r = c.delete(f"/v1/episodes/{eid}")
        assert r.status_code == 200 and r.json()["state"] == "cancelled"
        # The services got EpisodeCancel over Zenoh: the stopper ended its copy with the gateway's reason ...
        assert wait_for(lambda: stored_end(gw_settings, eid) is not None, 30)
        end = stored_end(gw_settings, eid)
        assert end is not None and end.state == "cancelled" and end.reason == "cancelled by user"
        # ... and the sim renders no more frames of it (one may have been in flight).
        time.sleep(0.7)
        with lock:
            seen = sum(1 for _, e in frames if e == eid)
        time.sleep(1.5)
        with lock:
            assert sum(1 for _, e in frames if e == eid) == seen >= 2
    assert c.delete(f"/v1/episodes/{eid}").status_code == 409
    assert c.delete("/v1/episodes/ep-none").status_code == 404
    last = list(sse_events(c, f"/v1/episodes/{eid}/events"))[-1][1]
    assert last["kind"] == "episode_end" and last["state"] == "cancelled"


def test_sim_refusal(gateway) -> None:
    _gw, c = gateway
    # The gateway checks the scene even with an explicit budget (an unknown scene never reaches the fleet)...
    r = c.post("/v1/questions", json={**Q, "scene": "missing"})
    assert r.status_code == 422 and "unknown scene 'missing'" in r.json()["detail"][0]["msg"]
    # ... and what only the sim can judge, a start pose off the floor, the real sim refuses at once.
    eid = c.post("/v1/questions", json={**Q, "start_pose": {"x": 5000.0, "y": 5000.0}}).json()["episode_id"]
    assert wait_for(lambda: state_of(c, eid) == "failed", EPISODE_S)
    st = c.get(f"/v1/episodes/{eid}").json()
    assert st["stop_reason"].startswith("sim refused the episode: start pose refused") and st["steps"] == 0
    kinds = [e["kind"] for _, e in sse_events(c, f"/v1/episodes/{eid}/events")]
    assert kinds == ["episode_start", "error", "episode_end"]
    assert c.get("/v1/ready").json()["robots"] == {"robot0": None}  # the robot is free again


def test_embedded_store_without_redis(fleet: Fleet, tmp_path: Path) -> None:
    """With no EQA_REDIS_URL the same gateway runs on the embedded SQLite store (the services keep theirs)."""
    s = fleet.client_settings().model_copy(update={"redis_url": None, "data_dir": tmp_path / "gw"})
    with GatewayThread(s) as gw, httpx.Client(base_url=gw.url, timeout=30) as c:
        assert wait_for(lambda: ready(c)), c.get("/v1/ready").text
        eid = c.post("/v1/questions", json=Q).json()["episode_id"]
        kinds = [e["kind"] for _, e in sse_events(c, f"/v1/episodes/{eid}/events", timeout=EPISODE_S)]
        assert kinds[0] == "episode_start" and kinds[-1] == "episode_end" and kinds.count("frame") == 4
        assert c.get(f"/v1/episodes/{eid}").json()["state"] == "stopped"
    assert (tmp_path / "gw" / "store.sqlite").exists()


# Keep last: it kills the planner of the module's fleet (restart=False).
def test_watchdog_names_dead_services(fleet: Fleet, gw_settings: Settings) -> None:
    s = gw_settings.model_copy(update={"episode_timeout_s": 3.0})
    with GatewayThread(s) as gw, client_for(gw) as c:
        assert wait_for(lambda: ready(c)), c.get("/v1/ready").text
        fleet.kill("planner")
        assert wait_for(lambda: c.get("/v1/ready").json()["missing"] == ["planner"], 30)
        assert c.get("/v1/ready").status_code == 503
        eid = c.post("/v1/questions", json=Q).json()["episode_id"]
        assert wait_for(lambda: state_of(c, eid) == "failed", EPISODE_S)
        st = c.get(f"/v1/episodes/{eid}").json()
        reason = st["stop_reason"]
        assert reason == "no message for 3 s (last step 0); services not alive: planner", reason
        kinds = [e["kind"] for _, e in sse_events(c, f"/v1/episodes/{eid}/events")]
        # sim, mapper and stopper did step 0; nothing moved the robot on
        assert {"frame", "map_update", "step_scores", "decision"} <= set(kinds) and "goal" not in kinds
        assert kinds[-1] == "episode_end"
