"""Task episodes in the stopper over real Zenoh: the planner's done ends them with the sim's phase
metrics in EpisodeEnd.metrics and no answer; question episodes are untouched."""

from __future__ import annotations

import threading

from support.fleet import wait_for

from eqa import keys
from eqa.bus import Bus
from eqa.messages import Decision, EpisodeEnd, EpisodeStart, Goal, Question, StepScores, StopConfig, Task
from eqa.settings import Settings
from eqa.store import open_store, task_metrics_key
from services.stopper.service import StopperService

ROBOT = "r0"


def _task_start(eid: str) -> EpisodeStart:
    task = Task(kind="find_object", text="Find a mug", scene="gen-1", object="mug", object_ids=[3])
    return EpisodeStart(episode_id=eid, robot=ROBOT, question=Question(text=task.text, scene="gen-1"),
                        max_steps=20, record=False, stop=StopConfig(rule="max_steps"), task=task)


def test_a_task_episode_ends_on_the_planners_done_with_its_metrics(hub_settings: Settings,
                                                                     settings: Settings) -> None:
    ends: list[EpisodeEnd] = []
    decisions: list[Decision] = []
    lock = threading.Lock()
    store = open_store(settings)
    with Bus(hub_settings, "gateway", "test") as bus:
        def on_end(_k: str, m: EpisodeEnd) -> None:
            with lock:
                ends.append(m)

        bus.subscribe(keys.stream(ROBOT, keys.EPISODE_END), EpisodeEnd, on_end)
        bus.subscribe(keys.stream(ROBOT, keys.STOPPER_DECISION), Decision, lambda _k, m: decisions.append(m))
        svc = StopperService(settings)
        svc.start()
        try:
            # the first messages wait until this bus sees the stopper's liveliness token, which it declares after
            # its subscriptions (published at once, they could reach no subscriber on a loaded machine)
            assert wait_for(lambda: bool(bus.alive(keys.alive_service("stopper"), timeout=0.5)), timeout=15.0)
            # the sim writes the metrics before its first frame; scores of two steps, then the planner's done
            store.set_json(task_metrics_key("ep-t1"), {"SR": 1.0, "SPL": 0.8, "collisions": 0.0})
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), _task_start("ep-t1"))
            for step in range(2):
                sc = StepScores(episode_id="ep-t1", step=step, answer_probs=[0.6, 0.4], relevance=0.5,
                                backend="test", choices=["A mug", "No mug"])
                bus.publish(keys.stream(ROBOT, keys.MAPPER_SCORES), sc)
            done = Goal(episode_id="ep-t1", step=1, done=True, reason="stopped near a mug", phase="finished")
            assert wait_for(lambda: any(d.step == 1 for d in decisions), timeout=15.0)
            assert not any(d.stop for d in decisions)  # a task never stops on scores before its step limit
            bus.publish(keys.stream(ROBOT, keys.PLANNER_GOAL), done)
            assert wait_for(lambda: len(ends) >= 1, timeout=15.0)
        finally:
            svc.stop()
    end = ends[0]
    assert end.state == "stopped" and end.reason == "task ended: stopped near a mug"
    assert end.metrics == {"SR": 1.0, "SPL": 0.8, "collisions": 0.0} and end.answer is None
