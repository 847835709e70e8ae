"""The planner service: MapUpdate(t) + Decision(t) -> Goal(t).

Per episode it waits for both the mapper's :class:`MapUpdate` and the stopper's :class:`Decision` of a step
(either may come first). When the decision is to stop it does nothing (the stopper ends the episode);
otherwise it plans with :func:`services.planner.step.plan_step` and publishes a :class:`Goal`: the next pose
with the path to it, the chosen frontier, and the sampling probability of every frontier of the map in
``Goal.weights`` (0 for frontiers that were not candidates), or ``done=True`` with the reason when nothing
is left to explore. When the simulator refuses the goal (``ErrorReply`` on ``sim/error`` for that episode
and step) the planner plans the step again as :class:`services.planner.refusals.Refusals` says (the policy the
in-process runners share): another frontier, then a turn in place, then done with the reason.

Monitoring (Rerun, per episode): ``world/plan/path`` (line strip to the goal), ``world/plan/full_path``,
``world/plan/target`` (approach point of the chosen frontier), ``world/plan/goal`` (goal pose and heading),
``world/frontiers`` (every frontier, radius and label by its sampling probability).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eqa import keys
from eqa.bus import Bus
from eqa.episode_service import EpisodeService
from eqa.messages import (
    Decision,
    EpisodeStart,
    ErrorReply,
    Frontier,
    Goal,
    MapUpdate,
    Strategy,
)
from eqa.service import SHELL_GROUPS
from eqa.settings import HeliosSettings, SettingsGroup
from eqa.store import Store
from services.planner import cp_guided
from services.planner.refusals import Refusals, plan_attempt
from services.planner.sampling import step_rng
from services.planner.step import Memory, PlannerParams, StepPlan
from services.planner.task_fsm import Thresholds
from services.planner.task_runner import PlannerTask

log = logging.getLogger(__name__)

_KEEP_STEPS = 3


@dataclass
class _Pending:
    """The goal published for one step, kept to plan again if the simulator refuses it."""

    map: MapUpdate
    plan: StepPlan
    refusals: Refusals

    @property
    def step(self) -> int:
        return self.refusals.step


@dataclass
class _Episode:
    episode_id: str
    strategy: Strategy
    seed: int
    memory: Memory = field(default_factory=Memory)
    maps: dict[int, MapUpdate] = field(default_factory=dict)
    decisions: dict[int, Decision] = field(default_factory=dict)
    planned: int = -1
    pending: _Pending | None = None
    done: bool = False
    task: PlannerTask | None = None  # a task episode's state machine
    task_before: dict[str, Any] | None = None  # its state before the pending step (to re-plan a refused goal)


class PlannerService(EpisodeService[_Episode]):
    """Frontier sampling (Eq. A6 weights), collision-free paths with clearance, next pose (Explore-EQA).

    Per-episode state (:class:`eqa.episode_service.EpisodeService`, ``eqa:planner:episode:{id}``): strategy,
    seed, last planned step and the between-step memory (committed target, visited, refused), so a restarted
    planner plans the next steps exactly as this one would have; the last goal is the step's stored answer."""

    name = "planner"
    settings_groups = (*SHELL_GROUPS, HeliosSettings)  # a task's thresholds

    def __init__(self, settings: SettingsGroup, bus: Bus | None = None, store: Store | None = None, *,
                 params: PlannerParams | None = None) -> None:
        super().__init__(settings, bus, store)
        self.params = params or PlannerParams()

    def setup_episodes(self) -> None:
        self.on_step(keys.MAPPER_MAP, self.on_map)
        self.on_step(keys.STOPPER_DECISION, self.on_decision)
        self.on_step(keys.SIM_ERROR, self.on_sim_error, resend=False, hold=False)

    # ---- episode state -------------------------------------------------------------------------------------
    def start_episode(self, robot: str, start: EpisodeStart) -> _Episode:
        log.info("episode %s on %s: strategy %s, seed %d", start.episode_id, robot, start.strategy, start.seed)
        ep = _Episode(start.episode_id, start.strategy, start.seed)
        ep.task = PlannerTask.from_start(start, Thresholds.from_settings(self.settings))
        return ep

    def answered_step(self, episode_id: str, state: _Episode) -> int:
        return state.planned

    def dump_state(self, state: _Episode, **extra: object) -> dict[str, object]:
        m = state.memory
        return {
            "strategy": state.strategy, "seed": state.seed, "planned": state.planned,
            "memory": {"target": m.target.model_dump() if m.target else None, "committed_steps": m.committed_steps,
                       "visited": m.visited, "refused": m.refused, "turns": m.turns},
            "task": state.task.to_json() if state.task is not None else None,
        }

    def load_state(self, episode_id: str, data: dict[str, object]) -> _Episode:
        mem = data["memory"]
        assert isinstance(mem, dict)
        memory = Memory(
            target=Frontier.model_validate(mem["target"]) if mem["target"] else None,
            committed_steps=int(mem["committed_steps"]), visited=[tuple(v) for v in mem["visited"]],
            refused=[tuple(v) for v in mem["refused"]], turns=int(mem["turns"]),
        )
        ep = _Episode(episode_id, data["strategy"], int(data["seed"]), memory=memory,  # type: ignore[arg-type]
                      planned=int(data["planned"]))  # type: ignore[arg-type]
        if data.get("task"):
            ep.task = PlannerTask.from_json(data["task"])  # type: ignore[arg-type]
        log.info("episode %s: restored (strategy %s, last planned step %d)", episode_id, ep.strategy, ep.planned)
        return ep

    # ---- inputs --------------------------------------------------------------------------------------------
    def on_map(self, robot: str, ep: _Episode, msg: MapUpdate) -> None:
        ep.maps[msg.step] = msg
        self._try_plan(ep, msg.step)

    def on_decision(self, robot: str, ep: _Episode, msg: Decision) -> None:
        ep.decisions[msg.step] = msg
        self._try_plan(ep, msg.step)

    def on_sim_error(self, robot: str, ep: _Episode, msg: ErrorReply) -> None:
        if msg.step is None or ep.done or ep.pending is None or ep.pending.step != msg.step:
            return
        self._replan_after_refusal(ep, msg)

    # ---- planning ------------------------------------------------------------------------------------------
    def _try_plan(self, ep: _Episode, step: int) -> None:
        if ep.done or step <= ep.planned or step not in ep.maps or step not in ep.decisions:
            return
        decision = ep.decisions[step]
        ep.planned = step
        for old in [s for s in ep.maps if s <= step - _KEEP_STEPS]:
            del ep.maps[old]
        for old in [s for s in ep.decisions if s <= step]:
            del ep.decisions[old]
        if decision.stop:
            log.debug("episode %s step %d: stopper stops (%s); no goal", ep.episode_id, step, decision.reason)
            return
        step_map = ep.maps[step] if ep.strategy != "cp_guided" else cp_guided.guided_map(ep.maps[step], decision)
        refusals = Refusals(step, step_map.pose, len(step_map.frontiers), ep.memory.copy(), self.params.turn_deg)
        pending = _Pending(map=step_map, plan=StepPlan("done", ""), refusals=refusals)
        ep.pending = pending
        self._plan_and_publish(ep, pending)

    def _plan_and_publish(self, ep: _Episode, pending: _Pending, forced: StepPlan | None = None) -> None:
        step_map = pending.map
        refusals = pending.refusals
        task_fields: dict[str, Any] = {}
        rng = step_rng(ep.seed, refusals.step, refusals.attempt)
        if forced is not None:
            plan = forced
        elif ep.task is not None:  # a task episode: the state machine chooses (services/planner/task_runner.py)
            if refusals.attempt == 0:
                ep.task_before = ep.task.to_json()
            tgoal, plan = ep.task.goal(ep.episode_id, step_map, refusals.memory(), rng, self.params,
                                       before=ep.task_before if refusals.attempt else None)
            task_fields = {"skill": tgoal.skill, "target": tgoal.target, "phase": tgoal.phase,
                           "numbers": tgoal.numbers}
        else:
            plan = plan_attempt(step_map, ep.strategy, refusals, rng, self.params)
        pending.plan = plan
        ep.memory = plan.memory
        goal = Goal(
            episode_id=ep.episode_id,
            step=pending.step,
            pose=plan.pose,
            path=plan.path,
            frontier=plan.frontier,
            weights=plan.probabilities,
            done=plan.done,
            reason=plan.reason,
            **task_fields,
        )
        if plan.done:
            ep.done = True
        log.info(
            "episode %s step %d: %s (%s) in %.0f ms",
            ep.episode_id,
            pending.step,
            plan.kind,
            plan.reason,
            plan.timing_ms.get("step", 0.0),
        )
        self.publish_step(ep.episode_id, keys.PLANNER_GOAL, goal, pending.step, save=True)
        self._record(ep, pending.step, step_map, plan)

    def _replan_after_refusal(self, ep: _Episode, err: ErrorReply) -> None:
        pending = ep.pending
        assert pending is not None
        forced = pending.refusals.refuse(pending.plan, err.reason)
        log.info(
            "episode %s step %d: simulator refused the goal (%s); attempt %d",
            ep.episode_id,
            pending.step,
            err.reason,
            pending.refusals.attempt,
        )
        self._plan_and_publish(ep, pending, forced)

    # ---- monitoring ----------------------------------------------------------------------------------------
    def _record(self, ep: _Episode, step: int, step_map: MapUpdate, plan: StepPlan) -> None:
        recorder = self.recorders.get(ep.episode_id)
        if recorder is None or not recorder.enabled:
            return
        import rerun as rr

        recorder.set_step(step)
        z = 0.05
        if plan.path:
            recorder.log(
                "world/plan/path",
                rr.LineStrips3D([[(x, y, z) for x, y in plan.path]], colors=[(255, 140, 0)], radii=[0.03]),
            )
        if plan.full_path:
            recorder.log(
                "world/plan/full_path",
                rr.LineStrips3D([[(x, y, z) for x, y in plan.full_path]], colors=[(255, 200, 120)], radii=[0.015]),
            )
            tx, ty = plan.full_path[-1]
            recorder.log("world/plan/target", rr.Points3D([(tx, ty, z)], colors=[(255, 0, 0)], radii=[0.12]))
        if plan.pose is not None:
            p = plan.pose
            heading = (0.5 * math.cos(p.yaw), 0.5 * math.sin(p.yaw), 0.0)
            recorder.log(
                "world/plan/goal",
                rr.Arrows3D(origins=[(p.x, p.y, z)], vectors=[heading], colors=[(255, 140, 0)]),
            )
        if step_map.frontiers:
            probs = np.asarray(plan.probabilities or [0.0] * len(step_map.frontiers), dtype=np.float64)
            pts = [(f.x, f.y, z) for f in step_map.frontiers]
            top = float(probs.max()) if probs.size and probs.max() > 0 else 1.0
            radii = [0.05 + 0.2 * float(v) / top for v in probs]
            colors = [(int(255 * float(v) / top), 80, int(255 * (1 - float(v) / top))) for v in probs]
            labels = [f"w={f.weight:.3g} p={float(v):.2f}" for f, v in zip(step_map.frontiers, probs, strict=False)]
            recorder.log("world/frontiers", rr.Points3D(pts, radii=radii, colors=colors, labels=labels))
        if plan.done:
            recorder.log("world/plan/status", rr.TextLog(f"done: {plan.reason}"))
