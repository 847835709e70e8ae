"""Hostile input against the gateway over real HTTP (uvicorn on loopback): bodies and headers,
event-stream ids, oversized and chunked bodies with and without a token, tenant crossing, failed-auth floods,
queue floods, readiness without a token, a store that goes away. Each case was accepted (or answered 500, or
read a whole body) before the fix.

The gateway runs in this process with a private Zenoh port and no services (episodes it starts stay
"running": nothing answers), with the simulator's scene library for the scene check.
"""

from __future__ import annotations

import json
import resource
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from support.fleet import GatewayThread, tenant_gateway_settings, wait_for
from support.gateway import ADMIN, READER, SCENE, A, B, Q

from eqa.launcher import free_port


@pytest.fixture(scope="module")
def gw(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[GatewayThread, httpx.Client]]:
    s = tenant_gateway_settings(tmp_path_factory.mktemp("hostile"), queue_max_per_robot=100, queue_max_per_token=100)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
        yield g, c


def raw_post(body: bytes, headers: dict[str, str]) -> httpx.Response:
    return httpx.post("http://x/v1/questions", content=body, headers={**headers, "content-type": "application/json"})


BAD_BODIES: list[tuple[str, object, str]] = [
    # (case, body (dict, or raw JSON text), field named in the 422)
    ("pose 1e308 (sim OverflowError)", {**Q, "start_pose": {"x": 1e308, "y": -1e308}}, "start_pose"),
    ("threshold NaN", '{"question": "q?", "scene": "gen-00001", "threshold": NaN}', "threshold"),
    ("threshold -Infinity", '{"question": "q?", "scene": "gen-00001", "threshold": -Infinity}', "threshold"),
    ("eps NaN", '{"question": "q?", "scene": "gen-00001", "eps": NaN}', "eps"),
    ("path scene with a budget", {**Q, "scene": "../../etc/passwd"}, "scene"),
    ("unknown scene with a budget", {**Q, "scene": "no-such-scene"}, "scene"),
    ("changed house past its rounds", {**Q, "scene": "gen-00001-c21"}, "scene"),
    ("scene with a trailing newline", {**Q, "scene": "gen-00001\n"}, "scene"),
    ("NUL in the question", {**Q, "question": "where\u0000is it?"}, "question"),
    ("NUL in a choice", {**Q, "choices": ["bed\u0000room", "hall"]}, "choices"),
    ("duplicate choices", {**Q, "choices": ["bedroom", "bedroom"]}, "choices"),
    ("duplicate choices by case and space", {**Q, "choices": ["Bedroom", " bedroom "]}, "choices"),
    ("blank choice", {**Q, "choices": ["bedroom", "   "]}, "choices"),
    ("record 0 as a boolean", {**Q, "record": 0}, "record"),
    ("record 'yes' as a boolean", {**Q, "record": "yes"}, "record"),
    ("robot with a trailing newline", {**Q, "robot": "robot0\n"}, "robot"),
    ("question id with a trailing newline", {**Q, "question_id": "q1\n"}, "question_id"),
    ("negative seed", {**Q, "seed": -1}, "seed"),
    ("benchmark-only strategy", {**Q, "strategy": "target_oracle"}, "strategy"),
    ("answer that is not a letter", {**Q, "answer": "bedroom"}, "answer"),
]


@pytest.mark.parametrize(("case", "body", "field"), BAD_BODIES, ids=[c for c, _, _ in BAD_BODIES])
def test_bad_bodies_get_a_422_naming_the_field(gw, case: str, body: object, field: str) -> None:
    _g, c = gw
    if isinstance(body, str):
        r = c.post("/v1/questions", content=body.encode(), headers={**A, "content-type": "application/json"})
    else:
        r = c.post("/v1/questions", json=body, headers=A)
    assert r.status_code == 422, (case, r.status_code, r.text[:300])
    detail = r.json()["detail"]
    assert any(field in [str(p) for p in d["loc"]] for d in detail), (case, detail)
    assert all(d["msg"] for d in detail)


def test_unknown_scene_message_shows_no_server_paths_and_makes_no_folder(gw) -> None:
    g, c = gw
    r = c.post("/v1/questions", json={**Q, "scene": "no-such-scene"}, headers=A)
    msg = r.json()["detail"][0]["msg"]
    assert r.status_code == 422 and "unknown scene" in msg and "gen-<number>" in msg
    assert str(g.settings.scenes_path) not in msg and str(g.settings.data_dir) not in msg and "/" not in msg
    c.post("/v1/questions", json={**Q, "scene": "gen-00001\n"}, headers=A)
    scenes = g.settings.scenes_path
    assert not any("\n" in p.name for p in scenes.iterdir()) if scenes.is_dir() else True
    assert c.get("/v1/episodes", headers=ADMIN).json()["episodes"] == [] or all(
        e["question"]["scene"] == SCENE for e in c.get("/v1/episodes", headers=ADMIN).json()["episodes"]
    )


@pytest.mark.parametrize(
    "event_id",
    ["99999999999999999999-0", "0-99999999999999999999", "9223372036854775808-0", "1-2-3", "1-2x", "0x1-0", "-1-0"],
)
def test_event_ids_out_of_range_are_refused(gw, event_id: str) -> None:
    _g, c = gw
    eid = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
    try:
        r = c.get(f"/v1/episodes/{eid}/events", headers={**A, "Last-Event-ID": event_id})
        assert r.status_code == 422 and ("<ms>-<seq>" in r.text or "out of range" in r.text), r.text
        r = c.get(f"/v1/episodes/{eid}/events", params={"after": event_id}, headers=A)
        assert r.status_code == 422, r.text
        # the largest valid id is fine: the stream answers (and has nothing after it)
        with c.stream("GET", f"/v1/episodes/{eid}/events", headers={**A, "Last-Event-ID": f"{2**63 - 1}-0"}) as s:
            assert s.status_code == 200
    finally:
        c.delete(f"/v1/episodes/{eid}", headers=A)


def _http(port: int, head: bytes, chunks: Iterator[bytes], max_send: int) -> tuple[int, int]:
    """Send a request by hand (headers, then body chunks while the server reads); return (status, bytes sent)."""
    sent = 0
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(head)
        sock.settimeout(0.05)
        for chunk in chunks:
            try:
                data = sock.recv(4096)
                if data:
                    return int(data.split(b" ", 2)[1]), sent
            except TimeoutError:
                pass
            try:
                sock.sendall(chunk)
            except (BrokenPipeError, ConnectionResetError):
                break
            sent += len(chunk)
            if sent > max_send:
                break
        sock.settimeout(10)
        data = sock.recv(4096)
        return int(data.split(b" ", 2)[1]), sent


def _chunked(total: int, size: int = 256 * 1024) -> Iterator[bytes]:
    piece = b"x" * size
    for _ in range(total // size):
        yield f"{size:x}\r\n".encode() + piece + b"\r\n"
    yield b"0\r\n\r\n"


def test_chunked_body_without_token_is_refused_before_reading(gw) -> None:
    g, _c = gw
    head = (b"POST /v1/questions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Transfer-Encoding: chunked\r\n\r\n")
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    code, sent = _http(g.port, head, _chunked(400 * 1024 * 1024), max_send=400 * 1024 * 1024)
    assert code == 401 and sent < 64 * 1024 * 1024, (code, sent)  # answered at the headers, not after 400 MB
    code, sent = _http(g.port, head.replace(b"Host: x", b"Host: x\r\nAuthorization: Bearer tok-a"),
                       _chunked(400 * 1024 * 1024), max_send=400 * 1024 * 1024)
    assert code == 413 and sent < 64 * 1024 * 1024, (code, sent)  # counted while streaming: over 2 MB -> 413
    get_head = head.replace(b"POST /v1/questions", b"GET /v1/episodes")  # a body on a GET: the same rules
    code, sent = _http(g.port, get_head, _chunked(100 * 1024 * 1024), max_send=100 * 1024 * 1024)
    assert code == 401 and sent < 64 * 1024 * 1024, (code, sent)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
    assert grown_mb < 100, grown_mb
    r = httpx.post(f"{g.url}/v1/questions", content=b"x" * (3 * 1024 * 1024), headers=A)
    assert r.status_code == 413 and "cap" in r.json()["detail"]
    r = httpx.post(f"{g.url}/v1/questions", content=b"x" * (3 * 1024 * 1024))
    assert r.status_code == 401


def test_tenants_see_only_their_episodes(gw) -> None:
    _g, c = gw
    sub = c.post("/v1/questions", json=Q, headers=A)
    assert sub.status_code == 202, sub.text
    eid = sub.json()["episode_id"]
    try:
        for method, path in [("GET", f"/v1/episodes/{eid}"), ("GET", f"/v1/episodes/{eid}/events"),
                             ("GET", f"/v1/episodes/{eid}/recording"), ("DELETE", f"/v1/episodes/{eid}")]:
            r = c.request(method, path, headers=B)
            assert r.status_code == 404 and "no episode" in r.text, (method, path, r.status_code)
            assert "Where is" not in r.text
        assert eid not in c.get("/v1/episodes", headers=B).text
        assert eid not in c.get("/v1/episodes", params={"state": "running"}, headers=B).text
        assert c.get(f"/v1/episodes/{eid}", headers=A).status_code == 200
        assert eid in c.get("/v1/episodes", headers=A).text
        assert c.get(f"/v1/episodes/{eid}", headers=ADMIN).status_code == 200  # admin sees every tenant
        assert eid in c.get("/v1/episodes", headers=ADMIN).text
        r = c.post("/v1/questions", json=Q, headers=READER)
        assert r.status_code == 403 and "submit" in r.json()["detail"]
        assert c.get(f"/v1/episodes/{eid}", headers=READER).status_code == 404  # read scope, other tenant
    finally:
        assert c.delete(f"/v1/episodes/{eid}", headers=A).json()["state"] == "cancelled"
    assert eid not in c.get("/v1/episodes", params={"state": "cancelled"}, headers=B).text
    assert eid in c.get("/v1/episodes", params={"state": "cancelled"}, headers=A).text


def test_ready_without_a_token_says_only_ready_or_not(gw) -> None:
    _g, c = gw
    eid = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
    try:
        r = c.get("/v1/ready")
        assert r.status_code == 503 and r.json() == {"ready": False}  # no services here
        full = c.get("/v1/ready", headers=B).json()
        assert full["robots"] == {"robot0": "busy"} and "gateway" in full["services"]  # another tenant's: busy
        assert c.get("/v1/ready", headers=A).json()["robots"] == {"robot0": eid}
        assert c.get("/v1/ready", headers={"Authorization": "Bearer wrong"}).json() == {"ready": False}
    finally:
        c.delete(f"/v1/episodes/{eid}", headers=A)


def test_failed_authentication_is_rate_limited_per_client(tmp_path: Path) -> None:
    s = tenant_gateway_settings(tmp_path, auth_failures_per_min=5)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=10) as c:
        codes = [c.get("/v1/episodes", headers={"Authorization": f"Bearer guess-{i}"}).status_code for i in range(8)]
        assert codes[:5] == [401] * 5 and codes[5:] == [429] * 3, codes
        r = c.get("/v1/episodes", headers={"Authorization": "Bearer guess-x"})
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1 and "failed authentications" in r.text
        r = c.post("/v1/questions", json=Q, headers={"Authorization": "Bearer guess-y"})
        assert r.status_code == 429  # bodies too, before reading them


def test_queue_floods_get_429_with_retry_after_and_stay_fast(tmp_path: Path) -> None:
    s = tenant_gateway_settings(tmp_path, queue_max_per_robot=3, queue_max_per_token=3)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=10) as c:
        got = [c.post("/v1/questions", json=Q, headers=A).status_code for _ in range(3)]
        assert got == [202, 202, 202]
        r = c.post("/v1/questions", json=Q, headers=A)  # this token has 3 queued or running
        assert r.status_code == 429 and "EQA_QUEUE_MAX_PER_TOKEN" in r.json()["detail"]
        assert int(r.headers["retry-after"]) >= 1
        assert c.post("/v1/questions", json=Q, headers=B).status_code == 202
        t0 = time.perf_counter()
        r = c.post("/v1/questions", json=Q, headers=B)  # robot0: 1 running + 3 queued -> full
        took = time.perf_counter() - t0
        assert r.status_code == 429 and "EQA_QUEUE_MAX_PER_ROBOT" in r.json()["detail"], r.text
        assert int(r.headers["retry-after"]) >= 1 and took < 1.0, took


@pytest.fixture
def own_redis(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], str]]:
    exe = shutil.which("redis-server")
    assert exe, "redis-server is not installed"
    port = free_port()
    proc = subprocess.Popen([exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                             "--dir", str(tmp_path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        assert wait_for(lambda: socket.socket().connect_ex(("127.0.0.1", port)) == 0, 10)
        yield proc, f"redis://127.0.0.1:{port}/0"
    finally:
        proc.kill()
        proc.wait(timeout=10)


def test_store_down_gives_503_with_retry_after(tmp_path: Path, own_redis) -> None:
    proc, url = own_redis
    s = tenant_gateway_settings(tmp_path, redis_url=url)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
        eid = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
        proc.send_signal(signal.SIGSTOP)  # frozen: a call times out (3 s) instead of hanging for 10 s
        try:
            t0 = time.monotonic()
            r = c.get("/v1/episodes/ep-frozen", headers=A)
            assert r.status_code == 503 and int(r.headers["retry-after"]) >= 1, r.text
            assert time.monotonic() - t0 < 8
        finally:
            proc.send_signal(signal.SIGCONT)
        proc.kill()
        proc.wait(timeout=10)
        for method, path in [("POST", "/v1/questions"), ("GET", "/v1/episodes"), ("GET", "/v1/episodes/ep-x"),
                             ("DELETE", f"/v1/episodes/{eid}")]:
            r = c.request(method, path, json=Q if method == "POST" else None, headers=A)
            assert r.status_code == 503, (method, path, r.status_code, r.text[:200])
            assert int(r.headers["retry-after"]) >= 1 and "store is unavailable" in r.json()["detail"]
        r = c.get("/v1/ready", headers=A)
        assert r.status_code == 503 and r.json()["store"] is False


def test_openapi_lists_every_answer_and_its_examples_work(gw) -> None:
    _g, c = gw
    spec = c.get("/openapi.json", headers=A).json()
    want = {
        ("/v1/questions", "post"): {"202", "400", "401", "403", "408", "409", "413", "422", "429", "503"},
        ("/v1/episodes", "get"): {"200", "401", "403", "422", "429", "503"},
        ("/v1/episodes/{episode_id}", "get"): {"200", "401", "403", "404", "422", "429", "503"},
        ("/v1/episodes/{episode_id}", "delete"): {"200", "400", "401", "403", "404", "408", "409", "413", "422",
                                                  "429", "503"},
        ("/v1/episodes/{episode_id}/events", "get"): {"200", "401", "403", "404", "422", "429", "503"},
        ("/v1/episodes/{episode_id}/recording", "get"): {"200", "401", "403", "404", "422", "429", "500", "503"},
        ("/v1/episodes/{episode_id}/recording.mcap", "get"): {"200", "401", "403", "404", "422", "429", "500",
                                                              "503"},
        ("/v1/ready", "get"): {"200", "503"},
    }
    for (path, method), codes in want.items():
        assert set(spec["paths"][path][method]["responses"]) == codes, (path, method)
    for example in spec["components"]["schemas"]["QuestionRequest"]["examples"]:
        r = c.post("/v1/questions", json=example, headers=A)
        assert r.status_code == 202, (example, r.text)
        c.delete(f"/v1/episodes/{r.json()['episode_id']}", headers=A)
    assert json.dumps(spec).count("gen-house") == 0


def test_scenes_new_to_the_gateway_are_rate_limited_per_token(tmp_path: Path) -> None:
    """Each new gen-<seed> scene costs a house generation (~130 ms, 114 KB of disk) inside the request, so
    scenes new to the gateway are limited per token (NEW_SCENES_PER_MIN)."""
    from gateway.manager import NEW_SCENES_PER_MIN

    with GatewayThread(tenant_gateway_settings(tmp_path)) as g, httpx.Client(base_url=g.url, timeout=30) as c:
        codes = [c.post("/v1/questions", json={**Q, "scene": f"room-{i}"}, headers=A).status_code
                 for i in range(NEW_SCENES_PER_MIN + 3)]
        assert codes[:NEW_SCENES_PER_MIN] == [422] * NEW_SCENES_PER_MIN and codes[-1] == 429, codes
        r = c.post("/v1/questions", json={**Q, "scene": "room-x"}, headers=A)
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1 and "new to the gateway" in r.text
        assert c.post("/v1/questions", json={**Q, "scene": "room-y"}, headers=B).status_code == 422  # per token
        assert c.post("/v1/questions", json={**Q, "scene": "room-1"}, headers=A).status_code == 422  # known


def test_sigterm_with_an_open_event_stream_exits_within_the_grace(tmp_path: Path) -> None:
    """A follower's event stream of a running episode never ends by itself: SIGTERM (docker stop) must not
    wait for it beyond ``EQA_GATEWAY_SHUTDOWN_GRACE_S``; the stream is cut and its client resumes elsewhere."""
    import threading

    from support.fleet import GatewayProcess

    gw = GatewayProcess(tenant_gateway_settings(tmp_path,
                                                gateway_shutdown_grace_s=1.0), log_path=tmp_path / "gw.log").start()
    try:
        eid = httpx.post(f"{gw.url}/v1/questions", json=Q, headers=A, timeout=30).json()["episode_id"]
        opened, ended = threading.Event(), threading.Event()

        def follow() -> None:
            try:
                with httpx.stream("GET", f"{gw.url}/v1/episodes/{eid}/events", headers=A, timeout=None) as s:
                    for _ in s.iter_lines():
                        opened.set()
            except httpx.HTTPError:
                pass
            ended.set()

        threading.Thread(target=follow, daemon=True).start()
        assert opened.wait(30), "the event stream did not open"
        assert gw.proc is not None
        t0 = time.monotonic()
        gw.proc.terminate()
        gw.proc.wait(timeout=20)  # TimeoutExpired: the open stream held the gateway past its grace
        took = time.monotonic() - t0
        assert ended.wait(5), "the stream's client was not cut off"
        assert took < 15, took
    finally:
        gw.kill()
