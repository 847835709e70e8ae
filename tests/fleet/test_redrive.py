"""Recovery without the resend timer: when an instance of a stateful service vanishes or (re)appears, the sim
sends the current frame of each robot whose owner changed again (eqa.sharding.Redrive), so a step lost with a
killed process is driven again as soon as someone can take it. The fleet test runs with
``EQA_STEP_RESEND_S=0`` (the sim never resends on its own): without the re-drive an episode whose step died
with a process would stand still until the watchdog."""

from __future__ import annotations

import os
import random
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from support.exactly_once import StepLedger, wait_on
from support.fleet import wait_for

from eqa import keys, sharding
from eqa.launcher import PIPELINE, Fleet
from eqa.messages import EpisodeEnd, EpisodeStart, Frame, Question, StopConfig
from eqa.settings import Settings
from eqa.sharding import Redrive

STEPS = 10
SCENE = "gen-00001"


def test_redrive_schedules_the_robots_whose_owner_changed_and_hands_them_out_in_time():
    robots = {f"r{i}": ("ep", i) for i in range(40)}
    rd = Redrive(["mapper", "planner"], after_s=(0.3, 2.0))
    assert rd.changed("scorer", "x", True, robots, 0.0) == set()  # not watched
    first = rd.changed("mapper", "m-a", True, robots, 0.0)
    assert first == set(robots)  # from nobody to m-a: every robot has a new owner
    assert rd.due(0.1) == {} and rd.due(0.35) == robots and rd.due(1.0) == {}
    assert rd.due(2.5) == robots and rd.pending() == 0  # the second send, then nothing more
    joined = rd.changed("mapper", "m-b", True, robots, 10.0)
    assert joined == {r for r in robots if sharding.owner(r, ["m-a", "m-b"]) == "m-b"}
    assert set(rd.due(10.3)) == joined and set(rd.due(12.1)) == joined
    # m-b up again while live: a process restarted under its name, whose predecessor's steps in flight are lost
    assert rd.changed("mapper", "m-b", True, robots, 15.0) == joined
    assert set(rd.due(15.3)) == joined
    assert rd.changed("mapper", "m-c", False, robots, 16.0) == set()  # never live: nothing scheduled
    left = rd.changed("mapper", "m-a", False, robots, 20.0)  # m-a dies: its robots go to m-b
    assert left == set(robots) - joined
    assert rd.live("mapper") == {"m-b"} and rd.live("planner") == frozenset()


class Run:
    def __init__(self) -> None:
        self.ends: dict[str, EpisodeEnd] = {}
        self.last: dict[str, int] = {}
        self.cond = threading.Condition()

    def on_end(self, _key: str, msg: EpisodeEnd) -> None:
        with self.cond:
            self.ends.setdefault(msg.episode_id, msg)
            self.cond.notify_all()

    def on_frame(self, _key: str, msg: Frame) -> None:
        with self.cond:
            self.last[msg.episode_id] = max(msg.step, self.last.get(msg.episode_id, -1))
            self.cond.notify_all()

    @classmethod
    def watching(cls, hub: Any) -> tuple[Run, StepLedger]:
        """A run and a step ledger subscribed to the fleet's ends, frames and step outputs through ``hub``."""
        run, ledger = cls(), StepLedger()
        hub.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, run.on_end)
        hub.subscribe(keys.any_robot(keys.SIM_FRAME), Frame, run.on_frame)
        ledger.subscribe(hub)
        return run, ledger

    def wait(self, pred, timeout: float) -> bool:
        return wait_on(self.cond, pred, timeout)

    def start_mid_step(self, hub: Any, eid: str, steps: int, seed: int, service: str) -> None:
        """Start a ``steps``-step episode on robot0 (max_steps rule) and return once its step 3 is sent, at a
        moment within that step drawn from ``service`` (a kill then lands somewhere inside the step)."""
        q = Question(text="Is there a bed in the bedroom?", choices=["Yes", "No"], scene=SCENE)
        hub.publish(keys.stream("robot0", keys.EPISODE_START),
                    EpisodeStart(episode_id=eid, robot="robot0", question=q, max_steps=steps,
                                 stop=StopConfig(rule="max_steps"), seed=seed, record=False))
        assert self.wait(lambda: self.last.get(eid, -1) >= 3, 120), self.last.get(eid)
        time.sleep(random.Random(service).uniform(0.0, 0.15))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory, redis_url: str):
    from services.sim.library import load_or_generate

    data = tmp_path_factory.mktemp("redrive")
    settings = Settings(data_dir=data, redis_url=redis_url, zenoh_listen=[], zenoh_connect=[], sim_width=160,
                        sim_height=120, record=False, step_resend_s=0.0, episode_timeout_s=300.0)
    load_or_generate(SCENE, settings.scenes_path)
    with Fleet(settings, services=PIPELINE, scorers=1, max_restarts=10) as f:
        run, ledger = Run.watching(f.hub)
        time.sleep(0.5)
        yield f, run, ledger


@pytest.mark.parametrize("service", ["mapper", "planner", "stopper", "sim"])
def test_an_episode_goes_on_after_a_kill_with_no_resend_timer(fleet, service: str, tmp_path: Path) -> None:
    f, run, ledger = fleet
    f.wait_alive(timeout=120)
    eid = f"redrive-{service}-{os.getpid()}-{time.time_ns()}"
    run.start_mid_step(f.hub, eid, STEPS, 3, service)
    before = f.child(service).proc.pid  # type: ignore[union-attr]
    f.kill(service)
    ended = run.wait(lambda: eid in run.ends, 180)
    logs = {c.instance: c.log_path.read_text(errors="replace")[-2000:] for c in f.children if c.service == service}
    assert ended, f"episode stuck at step {run.last.get(eid)} after the {service} kill; {logs}"
    end = run.ends[eid]
    assert end.state == "stopped" and end.steps == STEPS, end
    # the episode may end before the killed process is replaced (a kill in its last step): bounded wait
    assert wait_for(lambda: (p := f.child(service).proc) is not None and p.pid != before, 15.0), \
        f.child(service).history
    assert not (problems := ledger.settled_problems({eid: STEPS})), problems
