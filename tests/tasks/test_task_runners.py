"""The sim's and the planner's task runners (the parts of the shells for task episodes), with real messages."""

from __future__ import annotations

import json
import math

import numpy as np
from test_sim_tasks import _frame_ids, _mug_task, _room_scene

from eqa.messages import (
    EpisodeStart,
    GazePoint,
    Goal,
    GridSpec,
    MapUpdate,
    ObjectInstance,
    Pose2D,
    Question,
    SkillReport,
    decode,
    encode,
)
from services.planner.step import Memory
from services.planner.task_fsm import Thresholds
from services.planner.task_runner import PlannerTask
from services.sim.task_runner import SimTask


def _start(**kw: object) -> EpisodeStart:
    task = _mug_task()
    q = Question(text=task.text, scene=task.scene)
    return EpisodeStart(episode_id="ep-t", robot="r0", question=q, max_steps=50, task=task, **kw)  # type: ignore[arg-type]


def test_sim_task_runs_the_goal_skill_on_the_frame_at_the_goal() -> None:
    room = _room_scene()
    assert SimTask.from_start(EpisodeStart(episode_id="e", robot="r", question=Question(text="q?", scene="x"),
                                           max_steps=3)) is None
    sim = SimTask.from_start(_start(pick_limit=5))
    assert sim is not None
    before = Pose2D(x=0.8, y=2.5)
    goal = Goal(episode_id="ep-t", step=3, pose=Pose2D(x=1.7, y=2.5), path=[(1.2, 2.5)], skill="pick", target=7)
    rep = sim.after_goal(room, before, goal, _frame_ids(room, goal.pose))
    assert rep is not None and rep.success and rep.target == 7 and rep.skill == "pick"
    sim.observe(room, goal.pose, _frame_ids(room, goal.pose))
    place = Goal(episode_id="ep-t", step=4, pose=Pose2D(x=1.4, y=2.3), skill="place")
    assert sim.after_goal(room, goal.pose, place, _frame_ids(room, place.pose)).success
    again = SimTask.from_json(json.loads(json.dumps(sim.to_json())))
    assert again.metrics() == sim.metrics() and sim.metrics()["SR"] == 1.0
    assert sim.after_goal(room, place.pose, Goal(episode_id="ep-t", step=5, pose=place.pose), _frame_ids(
        room, place.pose)) is None  # a plain move: no report


GRID = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=100, cols=100)


def _map(step: int, pose: Pose2D, objects: list[ObjectInstance], skill: SkillReport | None = None) -> MapUpdate:
    occ = np.zeros((100, 100), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    return MapUpdate(episode_id="ep-t", step=step, grid=GRID, occupied=occ, free=~occ, explored=np.ones_like(occ),
                     pose=pose, objects=objects, skill=skill)


def _mug(psi: float) -> ObjectInstance:
    g = GazePoint(x=3.0, y=4.2, yaw=math.pi / 2, pitch=-0.5, psi_prime=psi + 0.1, ig=0.5)
    return ObjectInstance(instance_id=20, cls="mug", S=psi + 0.1, U=0.1, psi=psi, centre=(3.0, 5.0, 0.8),
                          extent=(0.1, 0.1, 0.1), n_gaussians=30, scores={"mug": (psi + 0.1, 0.1, psi)}, gaze=[g])


def test_planner_task_goals_from_map_updates_and_a_restart() -> None:
    planner = PlannerTask.from_start(_start(ablation="helios"), Thresholds())
    assert planner is not None
    rng = np.random.default_rng(0)
    goal, _ = planner.goal("ep-t", _map(0, Pose2D(x=3.0, y=2.0), [_mug(0.6)]), Memory(), rng)
    assert (goal.skill, goal.target, goal.phase) == ("pick", 20, "picking")  # 2.2 m: arrives in one step
    assert decode(encode(goal)) == goal
    saved = json.loads(json.dumps(planner.to_json()))
    update = _map(1, goal.pose, [_mug(0.6)], SkillReport(skill="pick", success=True, target=20, reason="picked"))
    g1, _ = planner.goal("ep-t", update, Memory(), rng)
    restarted = PlannerTask.from_json(saved)
    g2, _ = restarted.goal("ep-t", update, Memory(), np.random.default_rng(0))
    assert planner.machine.holding and restarted.machine.holding
    assert (g1.done, g1.reason) == (g2.done, g2.reason) and g1.phase == g2.phase
    # holding, no goal receptacle seen, nothing to explore: it looks around before it gives up
    assert not g1.done and "no frontier" in g1.reason and "turning in place to look around" in g1.reason
