"""Refusals answered by the gateway's edge middleware (gateway.limits.BodyLimit) before routing: wrong tokens and
requests over the rate limit of every API route, and submissions while every robot's queue is full (before the
body is parsed). Real HTTP (uvicorn on loopback), no services."""

from __future__ import annotations

from pathlib import Path

import httpx
from support.fleet import GatewayThread, tenant_gateway_settings
from support.gateway import A, Q


def test_a_wrong_token_is_refused_before_routing_and_a_valid_one_is_admitted_once(tmp_path: Path) -> None:
    s = tenant_gateway_settings(tmp_path, rate_limit_per_s=4.0)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=10) as c:
        r = c.get("/v1/no-such-route", headers={"Authorization": "Bearer guess"})
        assert r.status_code == 401, r.text  # refused before the router could answer 404
        assert c.get("/v1/no-such-route", headers=A).status_code == 404
        # the bucket holds rate_limit_per_s requests: each is admitted once (middleware), not again by the route
        codes = [c.get("/v1/episodes", headers=A).status_code for _ in range(3)]
        assert codes == [200, 200, 200], codes
        codes = [c.get("/v1/episodes", headers=A).status_code for _ in range(4)]
        assert 429 in codes, codes
        r = c.get("/v1/episodes", headers=A)
        assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1 and "rate limit" in r.text
        assert r.headers.get("connection") != "close"  # no body unread: the keep-alive connection stays


def test_a_submission_against_full_queues_is_refused_before_its_body_is_parsed(tmp_path: Path) -> None:
    s = tenant_gateway_settings(tmp_path, queue_max_per_robot=1, queue_max_per_token=100)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=10) as c:
        assert [c.post("/v1/questions", json=Q, headers=A).status_code for _ in range(2)] == [202, 202]
        r = c.post("/v1/questions", json={"question": 7}, headers=A)  # invalid, but every queue is full
        assert r.status_code == 429 and "EQA_QUEUE_MAX_PER_ROBOT" in r.json()["detail"], r.text
        assert int(r.headers["retry-after"]) >= 1 and r.headers.get("connection") != "close"
        reader = {"Authorization": "Bearer tok-reader"}
        assert c.post("/v1/questions", json=Q, headers=reader).status_code == 403  # scope first, then the queue
