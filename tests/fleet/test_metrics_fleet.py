"""Metrics and structured logs of a real fleet: every service a process of its own (the launcher) with a metrics
port, the gateway's /metrics, JSON log lines. The scrapes are parsed with prometheus_client's own parser
(independent of how the numbers were produced), and each count is compared with what happened: the steps of
the episode, the requests the scorer replicas served, the status codes the client received, the garbage sent."""

from __future__ import annotations

import json
import random
import socket
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from support.fleet import wait_for

from eqa import keys
from eqa.launcher import ALL_SERVICES, Fleet, free_port
from eqa.settings import Settings

TOKEN, ADMIN, METRICS_TOKEN = "user-token-1", "admin-token-1", "metrics-token-1"
STEPS = 6
Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


def _free_run(n: int) -> int:
    """A base port with ``n`` free ports from it (the launcher and each child take one)."""
    for _ in range(200):
        base = random.randint(20_000, 60_000)
        socks = []
        try:
            for p in range(base, base + n):
                s = socket.socket()
                socks.append(s)
                s.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError("no run of free ports")


def parse(text: str) -> Samples:
    out: Samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def value(samples: Samples, name: str, **labels: str) -> float:
    """The sum of the samples named ``name`` whose labels include ``labels``."""
    want = set(labels.items())
    return sum(v for (n, ls), v in samples.items() if n == name and want <= ls)


def scrape(port: int) -> Samples:
    r = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10)
    r.raise_for_status()
    return parse(r.text)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("metrics-fleet")
    n = len(ALL_SERVICES) + 2  # two scorer replicas, the launcher
    settings = Settings(
        data_dir=data, zenoh_listen=[], zenoh_connect=[], sim_width=160, sim_height=120, record=False,
        gateway_port=free_port(), episode_timeout_s=60, metrics_port=_free_run(n), log_format="json",
        api_tokens=[TOKEN, f"{ADMIN}:admin"], metrics_token=METRICS_TOKEN, auth_failures_per_min=3,
    )
    with Fleet(settings, services=ALL_SERVICES, scorers=2) as f:
        yield f


def _gw(fleet: Fleet) -> str:
    return f"http://127.0.0.1:{fleet.settings.gateway_port}"


def _ports(fleet: Fleet) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for c in fleet.children:
        port = int(c.env["EQA_METRICS_PORT"])
        if port:
            out.setdefault(c.service, []).append(port)
    return out


def _scrape_all(fleet: Fleet) -> dict[str, list[Samples]]:
    return {service: [scrape(p) for p in ports] for service, ports in _ports(fleet).items()}


def _total(scrapes: list[Samples], name: str, **labels: str) -> float:
    return sum(value(s, name, **labels) for s in scrapes)


def _episode(fleet: Fleet, client: httpx.Client) -> tuple[str, dict[str, Any], Samples]:
    body = {"question": "Is there a bed in the bedroom?", "choices": ["Yes", "No"], "scene": "gen-00001",
            "max_steps": STEPS, "stop_rule": "max_steps", "seed": 3}
    r = client.post("/v1/questions", json=body, headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code in (200, 201, 202), r.text
    eid = r.json()["episode_id"]

    def status() -> dict[str, Any]:
        return client.get(f"/v1/episodes/{eid}", headers={"Authorization": f"Bearer {TOKEN}"}).json()

    assert wait_for(lambda: status()["step"] >= 1, timeout=120, every=0.1), status()
    during = parse(client.get("/metrics").text)
    assert wait_for(lambda: status()["state"] in ("stopped", "failed", "cancelled"), timeout=180, every=0.2)
    return eid, status(), during


def test_metrics_count_what_happened_in_an_episode(fleet: Fleet):
    ports = _ports(fleet)
    assert set(ports) == set(ALL_SERVICES) - {"gateway"} and len(ports["vlm_scorer"]) == 2
    launcher_port = fleet.settings.metrics_port
    assert all(p > launcher_port for ps in ports.values() for p in ps)
    # the scrape targets the launcher wrote (Prometheus file_sd format): itself, each child, the gateway
    groups = json.loads((Path(fleet.settings.data_dir) / "metrics-targets.json").read_text())
    listed = sorted((g["labels"]["job"], g["targets"][0]) for g in groups)
    want = [("launcher", f"127.0.0.1:{launcher_port}"), ("gateway", f"127.0.0.1:{fleet.settings.gateway_port}")]
    want += [(s, f"127.0.0.1:{p}") for s, ps in ports.items() for p in ps]
    assert listed == sorted(want)
    before = _scrape_all(fleet)
    with httpx.Client(base_url=_gw(fleet), timeout=30) as client:
        gw_before = parse(client.get("/metrics").text)  # loopback, no proxy header: readable without a token
        _, st, during = _episode(fleet, client)
        assert st["state"] == "stopped" and st["steps"] == STEPS, st
        # while the episode ran: one running question episode on the gateway
        assert value(during, "eqa_gateway_episodes", state="running", kind="question") == 1
        assert value(during, "eqa_gateway_service_instances", service="vlm_scorer") == 2
        # the last step's observations are made after its message went out: scrape until every service
        # counted every step (bounded), then check everything on that scrape
        scraped: dict[str, dict[str, list[Samples]]] = {}

        def counted() -> bool:
            scraped["after"] = _scrape_all(fleet)
            return all(_total(scraped["after"][s], "eqa_step_seconds_count", service=s)
                       - _total(before[s], "eqa_step_seconds_count", service=s) >= STEPS
                       for s in ("sim", "mapper", "planner", "stopper"))

        assert wait_for(counted, timeout=30, every=0.2), "a service had not counted every step after 30 s"
        after = scraped["after"]
        gw = parse(client.get("/metrics").text)

    def delta(process: str, name: str, **labels: str) -> float:
        return _total(after[process], name, **labels) - _total(before[process], name, **labels)

    # steps computed per service == the episode's steps
    assert delta("sim", "eqa_step_seconds_count", service="sim", input="goal") == STEPS
    assert delta("mapper", "eqa_step_seconds_count", service="mapper", input="frame") == STEPS
    assert delta("stopper", "eqa_step_seconds_count", service="stopper", input="step_scores") == STEPS
    assert delta("planner", "eqa_step_seconds_count", service="planner", input="map_update") == STEPS
    # each stateful service claimed every step once (one instance each: no step lost to another)
    for service in ("sim", "mapper", "planner", "stopper"):
        assert delta(service, "eqa_step_claims_total", service=service, outcome="won") == STEPS, service
        assert delta(service, "eqa_step_claims_total", service=service, outcome="lost") == 0, service
        assert delta(service, "eqa_step_takeovers_total") == 0, service
        assert delta(service, "eqa_resends_total") == 0, service
        assert delta(service, "eqa_store_seconds_count", backend="sqlite") > 0, service
        assert _total(after[service], "eqa_store_errors_total") == 0, service
    # the scorer pool: one ScoreRequest per step (its four prompts in one request), asked by the mapper and
    # served by the replicas (counted on each side independently)
    asked = delta("mapper", "eqa_scorer_request_seconds_count", kind="score_request", outcome="ok")
    served = delta("vlm_scorer", "eqa_scorer_replica_seconds_count", kind="score_request", outcome="served")
    assert asked == served == STEPS
    assert _total(after["vlm_scorer"], "eqa_queryable_queue_depth") == 0
    assert _total(after["mapper"], "eqa_scorer_inflight") == 0
    # the gateway: the episode ended stopped, nothing left running
    assert (value(gw, "eqa_gateway_episodes_ended_total", state="stopped", kind="question")
            - value(gw_before, "eqa_gateway_episodes_ended_total", state="stopped", kind="question")) == 1
    assert value(gw, "eqa_gateway_episodes", state="running") == 0
    assert value(gw, "eqa_gateway_running_idle_seconds_max") == 0
    for service in ALL_SERVICES:
        assert value(gw, "eqa_gateway_service_instances", service=service) == (2 if service == "vlm_scorer" else 1)
    started = {s: [value(x, "eqa_service_started_seconds") for x in after[s]] for s in after}
    assert all(t > 0 for ts in started.values() for t in ts), started


def test_a_restart_is_counted_by_the_launcher_and_seen_as_a_new_start(fleet: Fleet):
    port = _ports(fleet)["vlm_scorer"][1]
    started = value(scrape(port), "eqa_service_started_seconds", service="vlm_scorer")
    launcher = fleet.settings.metrics_port
    restarts = value(scrape(launcher), "eqa_launcher_restarts_total", service="vlm_scorer")
    fleet.kill("vlm_scorer", 1)
    assert wait_for(lambda: not fleet.missing() and fleet.child("vlm_scorer", 1).alive, timeout=60, every=0.2)

    def restarted() -> bool:
        try:
            return value(scrape(port), "eqa_service_started_seconds", service="vlm_scorer") > started
        except httpx.HTTPError:
            return False

    assert wait_for(restarted, timeout=30, every=0.2)  # the same port: one scrape target per process
    assert value(scrape(launcher), "eqa_launcher_restarts_total", service="vlm_scorer") == restarts + 1


def _json_lines(path: Path) -> list[dict[str, Any]]:
    out = []
    for line in path.read_text().splitlines():
        if line.strip():
            out.append(json.loads(line))  # every line: a JSON object
    return out


def test_every_process_logs_json_lines_with_the_episode_context(fleet: Fleet):
    with httpx.Client(base_url=_gw(fleet), timeout=30) as client:
        eid, st, _ = _episode(fleet, client)
    assert st["state"] == "stopped"
    children = [c for c in fleet.children if c.service != "vlm_scorer"]

    def logged() -> bool:  # each process writes its lines of the episode's end after the end went out
        try:
            return all(any(r.get("episode") == eid for r in _json_lines(c.log_path))
                       for c in children if c.service in ("mapper", "planner", "stopper", "gateway"))
        except ValueError:  # a line being written; the final read below parses every line
            return False

    assert wait_for(logged, timeout=30, every=0.2), "a service logged nothing of the episode within 30 s"
    logs = {c.service: _json_lines(c.log_path) for c in children}
    for service, records in logs.items():
        assert records, service
        for r in records:
            assert {"time", "level", "logger", "message"} <= set(r), r
            assert r["time"].endswith("Z") and r["level"] in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
        assert {r.get("service") for r in records} >= {service}, service
    for service in ("sim", "mapper", "planner", "stopper", "gateway"):
        mine = [r for r in logs[service] if r.get("episode") == eid]
        assert mine or service == "sim", f"{service} logged nothing with episode {eid}"  # the sim: only trouble
        for r in mine:
            assert r["service"] == service and r["robot"] == "robot0", r
            assert "step" not in r or 0 <= r["step"] < STEPS, r
    # the planner logs each move it plans: its lines carry the step they are about
    planned = {r["step"] for r in logs["planner"] if r.get("episode") == eid and "step" in r}
    assert set(range(STEPS - 1)) <= planned, planned


def test_refusals_and_dropped_messages_are_counted(fleet: Fleet):
    """401 and 429 on the gateway are what the client received; malformed bus messages dropped by each
    subscriber are counted by reason."""
    with httpx.Client(base_url=_gw(fleet), timeout=30) as client:
        before = parse(client.get("/metrics").text)
        codes: dict[int, int] = {}
        for i in range(6):
            r = client.get("/v1/episodes", headers={"Authorization": f"Bearer wrong-{i}"})
            codes[r.status_code] = codes.get(r.status_code, 0) + 1
        assert set(codes) <= {401, 429} and codes.get(401, 0) >= 1, codes
        # /metrics from elsewhere: a proxied request needs a token; the metrics token or an admin token opens it
        proxied = {"X-Forwarded-For": "203.0.113.9"}
        assert client.get("/metrics", headers=proxied).status_code == 401
        assert client.get("/metrics", headers={**proxied, "Authorization": f"Bearer {TOKEN}"}).status_code == 401
        for token in (METRICS_TOKEN, ADMIN):
            assert client.get("/metrics", headers={**proxied, "Authorization": f"Bearer {token}"}).status_code == 200
        after = parse(client.get("/metrics").text)
    for code, n in codes.items():
        want = n + (2 if code == 401 else 0)  # the two refused /metrics requests
        got = value(after, "eqa_gateway_http_responses_total", method="GET", code=str(code)) - value(
            before, "eqa_gateway_http_responses_total", method="GET", code=str(code))
        assert got == want, (code, got, want)

    mapper = _ports(fleet)["mapper"][0]
    dropped_before = value(scrape(mapper), "eqa_bus_dropped_total", service="mapper", reason="malformed")
    garbage = [b"", b"\x00\xff garbage", b"\x81\xa4kind\xa5frame"]
    for payload in garbage:
        fleet.hub.publish_raw(keys.stream("robot0", keys.SIM_FRAME), payload)
    assert wait_for(lambda: value(scrape(mapper), "eqa_bus_dropped_total", service="mapper", reason="malformed")
                    - dropped_before == len(garbage), timeout=20, every=0.2)
