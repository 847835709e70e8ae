"""One planning step of a HELIOS task episode: the state machine's action (:mod:`services.planner.task_fsm`) turned
into the step's goal on the 2D map.

* ``frontier`` -> :func:`services.planner.step.plan_step` towards that one frontier (same paths, clearances,
  commitment and turning-in-place rules as question episodes);
* ``move`` / ``pick`` / ``place`` / ``stop`` -> :func:`plan_to_pose`: a collision-free path to the gaze pose
  (at most ``max_step_m`` per step, like every goal); the skill is asked for only on the step the robot arrives
  (``Goal.skill``), before that the goal is a plain move; a pose that cannot be reached rules the instance out
  (:meth:`~services.planner.task_fsm.TaskMachine.unreachable`) and the machine decides again;
* ``done`` -> ``Goal.done`` with the reason.

Frontier values for Eq. 10 come from ``Frontier.sv`` (the value map's score of the frontier for the class being
searched, in [0, 1]).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner.helios import FrontierOption
from services.planner.paths import MapError, check_map, planning_grid, truncate
from services.planner.step import Memory, PlannerParams, StepPlan, plan_step, wrap
from services.planner.task_fsm import Action, SeenObject, SkillOutcome, TaskMachine

ARRIVE_TOLERANCE_M = 0.5  # a gaze pose is reached from the nearest traversable point within this


@dataclass
class PoseStep:
    plan: StepPlan | None  # None: the pose cannot be reached
    arrived: bool
    reason: str


def plan_to_pose(grid: GridSpec, free: np.ndarray, occupied: np.ndarray, robot: Pose2D,
                 target: tuple[float, float, float], params: PlannerParams | None = None) -> PoseStep:
    """A path from ``robot`` to the pose ``target = (x, y, yaw)`` with clearance (tried at each of
    ``params.clearances_m``), cut at ``params.max_step_m``. On arrival the robot stands at the target (or the
    nearest traversable point within :data:`ARRIVE_TOLERANCE_M`) facing ``yaw``."""
    params = params or PlannerParams()
    try:
        check_map(grid, free, occupied)
    except MapError as exc:
        return PoseStep(None, False, f"malformed map: {exc}")
    tx, ty, tyaw = target
    if math.hypot(tx - robot.x, ty - robot.y) <= 0.05:
        pose = Pose2D(x=robot.x, y=robot.y, yaw=wrap(tyaw))
        return PoseStep(StepPlan("move", "at the pose: turning to face it", pose=pose,
                                 path=[(robot.x, robot.y)]), True, "arrived")
    for clearance in params.clearances_m:
        pg = planning_grid(grid, free, occupied, clearance, params.coarse_m, params.max_blocks)
        if not pg.search_from(robot.x, robot.y, params.snap_radius_m) or pg.dist is None:
            continue
        R, C = pg.dist.shape
        bi, bj = pg.block_of(tx, ty)
        rad = math.ceil(ARRIVE_TOLERANCE_M / pg.block_m) + 1
        r0, r1, c0, c1 = max(0, bi - rad), min(R, bi + rad + 1), max(0, bj - rad), min(C, bj + rad + 1)
        if r0 >= r1 or c0 >= c1:
            continue
        win = pg.dist[r0:r1, c0:c1]
        ii, jj = np.nonzero(np.isfinite(win))
        if ii.size == 0:
            continue
        cx, cy = pg.block_centre(ii + r0, jj + c0)
        e = np.hypot(cx - tx, cy - ty)
        if float(e.min()) > ARRIVE_TOLERANCE_M:
            continue
        m = int(np.argmin(e + 1e-3 * win[ii, jj]))
        block = (int(ii[m] + r0), int(jj[m] + c0))
        pulled, complete, full = pg.world_path(block, params.max_step_m)
        if not pulled:
            continue
        path, fits = truncate(pulled, params.max_step_m)
        arrived = fits and complete
        if arrived and pg.segment_clear(path[-1], (tx, ty)) and math.dist(path[-1], (tx, ty)) > 1e-6:
            path = [*path, (tx, ty)]
            path, fits = truncate(path, params.max_step_m)
            arrived = fits
        gx, gy = path[-1]
        if arrived:
            yaw = tyaw
        else:
            (ax, ay), (bx, by) = path[-2] if len(path) > 1 else (robot.x, robot.y), path[-1]
            yaw = math.atan2(by - ay, bx - ax) if math.hypot(bx - ax, by - ay) > 1e-6 else robot.yaw
        what = "arrives at" if arrived else "heads for"
        plan = StepPlan("move", f"{what} ({tx:.2f}, {ty:.2f}) (clearance {pg.clearance_m:.2f} m)",
                        pose=Pose2D(x=gx, y=gy, yaw=wrap(yaw)), path=path, full_path=full,
                        clearance_m=pg.clearance_m)
        return PoseStep(plan, arrived, plan.reason)
    return PoseStep(None, False, f"no path to ({tx:.2f}, {ty:.2f}) with clearance")


@dataclass
class TaskStep:
    """The goal of one task step: a plan (or done), the skill to run on arrival, the phase for events."""

    plan: StepPlan
    skill: str = "move"
    target: int | None = None
    phase: str = "searching"
    memory: Memory = field(default_factory=Memory)


def frontier_options(frontiers: list[Frontier]) -> list[FrontierOption]:
    return [FrontierOption(i, f.x, f.y, f.sv) for i, f in enumerate(frontiers)
            if all(math.isfinite(v) for v in (f.x, f.y, f.sv))]


def task_step(machine: TaskMachine, grid: GridSpec, free: np.ndarray, occupied: np.ndarray, pose: Pose2D,
              frontiers: list[Frontier], objects: list[SeenObject], outcome: SkillOutcome | None,
              memory: Memory, rng: np.random.Generator, params: PlannerParams | None = None,
              max_tries: int = 8) -> TaskStep:
    """Ask the machine for its action and plan it (module doc). ``memory`` is the planner's frontier memory
    (not modified; the result carries the one to keep)."""
    params = params or PlannerParams()
    robot = (pose.x, pose.y, pose.yaw)
    # frontiers the robot already went to are no option (plan_step would refuse them and turn in place)
    options = [o for o in frontier_options(frontiers)
               if not any(math.hypot(o.x - vx, o.y - vy) <= params.visited_radius_m for vx, vy in memory.visited)]
    for _ in range(max_tries):
        act: Action = machine.step(robot, options, objects, outcome)
        outcome = None  # consumed
        if act.kind == "done":
            return TaskStep(StepPlan("done", act.reason, memory=memory.copy()), phase="finished", memory=memory)
        if act.kind == "frontier":
            assert act.ref is not None
            plan = plan_step(grid, free, occupied, pose, [frontiers[act.ref]], "fbe", memory, rng, params)
            if plan.kind == "done":  # that frontier cannot be reached: let the machine choose again
                options = [o for o in options if o.index != act.ref]
                continue
            plan.reason = f"{act.reason}; {plan.reason}"
            return TaskStep(plan, "move", None, act.phase, plan.memory)
        assert act.pose is not None
        ps = plan_to_pose(grid, free, occupied, pose, act.pose, params)
        if ps.plan is None:
            if act.ref is not None:
                machine.unreachable(act.ref)
            continue
        ps.plan.reason = f"{act.reason}; {ps.plan.reason}"
        skill = act.kind if act.kind in ("pick", "place", "stop") and ps.arrived else "move"
        return TaskStep(ps.plan, skill, act.ref, act.phase, memory.copy())
    return TaskStep(StepPlan("done", f"no reachable action after {max_tries} tries", memory=memory.copy()),
                    phase="finished", memory=memory)


def outcome_of(report: Any) -> SkillOutcome | None:
    """A :class:`SkillOutcome` from ``MapUpdate.skill`` (an ``eqa.messages.SkillReport``) or None."""
    if report is None:
        return None
    return SkillOutcome(report.skill, bool(report.success), report.target, report.reason)
