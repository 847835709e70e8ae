"""A step whose instance dies half-way is taken over and computed exactly once: real mapper processes over real
Zenoh and Redis, one of them killed with SIGKILL at a chosen point of a step (right after it claimed the step,
or after it stored the map and before it published the update). The test plays the simulator: it sends each
frame and sends it again while no map update comes back (as the sim does after ``EQA_STEP_RESEND_S``).
Exactly once is read from what the mappers publish (tests/support/exactly_once.py): one integration of a step is one
``MapUpdate`` with its timings and one ``sent_at``, however often it is published."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from support.exactly_once import StepLedger
from support.fleet import wait_for
from support.mapper import Collector, frame, start_msg

from eqa import keys, sharding
from eqa.bus import Bus
from eqa.settings import Settings
from services.sim.library import load_or_generate
from services.sim.render import Renderer

REPO = Path(__file__).resolve().parents[2]
STEPS = 5
KILL_STEP = 2
ROBOT = "r0"  # the robot of test_mapper_service's frames and starts

# A mapper process that SIGKILLs itself at one point of step KILL_STEP: "claim" right after it won the step's
# claim (nothing computed), "publish" when it is about to publish the step's map update (the map is stored).
_MAPPER = """
import os, signal, sys
from eqa import sharding
from eqa.bus import Bus
from eqa.settings import Settings
from services.mapper.service import MapperService

point, kill_step = sys.argv[1], int(sys.argv[2])

def die():
    os.kill(os.getpid(), signal.SIGKILL)

claim = sharding.StepClaims.claim
def claim_then_die(self, episode_id, step):
    got = claim(self, episode_id, step)
    if point == "claim" and step == kill_step and got.won:
        die()
    return got
sharding.StepClaims.claim = claim_then_die

publish = Bus.publish
def die_before_publish(self, key, msg):
    if point == "publish" and key.endswith("/mapper/map") and getattr(msg, "step", None) == kill_step:
        die()
    publish(self, key, msg)
Bus.publish = die_before_publish

MapperService(Settings()).run_forever()
"""


def _instances() -> tuple[str, str]:
    """Two instance names of which the first owns ROBOT (rendezvous hashing), so the first is the one killed."""
    a, b = "mapper-a", "mapper-b"
    return (a, b) if sharding.owner(ROBOT, [a, b]) == a else (b, a)


class Mappers:
    def __init__(self, settings: Settings, redis_url: str, logs: Path) -> None:
        self.env = {**os.environ, **settings.env(), "EQA_REDIS_URL": redis_url, "EQA_SCORER_TIMEOUT_S": "0.5",
                    "EQA_RECORD": "false", "PYTHONPATH": str(REPO)}
        self.logs = logs
        self.procs: list[subprocess.Popen[bytes]] = []

    def start(self, instance: str, point: str = "none") -> subprocess.Popen[bytes]:
        env = {**self.env, "EQA_INSTANCE": instance}
        log = (self.logs / f"{instance}.log").open("ab")
        proc = subprocess.Popen([sys.executable, "-c", _MAPPER, point, str(KILL_STEP)], cwd=REPO, env=env,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()
        self.procs.append(proc)
        return proc

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
        for proc in self.procs:
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)


def _alive(bus: Bus) -> set[str]:
    return {inst for _, inst in bus.alive(keys.alive_service("mapper"), timeout=0.5)}


@pytest.fixture(scope="module")
def renderer(tmp_path_factory: pytest.TempPathFactory) -> Renderer:
    return Renderer(load_or_generate("gen-00007", Path(tmp_path_factory.mktemp("scenes"))))


@pytest.mark.parametrize("point,successor", [("claim", "other"), ("publish", "other"), ("publish", "restarted")])
def test_a_step_whose_mapper_dies_is_computed_once(point: str, successor: str, hub_settings: Settings,
                                                   settings: Settings, redis_url: str, renderer: Renderer,
                                                   tmp_path: Path) -> None:
    victim, other = _instances()
    eid = f"takeover-{point}-{successor}-{os.getpid()}-{time.time_ns()}"
    ledger = StepLedger()
    mappers = Mappers(settings, redis_url, tmp_path)
    with Bus(hub_settings, "sim", "test-sim") as bus:
        got = Collector(bus)
        ledger.subscribe(bus)
        try:
            doomed = mappers.start(victim, point)
            if successor == "other":
                mappers.start(other)
            want = {victim, other} if successor == "other" else {victim}
            assert wait_for(lambda: _alive(bus) == want, 60), _alive(bus)
            time.sleep(0.5)  # their subscriptions reach this session
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_msg(eid))
            for k in range(STEPS):
                f = frame(renderer, eid, k)
                bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), f)
                deadline = time.monotonic() + 90
                while True:
                    try:
                        m = got.maps.get(timeout=2.0)
                    except Exception:  # no update yet: send the frame again, as the sim does
                        assert time.monotonic() < deadline, f"no map update of step {k}"
                        if k == KILL_STEP and doomed.poll() is not None and successor == "restarted" \
                                and len(mappers.procs) == 1:
                            assert wait_for(lambda: victim not in _alive(bus), 15)
                            mappers.start(victim)  # the launcher restarts it under its name
                            assert wait_for(lambda: victim in _alive(bus), 60)
                            time.sleep(0.5)
                        bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), f)
                        continue
                    if m.episode_id == eid and m.step == k:
                        break
            assert doomed.poll() == -signal.SIGKILL  # it did die at the chosen point
        finally:
            mappers.close()
        time.sleep(0.5)
    logs = "\n".join(p.read_text(errors="replace")[-1500:] for p in tmp_path.glob("*.log"))
    problems = [p for p in ledger.problems({eid: STEPS}) if p.startswith("mapper/map")]
    assert not problems, f"{problems}\n{logs}"
