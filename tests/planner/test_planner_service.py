"""The planner service over real Zenoh: waits for map + decision, publishes goals, handles sim refusals."""

from __future__ import annotations

import math
import queue
import time
from collections.abc import Iterator

import numpy as np
import pytest

from eqa import keys
from eqa.bus import Bus
from eqa.messages import (
    Decision,
    EpisodeStart,
    ErrorReply,
    Frontier,
    Goal,
    MapUpdate,
    Pose2D,
    Question,
)
from eqa.settings import Settings
from services.planner.service import PlannerService
from services.planner.synthetic import rooms_map

ROBOT = "r0"
EP = "ep-plan"


@pytest.fixture
def rig(
    hub_settings: Settings, settings: Settings
) -> Iterator[tuple[Bus, PlannerService, queue.Queue[Goal]]]:
    hub = Bus(hub_settings, "gateway", "hub").open()
    svc = PlannerService(settings.model_copy(update={"record": True}))
    goals: queue.Queue[Goal] = queue.Queue()
    hub.subscribe(keys.stream(ROBOT, keys.PLANNER_GOAL), Goal, lambda _k, g: goals.put(g))
    svc.start()
    try:
        deadline = time.monotonic() + 10
        while not hub.alive(keys.alive_service("planner"), timeout=0.5):
            assert time.monotonic() < deadline, "planner never came up"
        time.sleep(0.3)
        yield hub, svc, goals
    finally:
        svc.stop()
        hub.close()


def _map(step: int, pose: Pose2D, frontiers: list[Frontier]) -> MapUpdate:
    grid, free, occ = rooms_map(np.random.default_rng(0), width_m=10, height_m=8, furniture=0)
    return MapUpdate(
        episode_id=EP,
        step=step,
        grid=grid,
        occupied=occ,
        free=free,
        explored=free.copy(),
        frontiers=frontiers,
        pose=pose,
    )


def _decision(step: int, stop: bool = False) -> Decision:
    return Decision(episode_id=EP, step=step, rule="cp", stop=stop, reason="stop" if stop else "go on")


def _get(goals: queue.Queue[Goal], timeout: float = 15.0) -> Goal:
    return goals.get(timeout=timeout)


def test_goal_after_map_and_decision_in_any_order_refusal_and_stop(rig) -> None:
    hub, svc, goals = rig
    pub = lambda pair, msg: hub.publish(keys.stream(ROBOT, pair), msg)  # noqa: E731
    q = Question(text="Where is the sofa?", choices=["kitchen", "bedroom"], scene="synthetic")
    pub(
        keys.EPISODE_START,
        EpisodeStart(episode_id=EP, robot=ROBOT, question=q, strategy="semantic", max_steps=20, seed=5),
    )
    frs = [
        Frontier(x=8.5, y=6.5, nx=1, ny=0, size=9, weight=2.0),
        Frontier(x=1.0, y=6.5, nx=-1, ny=0, size=9, weight=1.0),
        Frontier(x=8.5, y=1.0, nx=1, ny=0, size=9, weight=float("nan")),
    ]
    pose = Pose2D(x=1.5, y=1.5)
    # map first, then decision
    pub(keys.MAPPER_MAP, _map(0, pose, frs))
    time.sleep(0.2)
    assert goals.empty(), "the planner must wait for the decision"
    pub(keys.STOPPER_DECISION, _decision(0))
    g0 = _get(goals)
    assert g0.step == 0 and not g0.done and g0.pose is not None
    assert len(g0.weights) == 3 and g0.weights[2] == 0.0 and math.isclose(sum(g0.weights), 1.0)
    assert g0.path[0] == (1.5, 1.5) and g0.path[-1] == (g0.pose.x, g0.pose.y)
    assert math.hypot(g0.pose.x - 1.5, g0.pose.y - 1.5) <= 3.0 + 1e-9
    assert g0.frontier is not None and "invalid weight" in g0.reason
    # the simulator refuses it: another goal for the same step, away from the refused pose
    hub.publish(
        keys.stream(ROBOT, keys.SIM_ERROR),
        ErrorReply(source="sim", episode_id=EP, step=0, reason="pose in collision"),
    )
    g0b = _get(goals)
    assert g0b.step == 0 and not g0b.done and g0b.pose is not None
    assert math.hypot(g0b.pose.x - g0.pose.x, g0b.pose.y - g0.pose.y) > 0.3
    # garbage on the map key is dropped, the service goes on
    hub.publish_raw(keys.stream(ROBOT, keys.MAPPER_MAP), b"\x01not msgpack")
    # decision first, then map
    pose1 = g0b.pose
    pub(keys.STOPPER_DECISION, _decision(1))
    time.sleep(0.2)
    assert goals.empty()
    pub(keys.MAPPER_MAP, _map(1, pose1, frs))
    g1 = _get(goals)
    assert g1.step == 1 and not g1.done
    # step 1 sent again (the goal was lost): the same goal is published again, not a new plan
    pub(keys.MAPPER_MAP, _map(1, pose1, frs))
    assert _get(goals) == g1
    pub(keys.STOPPER_DECISION, _decision(1))
    assert _get(goals) == g1
    # an older step sent again is ignored
    pub(keys.MAPPER_MAP, _map(0, pose, frs))
    svc.drain()
    time.sleep(0.2)
    assert goals.empty()
    # the stopper stops at step 2: no goal
    pub(keys.MAPPER_MAP, _map(2, g1.pose, frs))
    pub(keys.STOPPER_DECISION, _decision(2, stop=True))
    svc.drain()
    time.sleep(0.3)
    assert goals.empty()
    # Rerun recording written for the episode
    assert (svc.settings.recordings_path / EP / "planner.rrd").exists()


def test_nothing_to_explore_ends_with_a_reason_and_bad_robot_pose(rig) -> None:
    hub, _svc, goals = rig
    pub = lambda pair, msg: hub.publish(keys.stream(ROBOT, pair), msg)  # noqa: E731
    q = Question(text="Is the tv on?", choices=["yes", "no"], scene="synthetic")
    pub(
        keys.EPISODE_START,
        EpisodeStart(episode_id=EP, robot=ROBOT, question=q, strategy="fbe", max_steps=20, record=False),
    )
    pose = Pose2D(x=2.0, y=2.0)
    turns = 0
    for step in range(10):
        pub(keys.MAPPER_MAP, _map(step, pose, []))
        pub(keys.STOPPER_DECISION, _decision(step))
        g = _get(goals)
        assert g.step == step
        if g.done:
            assert "fully explored" in g.reason and g.pose is None
            break
        turns += 1
        assert (g.pose.x, g.pose.y) == (pose.x, pose.y) and "turning in place" in g.reason
        pose = g.pose
    else:
        pytest.fail("never ended")
    assert turns == 6
    # a new episode whose robot stands outside the map
    pub(
        keys.EPISODE_START,
        EpisodeStart(
            episode_id="ep-out", robot=ROBOT, question=q, strategy="fbe", max_steps=20, record=False
        ),
    )
    m = _map(0, Pose2D(x=300.0, y=2.0), [Frontier(x=2.0, y=2.0, nx=1, ny=0, size=4)])
    pub(keys.MAPPER_MAP, m.model_copy(update={"episode_id": "ep-out"}))
    pub(keys.STOPPER_DECISION, _decision(0).model_copy(update={"episode_id": "ep-out"}))
    g = _get(goals)
    assert g.episode_id == "ep-out" and g.done and "outside the map" in g.reason


def test_a_restarted_planner_plans_the_next_step_as_the_first_would_have(hub_settings, settings) -> None:
    """Strategy, seed and the committed target survive a restart (store), so step 1's goal is identical."""
    q = Question(text="Where is the sofa?", choices=["kitchen", "bedroom"], scene="synthetic")
    start = EpisodeStart(episode_id=EP, robot=ROBOT, question=q, strategy="fbe", max_steps=20, seed=9, record=False)
    # many far frontiers: re-sampling after a lost memory (other seed, no committed target) picks another one
    frs = [Frontier(x=x, y=y, nx=1, ny=0, size=9) for x, y in
           ((8.5, 6.5), (1.0, 6.5), (8.5, 1.0), (5.0, 7.0), (9.0, 4.0), (4.0, 6.8), (7.0, 7.0), (9.2, 2.5))]

    def run(restart: bool) -> Goal:
        store_dir = settings.data_dir / ("restart" if restart else "straight")
        s = settings.model_copy(update={"data_dir": store_dir})
        goals: queue.Queue[Goal] = queue.Queue()
        with Bus(hub_settings, "gateway", "hub") as hub:
            hub.subscribe(keys.stream(ROBOT, keys.PLANNER_GOAL), Goal, lambda _k, g: goals.put(g))
            svc = PlannerService(s)
            svc.start()
            time.sleep(0.5)
            hub.publish(keys.stream(ROBOT, keys.EPISODE_START), start)
            hub.publish(keys.stream(ROBOT, keys.MAPPER_MAP), _map(0, Pose2D(x=1.5, y=1.5), frs))
            hub.publish(keys.stream(ROBOT, keys.STOPPER_DECISION), _decision(0))
            g0 = _get(goals)
            if restart:
                svc.stop()  # everything in memory is gone
                svc = PlannerService(s)
                svc.start()
                time.sleep(0.5)
            hub.publish(keys.stream(ROBOT, keys.MAPPER_MAP), _map(1, g0.pose, frs))
            hub.publish(keys.stream(ROBOT, keys.STOPPER_DECISION), _decision(1))
            g1 = _get(goals)
            svc.stop()
        return g1

    straight, restarted = run(False), run(True)
    assert restarted.step == 1 and restarted.pose == straight.pose and restarted.frontier == straight.frontier
