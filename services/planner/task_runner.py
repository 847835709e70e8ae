"""What the planner shell does for a task episode: one :class:`PlannerTask` per episode turns each
``MapUpdate`` (frontiers, ``objects`` from the object layer, ``skill``: the outcome of the last skill) into the
step's ``Goal`` through the state machine (:mod:`services.planner.task_fsm`) and the task step
(:mod:`services.planner.task_step`). The machine's state is plain data: the shell stores it with the episode
(:meth:`PlannerTask.to_json`), so a restarted planner continues the task; a goal the sim refuses is planned again
from the state before the step (:meth:`PlannerTask.goal` with ``before``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from eqa.messages import EpisodeStart, Frontier, Goal, MapUpdate, Pose2D
from services.planner import helios
from services.planner.step import Memory, PlannerParams, StepPlan
from services.planner.task_fsm import SeenObject, TaskMachine, Thresholds, from_instance
from services.planner.task_step import TaskStep, outcome_of, task_step


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
                               start.pick_limit, th, start.max_steps))

    def goal(self, episode_id: str, update: MapUpdate, memory: Memory, rng: np.random.Generator,
             params: PlannerParams | None = None, before: dict[str, Any] | None = None) -> tuple[Goal, StepPlan]:
        """The goal of step ``update.step``. ``before``: the machine's state to plan from again (a refused goal)."""
        if before is not None:
            self.machine = TaskMachine.from_json(before)
        objects = [from_instance(o) for o in getattr(update, "objects", [])]
        st = task_step(self.machine, update.grid, update.free, update.occupied, update.pose, list(update.frontiers),
                       objects, outcome_of(getattr(update, "skill", None)), memory, rng, params,
                       step=update.step)
        plan = st.plan
        plan.memory = st.memory
        goal = Goal(episode_id=episode_id, step=update.step, pose=plan.pose, path=plan.path, frontier=plan.frontier,
                    weights=plan.probabilities, done=plan.done, reason=plan.reason, skill=st.skill,  # type: ignore[arg-type]
                    target=st.target, phase=st.phase,  # type: ignore[arg-type]
                    numbers=decision_numbers(self.machine, st, objects, update.pose))
        return goal, plan

    def to_json(self) -> dict[str, Any]:
        return self.machine.to_json()

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PlannerTask:
        return cls(TaskMachine.from_json(data))


def decision_numbers(machine: TaskMachine, st: TaskStep, objects: Sequence[SeenObject],
                     robot: Pose2D) -> dict[str, float]:
    """The numbers behind the step's decision, for the task trace (read from the state the machine decided on,
    never fed back into it). An instance goal (``st.target``): its ``S``, ``U``, ``Psi`` (Eq. 7) for the class
    of the phase (the goal receptacle while holding, the start receptacle in local search, else the object),
    ``Psi'`` of its best gaze point (Eq. 11), its optimistic ``IG`` (Eq. 12) and, for a start-receptacle
    candidate, ``V = S IG - alpha_d dist`` (Eq. 10). A frontier goal: its value-map score ``F``, ``F0`` (Eq. 9)
    and ``V = F F0 - alpha_d dist`` (Eq. 10). ``F0`` is given on every step; non-finite numbers are left out."""
    th = machine.th
    f0 = helios.f0_association(machine.memory.chosen, list(machine.memory.stored.values()), th.alpha_d)
    out: dict[str, float] = {"F0": f0}
    obj = next((o for o in objects if o.instance_id == st.target), None) if st.target is not None else None
    if obj is not None:
        cls = (machine.goal_receptacle if machine.holding else
               machine.start_receptacle if st.phase == "local_search" else machine.object) or machine.object
        s = obj.of(cls)
        if s is not None:
            out.update(S=s[0], U=s[1], Psi=s[2])
        g = obj.best_gaze()
        if g is not None:
            out["Psi_prime"] = g.psi_prime
        out["IG"] = obj.ig
        if st.phase == "local_search" and s is not None:
            out["V"] = s[0] * obj.ig - th.alpha_d * math.hypot(obj.x - robot.x, obj.y - robot.y)
    elif st.plan.frontier is not None and st.phase == "searching":
        f: Frontier = st.plan.frontier
        out["F"] = f.sv
        scale = f0 if (machine.ablation != "trusting" and not machine.holding and machine.kind == "pick_place") else 1.0
        out["V"] = f.sv * scale - th.alpha_d * math.hypot(f.x - robot.x, f.y - robot.y)
    return {k: float(v) for k, v in out.items() if v is not None and math.isfinite(v)}
