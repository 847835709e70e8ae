"""Task episodes in the planner service over real Zenoh: MapUpdate.objects and the sim's skill
outcome in, goals with skill / target / phase out; a planner restarted mid-task continues it."""

from __future__ import annotations

import math
import queue
import time

import numpy as np
import pytest

from eqa import keys
from eqa.bus import Bus
from eqa.messages import (
    Decision,
    EpisodeStart,
    GazePoint,
    Goal,
    GridSpec,
    MapUpdate,
    ObjectInstance,
    Pose2D,
    Question,
    SkillReport,
    StopConfig,
    Task,
)
from services.planner.service import PlannerService

EP, ROBOT = "ep-pt", "r0"
GRID = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=100, cols=100)


def _start() -> EpisodeStart:
    task = Task(kind="pick_place", text="Move the mug from the table to the counter", scene="gen-1", object="mug",
                start_receptacle="table", goal_receptacle="counter")
    return EpisodeStart(episode_id=EP, robot=ROBOT, question=Question(text=task.text, scene="gen-1"), max_steps=40,
                        record=False, stop=StopConfig(rule="max_steps"), task=task, pick_limit=5)


def _map(step: int, pose: Pose2D, skill: SkillReport | None = None) -> MapUpdate:
    occ = np.zeros((100, 100), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    g = GazePoint(x=3.0, y=4.2, yaw=math.pi / 2, pitch=-0.5, psi_prime=0.7, ig=0.5)
    mug = ObjectInstance(instance_id=20, cls="mug", S=0.7, U=0.1, psi=0.6, centre=(3.0, 5.0, 0.8),
                         extent=(0.1, 0.1, 0.1), n_gaussians=30, scores={"mug": (0.7, 0.1, 0.6)}, gaze=[g])
    return MapUpdate(episode_id=EP, step=step, grid=GRID, occupied=occ, free=~occ, explored=np.ones_like(occ),
                     pose=pose, objects=[mug], skill=skill)


def _decision(step: int) -> Decision:
    return Decision(episode_id=EP, step=step, rule="max_steps", stop=False, reason="go on")


def test_planner_runs_the_task_machine_and_survives_a_restart(hub_settings, settings) -> None:
    goals: queue.Queue[Goal] = queue.Queue()
    with Bus(hub_settings, "gateway", "test") as bus:
        bus.subscribe(keys.stream(ROBOT, keys.PLANNER_GOAL), Goal, lambda _k, m: goals.put(m))
        svc = PlannerService(settings)
        svc.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), _start())
            bus.publish(keys.stream(ROBOT, keys.MAPPER_MAP), _map(0, Pose2D(x=3.0, y=2.0)))
            bus.publish(keys.stream(ROBOT, keys.STOPPER_DECISION), _decision(0))
            g0 = goals.get(timeout=20.0)
            assert (g0.step, g0.skill, g0.target, g0.phase) == (0, "pick", 20, "picking")
            # the skill pose: SKILL_APPROACH_M (0.6 m) from the mug's centre (3, 5) towards its gaze point (3, 4.2)
            assert g0.pose is not None and (g0.pose.x, g0.pose.y) == pytest.approx((3.0, 4.4))
        finally:
            svc.stop()
        # a new planner process: the machine (pick attempts, phase) comes back from the store
        svc2 = PlannerService(settings)
        svc2.start()
        try:
            time.sleep(0.5)
            picked = SkillReport(skill="pick", success=True, target=20, reason="picked mug")
            bus.publish(keys.stream(ROBOT, keys.MAPPER_MAP), _map(1, g0.pose, picked))
            bus.publish(keys.stream(ROBOT, keys.STOPPER_DECISION), _decision(1))
            g1 = goals.get(timeout=20.0)
            # holding the mug, no counter seen and nothing left to explore: it looks around before it gives up
            assert g1.step == 1 and not g1.done and g1.phase == "searching" and "no frontier" in g1.reason
            assert "turning in place to look around" in g1.reason
            task = svc2.episode(EP)
            assert task is not None and task.task is not None and task.task.machine.holding
            assert task.task.machine.budget.attempts == 1
        finally:
            svc2.stop()
