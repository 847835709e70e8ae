"""The simulator's side of one task episode: it executes the skills and keeps the OVMM phase metrics (HELIOS
section 4.1 "Metrics"; section 4.2 for object search).

``pick_place`` (every flag sticky once set):

* **FindObj** -- the robot was ever close enough to a target object: a frame in which the oracle pick would have
  succeeded (a target in frame and within reach, :func:`services.sim.skills.pick`);
* **Pick** -- a pick succeeded;
* **FindRec** -- after the pick, the robot was close enough to a goal receptacle (in frame, within reach);
* **Place** -- the place skill left the object resting on a goal receptacle (:func:`services.sim.skills.place`);
* **SR** -- all four and no collision.

With a pick limit, an episode that exceeded it scores 0 on every metric (the paper's rule). ``find_object``:
success = the stop call within :data:`~services.sim.tasks.FIND_SUCCESS_M` of a target's box; SPL = success x
shortest / max(shortest, travelled). Collisions: base motions whose path hits an obstacle
(:func:`services.sim.skills.path_collides`). The state is plain data (a restarted sim continues it).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from eqa.messages import Pose2D, Task
from services.sim import skills
from services.sim.scene import Scene
from services.sim.tasks import FIND_SUCCESS_M

OBJECT_SIZE_DEFAULT = (0.15, 0.15, 0.15)
TRACE_FIELDS = ("step", "pose", "phase", "skill", "target", "reason", "numbers", "collided", "skill_result",
                "collisions", "pick_attempts", "path_m", "FindObj", "Pick", "FindRec", "Place", "found")


@dataclass
class TaskEpisode:
    task: Task
    pick_limit: int | None = None
    find_obj: bool = False
    picked: bool = False
    held_id: int | None = None
    find_rec: bool = False
    placed: bool = False
    stopped: bool = False
    found: bool = False
    collisions: int = 0
    pick_attempts: int = 0
    path_m: float = 0.0
    skill_log: list[dict[str, Any]] = field(default_factory=list)
    trace: list[dict[str, Any]] = field(default_factory=list)  # one entry per step (:meth:`record`)
    end_reason: str | None = None  # the planner's reason when it ended the task

    # ---- observations and motion ------------------------------------------------------------------------
    def observe(self, scene: Scene, pose: Pose2D, instances: np.ndarray) -> None:
        """Update FindObj / FindRec from a rendered frame (its per-pixel instance ids) at ``pose``."""
        if not self.picked and not self.find_obj and skills.pick(scene, pose, instances, self.task.object_ids).success:
            self.find_obj = True
        goals = self.task.goal_receptacle_ids
        if self.picked and not self.find_rec and goals and skills.pick(scene, pose, instances, goals).success:
            self.find_rec = True

    def move(self, scene: Scene, path: list[tuple[float, float]]) -> bool:
        """A base motion along ``path`` (from the current pose to the goal); counts a collision, the length."""
        pts = [tuple(map(float, p)) for p in path]
        if len(pts) >= 2:
            self.path_m += float(sum(math.dist(a, b) for a, b in itertools.pairwise(pts)))
        hit = skills.path_collides(scene, pts)
        self.collisions += int(hit)
        return hit

    # ---- skills ------------------------------------------------------------------------------------------
    @property
    def limit_exceeded(self) -> bool:
        return self.pick_limit is not None and self.pick_attempts > self.pick_limit

    def pick(self, scene: Scene, pose: Pose2D, instances: np.ndarray) -> skills.PickResult:
        if self.picked:
            return skills.PickResult(False, "already holding the object")
        self.pick_attempts += 1
        r = skills.pick(scene, pose, instances, self.task.object_ids)
        if r.success:
            self.picked, self.held_id, self.find_obj = True, r.object_id, True
        self.skill_log.append({"skill": "pick", "success": r.success, "reason": r.reason,
                               "attempt": self.pick_attempts})
        return r

    def place(self, scene: Scene, pose: Pose2D) -> skills.PlaceResult:
        if not self.picked or self.held_id is None:
            return skills.PlaceResult(False, "nothing held to place")
        info = scene.instances.get(self.held_id)
        size = info.size if info is not None else OBJECT_SIZE_DEFAULT
        r = skills.place(scene, pose, size, self.task.goal_receptacle_ids, self.held_id,  # type: ignore[arg-type]
                         self.task.goal_receptacle)
        self.placed = r.success
        self.held_id = None
        self.skill_log.append({"skill": "place", "success": r.success, "reason": r.reason})
        return r

    def stop(self, scene: Scene, pose: Pose2D) -> bool:
        """The stop call of a ``find_object`` task: success within FIND_SUCCESS_M of a target's box."""
        self.stopped = True
        self.found = any(
            skills.box_distance_xy(pose.x, pose.y, scene.instances[i].position, scene.instances[i].size)
            <= FIND_SUCCESS_M for i in self.task.object_ids if i in scene.instances)
        self.skill_log.append({"skill": "stop", "success": self.found})
        return self.found

    # ---- the trace ----------------------------------------------------------------------------------------
    def record(self, step: int, pose: Pose2D, goal: dict[str, Any] | None, collided: bool,
               skill: dict[str, Any] | None) -> dict[str, Any]:
        """Append the trace entry of ``step`` (:data:`TRACE_FIELDS`): the planner's goal that led here (phase,
        skill asked for, target instance, reason, decision numbers; None at step 0), the pose reached, whether
        the motion collided, the skill's outcome and, after it, the cumulative counts and phase flags."""
        entry: dict[str, Any] = {
            "step": int(step), "pose": [round(pose.x, 4), round(pose.y, 4), round(pose.yaw, 4)],
            "phase": None, "skill": None, "target": None, "reason": "", "numbers": {},
            **({k: goal[k] for k in ("phase", "skill", "target", "reason", "numbers") if k in goal} if goal else {}),
            "collided": bool(collided), "skill_result": skill,
            "collisions": self.collisions, "pick_attempts": self.pick_attempts, "path_m": round(self.path_m, 4),
            "FindObj": self.find_obj, "Pick": self.picked, "FindRec": self.find_rec, "Place": self.placed,
            "found": self.found,
        }
        if self.trace and self.trace[-1]["step"] == entry["step"]:  # the same step rendered again (a restart)
            self.trace[-1] = entry
        else:
            self.trace.append(entry)
        return entry

    def trace_doc(self) -> dict[str, Any]:
        """The stored trace of the episode (:func:`eqa.store.task_trace_key`): the task with its ground truth,
        the pick limit, the planner's end reason (once it is done) and the per-step entries."""
        return {"task": self.task.model_dump(mode="json"), "pick_limit": self.pick_limit,
                "end_reason": self.end_reason, "steps": self.trace}

    # ---- scoring -----------------------------------------------------------------------------------------
    def metrics(self) -> dict[str, float]:
        """The episode's metrics (module doc), each 0 or 1 (SPL in [0, 1])."""
        if self.task.kind == "find_object":
            shortest = self.task.shortest_path_m or 0.0
            spl = (shortest / max(shortest, self.path_m, 1e-9)) if self.found else 0.0
            return {"SR": float(self.found), "SPL": round(spl, 6), "collisions": float(self.collisions)}
        if self.limit_exceeded:
            vals = dict.fromkeys(("FindObj", "Pick", "FindRec", "Place", "SR"), 0.0)
        else:
            vals = {"FindObj": float(self.find_obj), "Pick": float(self.picked), "FindRec": float(self.find_rec),
                    "Place": float(self.placed),
                    "SR": float(self.find_obj and self.picked and self.find_rec and self.placed
                                and self.collisions == 0)}
        return {**vals, "collisions": float(self.collisions), "pick_attempts": float(self.pick_attempts)}

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["task"] = self.task.model_dump(mode="json")
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> TaskEpisode:
        return cls(**{**d, "task": Task.model_validate(d["task"])})
