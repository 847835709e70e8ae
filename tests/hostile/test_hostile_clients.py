"""Hostile clients against the gateway over real sockets (uvicorn on loopback, the app as ``python -m gateway``
serves it: :func:`gateway.cli.uvicorn_options`): failed-auth limits that never refuse a valid token, client
addresses behind trusted proxies only, slow and short bodies, the cap on concurrent uploads, strict types, blank
texts, choice counts, self-referential tasks and the per-token cap on event streams.

The gateway runs in this process with a private Zenoh port and no services (episodes stay "running").
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from pathlib import Path

import httpx
import pytest
from support.fleet import GatewayThread, tenant_gateway_settings
from support.gateway import ADMIN, A, B, Q

from gateway.auth import client_ip, parse_networks


def _codes(c: httpx.Client, n: int, token: str, xff: str | None = None) -> list[int]:
    headers = {"Authorization": f"Bearer {token}"}
    if xff is not None:
        headers["X-Forwarded-For"] = xff
    return [c.get("/v1/episodes", headers=headers).status_code for _ in range(n)]


# ---- failed authentication -----------------------------------------------------------------------------


def test_valid_tokens_are_never_refused_for_other_callers_failures(tmp_path: Path) -> None:
    with GatewayThread(tenant_gateway_settings(tmp_path, auth_failures_per_min=5)) as g, \
            httpx.Client(base_url=g.url, timeout=10) as c:
        wrong = [c.get("/v1/episodes", headers={"Authorization": f"Bearer guess{i:03d}"}).status_code
                 for i in range(20)]
        assert wrong[:5] == [401] * 5 and set(wrong[5:]) == {429}, wrong
        assert c.get("/v1/episodes").status_code == 429  # no token at all: counted with the wrong ones
        for headers in (A, B, ADMIN):  # the same address, valid tokens of three tenants: served
            assert c.get("/v1/episodes", headers=headers).status_code == 200
        r = c.post("/v1/questions", json=Q, headers=A)  # a body-bearing request too (checked before reading)
        assert r.status_code == 202, r.text
        assert c.get("/v1/episodes", headers={"Authorization": "Bearer guess-x"}).status_code == 429
        c.delete(f"/v1/episodes/{r.json()['episode_id']}", headers=A)


def test_wrong_tokens_are_limited_per_prefix_from_any_address(tmp_path: Path) -> None:
    s = tenant_gateway_settings(tmp_path, auth_failures_per_min=100, auth_failures_per_prefix_per_min=4,
                    trusted_proxies=["127.0.0.1/32"])
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=10) as c:
        got = [_codes(c, 1, f"tok-a-{i}", xff=f"203.0.113.{i}")[0] for i in range(8)]  # 8 addresses, one prefix
        assert got[:4] == [401] * 4 and set(got[4:]) == {429}, got
        assert _codes(c, 1, "other-prefix", xff="203.0.113.99") == [401]  # another prefix: its own bucket
        assert _codes(c, 1, "tok-a", xff="203.0.113.1") == [200]  # the valid token of that prefix: served


def test_forwarded_for_counts_only_from_a_trusted_proxy(tmp_path: Path) -> None:
    with GatewayThread(tenant_gateway_settings(tmp_path, auth_failures_per_min=3)) as g, \
            httpx.Client(base_url=g.url, timeout=10) as c:
        # no trusted proxy: the header is the client's word, ignored; every request is the peer 127.0.0.1
        got = [_codes(c, 1, f"wrong{i}", xff=f"198.51.100.{i}")[0] for i in range(5)]
        assert got == [401, 401, 401, 429, 429], got
    s = tenant_gateway_settings(tmp_path / "trusted",
                                auth_failures_per_min=3, trusted_proxies=["127.0.0.0/8", "10.0.0.0/8"])
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=10) as c:
        assert _codes(c, 4, "wrong", xff="198.51.100.7") == [401, 401, 401, 429]
        assert _codes(c, 2, "wrong2", xff="198.51.100.8") == [401, 401]  # another client behind the proxy
        # a client's own forged entry left of the proxy's: the proxy's (rightmost) entry is the client
        assert _codes(c, 1, "wrong3", xff="198.51.100.8, 198.51.100.7") == [429]
        assert _codes(c, 1, "wrong4", xff="198.51.100.7, 10.1.2.3") == [429]  # through two trusted proxies
        assert _codes(c, 1, "tok-a", xff="198.51.100.7") == [200]


def test_client_ip_reads_forwarded_for_from_trusted_peers_only() -> None:
    trusted = parse_networks(["10.0.0.0/8", "::1"])
    assert client_ip("192.0.2.1", ["203.0.113.5"], trusted) == "192.0.2.1"  # peer not trusted
    assert client_ip("10.0.0.2", ["203.0.113.5"], trusted) == "203.0.113.5"
    assert client_ip("10.0.0.2", ["1.1.1.1, 203.0.113.5, 10.9.9.9"], trusted) == "203.0.113.5"
    assert client_ip("10.0.0.2", ["1.1.1.1", "203.0.113.5"], trusted) == "203.0.113.5"  # two header lines
    assert client_ip("10.0.0.2", ["not-an-ip"], trusted) == "10.0.0.2"  # a broken header: the proxy
    assert client_ip("10.0.0.2", [], trusted) == "10.0.0.2"
    assert client_ip("::1", ["2001:db8::1"], trusted) == "2001:db8::1"
    assert client_ip("10.0.0.2", ["203.0.113.5"], ()) == "10.0.0.2"  # nothing trusted: never read
    with pytest.raises(ValueError, match="CIDR"):
        tenant_gateway_settings(Path("/tmp"), trusted_proxies=["10.0.0.0/33"])


# ---- slow, short and many bodies -------------------------------------------------------------------------


def _head(length: int, token: str = "tok-a") -> bytes:
    return (f"POST /v1/questions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {length}\r\n\r\n").encode()


def _answer_and_close(sock: socket.socket, timeout: float) -> tuple[int, bool]:
    """(status, closed by the server afterwards) of a request whose body is incomplete."""
    sock.settimeout(timeout)
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    status = int(data.split(b" ", 2)[1]) if data else 0
    try:
        while sock.recv(4096):
            pass
        closed = True
    except TimeoutError:
        closed = False
    return status, closed


def test_a_body_shorter_than_its_length_gets_408_and_the_connection_closes(tmp_path: Path) -> None:
    with GatewayThread(tenant_gateway_settings(tmp_path, body_timeout_s=2.0)) as g:
        with socket.create_connection(("127.0.0.1", g.port), timeout=10) as sock:
            sock.sendall(_head(200) + b'{"question": "where')  # 19 of 200 bytes, then nothing
            t0 = time.monotonic()
            status, closed = _answer_and_close(sock, timeout=10)
            took = time.monotonic() - t0
        assert status == 408 and closed, (status, closed)
        assert 1.5 < took < 6, took
        assert httpx.get(f"{g.url}/v1/health").status_code == 200


def test_slow_loris_uploads_are_cut_off_and_capped(tmp_path: Path) -> None:
    """30 connections sending one byte of a 200-byte body every 2 s: those over the upload cap are refused at
    once (503), the others get 408 at the body deadline and are closed; health stays fast meanwhile."""
    s = tenant_gateway_settings(tmp_path, body_timeout_s=4.0, max_concurrent_uploads=20)
    with GatewayThread(s) as g:
        socks = [socket.create_connection(("127.0.0.1", g.port), timeout=10) for _ in range(30)]
        results: dict[int, tuple[int, bool, float]] = {}
        stop = threading.Event()
        t0 = time.monotonic()

        def trickle() -> None:
            while not stop.wait(2.0):
                for sock in socks:
                    with contextlib.suppress(OSError):
                        sock.sendall(b" ")

        def watch(i: int) -> None:
            status, closed = _answer_and_close(socks[i], timeout=20)
            results[i] = (status, closed, time.monotonic() - t0)

        for sock in socks:
            sock.sendall(_head(200))
            time.sleep(0.02)  # in order: the first 20 take the upload places
        feeder = threading.Thread(target=trickle, daemon=True)
        feeder.start()
        watchers = [threading.Thread(target=watch, args=(i,), daemon=True) for i in range(30)]
        for w in watchers:
            w.start()
        health_s = []
        for _ in range(5):
            h0 = time.monotonic()
            assert httpx.get(f"{g.url}/v1/health", timeout=10).status_code == 200
            health_s.append(time.monotonic() - h0)
            time.sleep(0.5)
        for w in watchers:
            w.join(timeout=25)
        stop.set()
        for sock in socks:
            sock.close()
    codes = [results.get(i, (0, False, 0.0))[0] for i in range(30)]
    assert codes.count(408) == 20 and codes.count(503) == 10, codes
    assert all(results[i][1] for i in range(30)), results  # every connection closed by the server
    assert max(results[i][2] for i in range(30) if codes[i] == 408) < 4.0 + 3.0, results
    assert max(results[i][2] for i in range(30) if codes[i] == 503) < 3.0, results
    assert max(health_s) < 1.0, health_s


# ---- strict types, blank texts, counts, tasks ----------------------------------------------------------

ZW = "\u200b\u200c\u200d\ufeff"  # zero-width space, non-joiner, joiner, byte-order mark (category Cf)
STRICT_BODIES: list[tuple[str, dict[str, object], str]] = [
    ("eps as a string", {**Q, "eps": "0.2"}, "eps"),
    ("max_steps as a string", {**Q, "max_steps": "10"}, "max_steps"),
    ("max_steps as true", {**Q, "max_steps": True}, "max_steps"),
    ("threshold as a string", {**Q, "stop_rule": "entropy", "threshold": "0.5"}, "threshold"),
    ("seed as a string", {**Q, "seed": "7"}, "seed"),
    ("seed as a float", {**Q, "seed": 7.5}, "seed"),
    ("pose x as a string", {**Q, "start_pose": {"x": "9.3", "y": 13.9}}, "start_pose"),
    ("pose y as true", {**Q, "start_pose": {"x": 9.3, "y": True}}, "start_pose"),
    ("scene as a number", {**Q, "scene": 7}, "scene"),
    ("question of zero-width characters", {**Q, "question": ZW}, "question"),
    ("question of spaces and zero-width characters", {**Q, "question": " \u200b \u2060 "}, "question"),
    ("a zero-width choice", {**Q, "choices": ["bedroom", "\u200b"]}, "choices"),
    ("no choices", {**Q, "choices": []}, "choices"),
    ("one choice", {**Q, "choices": ["bedroom"]}, "choices"),
    ("27 choices", {**Q, "choices": [f"room {i}" for i in range(27)]}, "choices"),
]


@pytest.fixture(scope="module")
def gw(tmp_path_factory: pytest.TempPathFactory):
    s = tenant_gateway_settings(tmp_path_factory.mktemp("hostile-clients"),
                                queue_max_per_robot=100, queue_max_per_token=100,
                    sse_max_per_token=2)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
        yield g, c


@pytest.mark.parametrize(("case", "body", "field"), STRICT_BODIES, ids=[c for c, _, _ in STRICT_BODIES])
def test_lax_values_get_a_422_naming_the_field(gw, case: str, body: dict[str, object], field: str) -> None:
    _g, c = gw
    r = c.post("/v1/questions", json=body, headers=A)
    assert r.status_code == 422, (case, r.status_code, r.text[:300])
    assert any(field in [str(p) for p in d["loc"]] for d in r.json()["detail"]), (case, r.json())


def test_exact_values_are_still_accepted(gw) -> None:
    _g, c = gw
    for body in ({**Q, "eps": 0.1, "max_steps": 4, "seed": 3, "start_pose": {"x": 9, "y": 13.9}},
                 {**Q, "choices": None}, {k: v for k, v in Q.items() if k != "choices"}):
        r = c.post("/v1/questions", json=body, headers=A)
        assert r.status_code == 202, (body, r.text)
        c.delete(f"/v1/episodes/{r.json()['episode_id']}", headers=A)


TASKS = [
    ("object is its own receptacle", "Move the mug from the mug to the mug"),
    ("object is the goal", "Move the mug from the table to the mug"),
    ("zero-width instruction", "\u200b\u200b"),
]


@pytest.mark.parametrize(("case", "instruction"), TASKS, ids=[c for c, _ in TASKS])
def test_self_referential_or_blank_tasks_get_a_422(gw, case: str, instruction: str) -> None:
    _g, c = gw
    r = c.post("/v1/tasks", json={"instruction": instruction, "scene": "gen-00001"}, headers=A)
    assert r.status_code == 422, (case, r.status_code, r.text[:300])
    assert "instruction" in str(r.json()["detail"]), r.text
    r = c.post("/v1/tasks", json={"instruction": "Find a mug", "scene": "gen-00001", "max_steps": "5"}, headers=A)
    assert r.status_code == 422


def test_a_boolean_label_is_refused(gw) -> None:
    _g, c = gw
    eid = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
    c.delete(f"/v1/episodes/{eid}", headers=A)
    for answer in (True, False, 1.0, None):
        r = c.post(f"/v1/episodes/{eid}/label", json={"answer": answer}, headers=A)
        assert r.status_code == 422, (answer, r.status_code, r.text)


def test_event_streams_are_capped_per_token(gw) -> None:
    _g, c = gw
    eid = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
    eid_b = c.post("/v1/questions", json=Q, headers=B).json()["episode_id"]
    try:
        with c.stream("GET", f"/v1/episodes/{eid}/events", headers=A) as s1, \
                c.stream("GET", f"/v1/episodes/{eid}/events", headers=A) as s2:
            assert s1.status_code == 200 and s2.status_code == 200
            r = c.get(f"/v1/episodes/{eid}/events", headers=A)
            assert r.status_code == 429 and "EQA_SSE_MAX_PER_TOKEN" in r.text and int(r.headers["retry-after"]) >= 1
            with c.stream("GET", f"/v1/episodes/{eid_b}/events", headers=B) as sb:  # another token: its own cap
                assert sb.status_code == 200
        deadline = time.monotonic() + 10  # the server sees the streams closed at its next write or check
        while time.monotonic() < deadline:
            with c.stream("GET", f"/v1/episodes/{eid}/events", headers=A) as s3:
                if s3.status_code == 200:
                    break
            time.sleep(0.2)
        else:
            pytest.fail("closed streams were not released")
    finally:
        c.delete(f"/v1/episodes/{eid}", headers=A)
        c.delete(f"/v1/episodes/{eid_b}", headers=B)
