"""What the sim shell does for a task episode, beside rendering: after each goal it counts the motion's
collisions, runs the goal's skill on the frame rendered at the goal pose, and keeps the phase metrics
(:class:`services.sim.task_episode.TaskEpisode`).

Order within one step, as the shell calls it: move the robot to ``goal.pose`` -> render the frame ->
:meth:`SimTask.after_goal` (collisions of the path, then the skill with that frame's instance ids; its
:class:`eqa.messages.SkillReport` goes on the frame) -> :meth:`SimTask.observe` (FindObj / FindRec) -> publish.
Step 0 only observes. The held object is not removed from the rendered scene (the renderer's mesh is fixed);
the skills' ground truth knows it is held.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from eqa.messages import EpisodeStart, Goal, Pose2D, SkillReport
from services.sim.scene import Scene
from services.sim.task_episode import TaskEpisode


class SimTask:
    def __init__(self, episode: TaskEpisode) -> None:
        self.episode = episode
        self.collided = False  # the last motion's collision, until the step's trace entry takes it

    @classmethod
    def from_start(cls, start: EpisodeStart, scene: Scene | None = None, pose: Pose2D | None = None) -> SimTask | None:
        """The task runner of an episode, or None for a question episode. With the ``scene`` and start ``pose``,
        a task given in words gets its ground truth from the scene graph
        (:func:`services.sim.tasks.with_ground_truth`)."""
        if start.task is None:
            return None
        task = start.task
        if scene is not None and pose is not None:
            from services.sim.tasks import with_ground_truth

            task = with_ground_truth(task, scene, pose)
        return cls(TaskEpisode(task, pick_limit=start.pick_limit))

    def after_goal(self, scene: Scene, before: Pose2D, goal: Goal, instances: np.ndarray) -> SkillReport | None:
        """Count the motion ``before -> goal.path -> goal.pose`` and run ``goal.skill`` with the per-pixel
        ``instances`` of the frame rendered at ``goal.pose``."""
        assert goal.pose is not None
        from services.sim.skills import motion_path

        self.collided = self.episode.move(scene, motion_path((before.x, before.y), goal.path,
                                                             (goal.pose.x, goal.pose.y)))
        if goal.skill == "pick":
            r = self.episode.pick(scene, goal.pose, instances)
            return SkillReport(skill="pick", success=r.success, target=goal.target, reason=r.reason[:300])
        if goal.skill == "place":
            p = self.episode.place(scene, goal.pose)
            return SkillReport(skill="place", success=p.success, target=goal.target, reason=p.reason[:300])
        if goal.skill == "stop":
            ok = self.episode.stop(scene, goal.pose)
            why = "within reach of the object" if ok else "not near a target object"
            return SkillReport(skill="stop", success=ok, target=goal.target, reason=why)
        return None

    def observe(self, scene: Scene, pose: Pose2D, instances: np.ndarray) -> None:
        self.episode.observe(scene, pose, instances)

    def record(self, step: int, pose: Pose2D, goal: Goal | None, skill: SkillReport | None) -> dict[str, Any]:
        """The trace entry of the step just rendered (after :meth:`after_goal` and :meth:`observe`)."""
        g = None if goal is None else {"phase": goal.phase, "skill": goal.skill, "target": goal.target,
                                       "reason": goal.reason[:300], "numbers": dict(goal.numbers)}
        hit, self.collided = self.collided, False
        return self.episode.record(step, pose, g, hit, None if skill is None else skill.model_dump())

    def metrics(self) -> dict[str, float]:
        return self.episode.metrics()

    def to_json(self) -> dict[str, Any]:
        return self.episode.to_json()

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SimTask:
        return cls(TaskEpisode.from_json(data))
