"""Robots shared among several instances of every stateful service, through the real fleet: 2 sims,
3 mappers, 2 planners, 3 stoppers and 2 scorer replicas as separate processes over Zenoh with Redis; 6 robots
run 8-step episodes at once while a mapper and a stopper are killed with SIGKILL (their launcher restarts
them), a sim is killed, and a new planner instance joins mid-run.

Exactly once is checked on what the services publish (tests/support/exactly_once.py): a step integrated (mapper),
decided (stopper) or planned (planner) by two instances shows two outputs made at different times, while an
answer re-published for a resent step keeps its time or says it integrated nothing. Every step of every
episode must have exactly one. With ``EQA_SHARD=false`` every instance acts on every robot and this test
fails."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from support.exactly_once import Ends, StepLedger
from support.fleet import wait_for

from eqa import keys
from eqa.launcher import PIPELINE, Fleet
from eqa.messages import EpisodeEnd, EpisodeStart, Question, StopConfig
from eqa.settings import Settings
from eqa.sharding import CLAIM_PREFIX
from eqa.store import RedisStore

REPO = Path(__file__).resolve().parents[2]
ROBOTS = [f"shard{i}" for i in range(6)]
STEPS = 8
SCENE = "gen-00001"


def test_every_step_once_with_several_instances_through_kills_and_a_join(tmp_path: Path, redis_url: str):
    from services.sim.library import load_or_generate

    settings = Settings(data_dir=tmp_path / "var", redis_url=redis_url, zenoh_listen=[], zenoh_connect=[],
                        record=False, sim_width=160, sim_height=120, step_resend_s=5.0, log_level="INFO")
    load_or_generate(SCENE, settings.scenes_path)
    instances = {"sim": 2, "mapper": 3, "planner": 2, "stopper": 3}
    watch = Ends()
    ledger = StepLedger()
    joined: subprocess.Popen[bytes] | None = None
    with Fleet(settings, services=PIPELINE, scorers=2, instances=instances) as fleet:
        bus = fleet.hub
        ledger.subscribe(bus)
        bus.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, watch)
        time.sleep(0.5)
        q = Question(text="Is there a bed in the bedroom?", choices=["Yes", "No"], scene=SCENE)
        starts = [EpisodeStart(episode_id=f"shard-{i}-{os.getpid()}-{int(time.time())}", robot=r, question=q,
                               max_steps=STEPS, stop=StopConfig(rule="max_steps"), seed=i, record=False)
                  for i, r in enumerate(ROBOTS)]
        for st in starts:
            bus.publish(keys.stream(st.robot, keys.EPISODE_START), st)
        try:
            time.sleep(1.5)
            fleet.kill("mapper", 0)     # SIGKILL; the launcher restarts it (a leave, then a join)
            fleet.kill("stopper", 1)
            time.sleep(1.5)
            instance = f"planner-joined-{os.getpid()}"
            env = fleet._child_env("planner", instance)
            log = open(tmp_path / "planner-joined.log", "wb")  # noqa: SIM115 - handed to the child
            joined = subprocess.Popen([sys.executable, "-m", "services.planner"], env=env, stdout=log,
                                      stderr=subprocess.STDOUT, start_new_session=True, cwd=REPO)
            log.close()
            fleet.kill("sim", 1)
            ids = {s.episode_id for s in starts}
            ok = wait_for(lambda: ids <= set(watch.ends), 120, every=0.1)
            assert ok, f"ended: {sorted(watch.ends)} of {sorted(ids)}; restarts: " + str(
                {c.instance: c.history for c in fleet.children if c.history})
            # the episodes may end before the launcher has restarted the last killed instance (backoff): wait
            # for it inside the fleet, so the check below sees the restarts and not a race with them
            wait_for(lambda: {c.service for c in fleet.children if c.restarts} >= {"mapper", "stopper", "sim"}, 30,
                     every=0.1)
        finally:
            if joined is not None and joined.poll() is None:
                os.killpg(joined.pid, signal.SIGTERM)
                joined.wait(timeout=15)
    assert {c.service for c in fleet.children if c.restarts} >= {"mapper", "stopper", "sim"}
    bad = {e: (m.state, m.reason) for e, m in watch.ends.items() if e in ids and m.state != "stopped"}
    assert not bad, bad
    assert all(watch.ends[eid].steps == STEPS for eid in ids)
    store = RedisStore(redis_url)  # the claims of ended episodes are deleted, not left to expire

    def left() -> list[str]:
        return [k for k in store.keys(CLAIM_PREFIX) if k.endswith(":holder") and any(e in k for e in ids)]

    try:
        assert wait_for(lambda: not left(), 10, every=0.1), left()[:20]
    finally:
        store.close()
    problems = ledger.problems({eid: STEPS for eid in ids})
    assert not problems, problems
