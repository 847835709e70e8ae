"""The walking skeleton, end to end: every service as its own process (the launcher), talking only over Zenoh;
garbage on every service's keys kills none of them; `eqa ask` answers through the gateway; a killed service is
restarted by the launcher and the fleet keeps answering.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

from eqa import keys
from eqa.bus import Bus
from eqa.health import check
from eqa.launcher import ALL_SERVICES, Fleet, free_port
from eqa.settings import Settings

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("fleet")
    settings = Settings(
        data_dir=data, zenoh_listen=[], zenoh_connect=[], sim_width=160, sim_height=120, record=True,
        gateway_port=free_port(), episode_timeout_s=60,
    )
    with Fleet(settings, services=ALL_SERVICES, scorers=2) as f:
        yield f


def _url(fleet: Fleet) -> str:
    return f"http://127.0.0.1:{fleet.settings.gateway_port}"


def test_services_are_separate_processes_with_liveliness(fleet: Fleet):
    pids = {c.proc.pid for c in fleet.children if c.proc is not None}
    assert len(pids) == len(fleet.children) == len(ALL_SERVICES) + 1  # two scorer replicas
    assert os.getpid() not in pids
    alive = fleet.hub.alive()
    for service in ALL_SERVICES:
        assert any(s == service for s, _ in alive), f"{service} holds no liveliness token"


def test_garbage_on_every_key_kills_no_service(fleet: Fleet):
    bus = fleet.hub
    garbage = [b"", b"\x00\xff garbage", b"\x81\xa4kind\xa5frame"]  # the last: a map with a bad frame
    for pair in (keys.EPISODE_START, keys.EPISODE_CANCEL, keys.EPISODE_END, keys.SIM_FRAME, keys.MAPPER_MAP,
                 keys.MAPPER_SCORES, keys.STOPPER_DECISION, keys.PLANNER_GOAL, keys.SIM_ERROR):
        for payload in garbage:
            bus.publish_raw(keys.stream("robot0", pair), payload)
    replies = bus.session.get(keys.SCORER_ANY, payload=b"junk", timeout=5.0)
    assert sum(1 for r in replies if r.ok is not None) == 2  # both replicas answered (with an error reply)
    time.sleep(1.0)
    assert all(c.alive for c in fleet.children), [c.history for c in fleet.children]
    assert not fleet.missing()


def _ask(fleet: Fleet, *extra: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, **{k: v for k, v in fleet.settings.env().items() if k in ("EQA_DATA_DIR",)}}
    return subprocess.run(
        [sys.executable, "-m", "eqa_app", "ask", "Is there a bed in the bedroom?", "--choice", "Yes",
         "--choice", "No", "--scene", "gen-00001", "--url", _url(fleet), *extra],
        capture_output=True, text=True, timeout=240, env=env, cwd=REPO,
    )


def test_eqa_ask_answers_through_the_gateway(fleet: Fleet):
    out = _ask(fleet, "--stop-rule", "max_steps", "--max-steps", "4")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "answer: " in out.stdout and "steps: 4 of 4" in out.stdout
    assert "recording:" in out.stdout
    status = httpx.get(f"{_url(fleet)}/v1/episodes", timeout=10).json()
    latest = status["episodes"][0]
    assert latest["state"] == "stopped" and latest["answer"] in ("A", "B")


def test_a_question_without_choices_is_answered_with_a_proposed_choice(fleet: Fleet):
    """Explore-EQA section VI-A: the scorer proposes the candidate answers; the answer names one of them."""
    env = {**os.environ, **{k: v for k, v in fleet.settings.env().items() if k in ("EQA_DATA_DIR",)}}
    out = subprocess.run(
        [sys.executable, "-m", "eqa_app", "ask", "Where is the bed?", "--scene", "gen-00001", "--url", _url(fleet),
         "--stop-rule", "max_steps", "--max-steps", "3"],
        capture_output=True, text=True, timeout=240, env=env, cwd=REPO,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "no choices: the scorer proposes" in out.stdout
    answer = next(line for line in out.stdout.splitlines() if line.startswith("answer: "))
    proposed = ("bedroom", "kitchen", "living room", "bathroom", "hallway", "dining room", "office", "garage",
                "laundry", "storage", "An option not listed here")
    assert any(p in answer for p in proposed) and not re.search(r"\) option [A-Z]$", answer), answer


def test_a_killed_service_is_restarted_and_the_fleet_goes_on(fleet: Fleet):
    before = fleet.child("planner").proc.pid  # type: ignore[union-attr]
    fleet.kill("planner")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        child = fleet.child("planner")
        if child.alive and child.proc.pid != before and not fleet.missing():  # type: ignore[union-attr]
            break
        time.sleep(0.2)
    else:
        pytest.fail("the planner was not restarted")
    out = _ask(fleet, "--stop-rule", "relevance", "--threshold", "0.99", "--max-steps", "3")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "steps: 3 of 3" in out.stdout


def test_a_second_peer_joins_with_client_settings(fleet: Fleet):
    # A session just opened has not heard of every peer yet (and a loaded machine answers the liveliness query
    # slowly): gather what each query sees until every service was seen or the deadline passes.
    seen: set[str] = set()
    with Bus(fleet.client_settings(), "probe", "probe") as bus:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not seen >= set(ALL_SERVICES):
            seen |= {s for s, _ in bus.alive()}
            time.sleep(0.2)
    assert seen >= set(ALL_SERVICES)


def test_eqa_health_from_another_process(fleet: Fleet):
    """`eqa health` in a fresh process (as compose runs it) sees every service of the fleet: it asks the
    launcher's router, which holds every token (eqa.health.check_settings)."""
    env = {**os.environ, "EQA_ZENOH_CONNECT": fleet.endpoint, "EQA_ZENOH_LISTEN": ""}
    cmd = [sys.executable, "-m", "eqa_app", "health", *ALL_SERVICES]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60, env=env, cwd=REPO)
    assert out.returncode == 0 and out.stdout.startswith("alive: "), out.stderr[-500:]
    out = subprocess.run([*cmd, "nosuch", "--timeout", "1"], capture_output=True, text=True, timeout=60, env=env,
                         cwd=REPO)
    assert out.returncode == 1 and "not alive: nosuch" in out.stderr and "EQA_ZENOH_CONNECT" in out.stderr


def test_eqa_health_sees_a_peer_too_busy_to_link(fleet: Fleet):
    """A service whose process gets no CPU for a while (a loaded machine, made certain here by SIGSTOP for less
    than the Zenoh lease) still holds its token at the router, so the check reports it alive. A check that had
    to link to every peer itself would wait on that peer's handshake and report it dead."""
    victim = fleet.child("stopper").proc
    assert victim is not None
    # the resume comes from a timer: a check waiting on the stopped peer's handshake blocks until it
    resume = threading.Timer(4.0, os.kill, (victim.pid, signal.SIGCONT))
    settings = fleet.settings.model_copy(update={"zenoh_connect": [fleet.endpoint], "zenoh_listen": []})
    os.kill(victim.pid, signal.SIGSTOP)
    resume.start()
    try:
        missing = check(settings, list(ALL_SERVICES), timeout=2.0)
    finally:
        resume.cancel()
        os.kill(victim.pid, signal.SIGCONT)
    assert missing == []


@pytest.mark.parametrize(
    "args, message",
    [
        (["q?", "--choice", "a", "--scene", "gen-00001"], "between 2 and 26"),
        (["q?", *[a for i in range(27) for a in ("--choice", f"c{i}")], "--scene", "gen-00001"], "between 2 and 26"),
        (["q?", "--choice", "a", "--choice", "b", "--scene", "no-such-scene"], "unknown scene"),
        (["q?", "--choice", "a", "--choice", "b", "--scene", "gen-00001", "--pose", "1,x"], "pose must be numbers"),
        (["q?", "--choice", "a", "--choice", "b", "--scene", "gen-00001", "--eps", "1.5"], "--eps"),
        (["q?", "--choice", "a", "--choice", "b", "--scene", "gen-00001", "--home", "my flat"], "--home"),
        # a fleet whose scorer could only answer errors is refused before it starts
        (["EQA_SCORER_BACKEND=hf", "EQA_HF_MODEL_PATH=/no/such/model"], "set EQA_HF_MODEL_PATH"),
        (["EQA_SCORER_BACKEND=remote"], "EQA_REMOTE_BASE_URL"),
    ],
)
def test_eqa_ask_bad_input_is_one_line_and_exit_2(tmp_path: Path, args: list[str], message: str):
    env = {**os.environ, "EQA_DATA_DIR": str(tmp_path)}
    env.update(a.split("=", 1) for a in args if a.startswith("EQA_"))
    args = [a for a in args if not a.startswith("EQA_")]
    out = subprocess.run([sys.executable, "-m", "eqa_app", "ask", *args], capture_output=True, text=True,
                         timeout=120, env=env, cwd=REPO)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in out.stderr
