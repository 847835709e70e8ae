"""What the planner does when the simulator refuses the goal of a step (a pose in collision or off the floor).

The step is planned again: the refused goal's frontier is no longer a candidate for this step, and the refused
pose (when it is not the robot's own position) is remembered as refused for the rest of the episode
(:class:`services.planner.step.Memory`, ``refused_radius_m``). After ``MAX_REFUSALS`` refusals the robot turns
in place by ``turn_deg`` instead; when even a turn in place (or a goal without a pose) is refused the episode
is done, with the reason.

:class:`Refusals` is the policy as data (pure: no bus, no simulator); the planner service keeps one per
pending step and feeds it the simulator's ``ErrorReply``, and in-process runners drive it with
:func:`plan_until_accepted` and the simulator's goal check, so both take the same goals.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from eqa.messages import MapUpdate, Pose2D, Strategy
from services.planner.step import Memory, PlannerParams, StepPlan, plan_step

MAX_REFUSALS = 4
# a refused goal this close to the robot is a turn at its own position: remembering it would block the robot
_SAME_POSITION_M = 0.05


@dataclass
class Refusals:
    """The refused goals of one step: planning again after a refusal (module doc)."""

    step: int
    here: Pose2D  # the robot's pose at the step
    frontiers: int  # how many frontiers the step's map has (a forced plan gives each probability 0)
    memory_before: Memory  # the planner's memory before the step
    turn_deg: float = 60.0
    attempt: int = 0  # how many goals of the step were refused so far
    excluded: list[tuple[float, float]] = field(default_factory=list)  # frontiers not to choose again this step
    refused: list[tuple[float, float]] = field(default_factory=list)  # refused goal positions of this step

    def memory(self) -> Memory:
        """The memory to plan the next attempt with: the step's start plus the refused positions."""
        mem = self.memory_before.copy()
        mem.refused.extend(self.refused)
        return mem

    def refuse(self, plan: StepPlan, reason: str) -> StepPlan | None:
        """Take the simulator's refusal (``reason``) of ``plan``: None to plan the step again (with
        :meth:`memory`, ``exclude=excluded`` and the generator of attempt :attr:`attempt`), or the plan to
        publish instead (a turn in place after ``MAX_REFUSALS`` refusals, done when a turn was refused)."""
        self.attempt += 1
        if plan.kind == "turn" or plan.pose is None:
            why = f"the simulator refused {self.attempt} goal(s) at step {self.step}, the last: {reason}"
            return StepPlan("done", why, memory=self.memory_before.copy(), probabilities=[0.0] * self.frontiers)
        if plan.frontier is not None:
            self.excluded.append((plan.frontier.x, plan.frontier.y))
        if math.hypot(plan.pose.x - self.here.x, plan.pose.y - self.here.y) > _SAME_POSITION_M:
            self.refused.append((plan.pose.x, plan.pose.y))
        if self.attempt <= MAX_REFUSALS:
            return None
        mem = self.memory_before.copy()
        mem.target = None
        here = self.here
        yaw = here.yaw + math.radians(self.turn_deg)
        return StepPlan(
            "turn",
            f"the simulator refused {self.attempt} goal(s) ({reason}): turning in place",
            pose=Pose2D(x=here.x, y=here.y, yaw=math.atan2(math.sin(yaw), math.cos(yaw))),
            path=[(here.x, here.y)],
            probabilities=[0.0] * self.frontiers,
            memory=mem,
        )


def plan_attempt(step_map: MapUpdate, strategy: Strategy, refusals: Refusals, rng: np.random.Generator,
                 params: PlannerParams) -> StepPlan:
    """Plan attempt ``refusals.attempt`` of a question episode's step on ``step_map`` (the step's map, re-weighted
    for ``cp_guided``): :func:`services.planner.step.plan_step` without the step's refused goals."""
    return plan_step(step_map.grid, step_map.free, step_map.occupied, step_map.pose, step_map.frontiers, strategy,
                     refusals.memory(), rng, params, exclude=refusals.excluded, explored=step_map.explored)


def plan_until_accepted(refusals: Refusals, plan: Callable[[Refusals], StepPlan],
                        refusal: Callable[[StepPlan], str | None]) -> StepPlan:
    """Plan one step until the goal is accepted, as the planner service does with the simulator's replies:
    ``plan(refusals)`` plans attempt ``refusals.attempt`` (:meth:`Refusals.memory`, ``refusals.excluded``),
    ``refusal(plan)`` is the simulator's reason to refuse a goal (None: taken). Returns the accepted plan, or a
    done plan (the planner's own, or the policy's when refusals ran out)."""
    current = plan(refusals)
    while not current.done:
        reason = refusal(current)
        if reason is None:
            return current
        forced = refusals.refuse(current, reason)
        current = forced if forced is not None else plan(refusals)
    return current
