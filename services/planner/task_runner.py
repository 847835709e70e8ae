"""What the planner shell does for a task episode (issue 17): one :class:`PlannerTask` per episode turns each
``MapUpdate`` (frontiers, ``objects`` from the object layer, ``skill``: the outcome of the last skill) into the
step's ``Goal`` through the state machine (:mod:`services.planner.task_fsm`) and the task step
(:mod:`services.planner.task_step`). The machine's state is plain data: the shell stores it with the episode
(:meth:`PlannerTask.to_json`), so a restarted planner continues the task; a goal the sim refuses is planned again
from the state before the step (:meth:`PlannerTask.goal` with ``before``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from eqa.messages import EpisodeStart, Goal, MapUpdate
from services.planner.step import Memory, PlannerParams, StepPlan
from services.planner.task_fsm import TaskMachine, Thresholds, from_instance
from services.planner.task_step import outcome_of, task_step


class PlannerTask:
    def __init__(self, machine: TaskMachine) -> None:
        self.machine = machine

    @classmethod
    def from_start(cls, start: EpisodeStart, th: Thresholds) -> PlannerTask | None:
        """The task planner of an episode (None for a question episode)."""
        t = start.task
        if t is None:
            return None
        return cls(TaskMachine(t.kind, t.object, t.start_receptacle, t.goal_receptacle, start.ablation,
                               start.pick_limit, th))

    def goal(self, episode_id: str, mu: MapUpdate, memory: Memory, rng: np.random.Generator,
             params: PlannerParams | None = None, before: dict[str, Any] | None = None) -> tuple[Goal, StepPlan]:
        """The goal of step ``mu.step``. ``before``: the machine's state to plan from again (a refused goal)."""
        if before is not None:
            self.machine = TaskMachine.from_json(before)
        objects = [from_instance(o) for o in getattr(mu, "objects", [])]
        st = task_step(self.machine, mu.grid, mu.free, mu.occupied, mu.pose, list(mu.frontiers), objects,
                       outcome_of(getattr(mu, "skill", None)), memory, rng, params)
        plan = st.plan
        plan.memory = st.memory
        goal = Goal(episode_id=episode_id, step=mu.step, pose=plan.pose, path=plan.path, frontier=plan.frontier,
                    weights=plan.probabilities, done=plan.done, reason=plan.reason, skill=st.skill,  # type: ignore[arg-type]
                    target=st.target, phase=st.phase)  # type: ignore[arg-type]
        return goal, plan

    def to_json(self) -> dict[str, Any]:
        return self.machine.to_json()

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PlannerTask:
        return cls(TaskMachine.from_json(data))
