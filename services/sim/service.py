"""The simulator service: renders the robot's view for each episode step.

On ``EpisodeStart`` it loads (or generates) the question's scene, places the robot at the question's
start pose (or samples one with 0.5 m clearance, seeded by ``EpisodeStart.seed``) and publishes step 0;
on a ``Goal`` of that episode it moves the robot to the goal pose and publishes the next step. A bad scene,
a pose in collision, off the floor or not finite, a mesh that does not parse, or a task naming an object or
receptacle the house lacks (:func:`services.sim.tasks.scene_lacks`) gets an ``ErrorReply`` on ``sim/error`` (with
episode and step), and the service goes on serving every robot.

The service is an :class:`eqa.episode_service.EpisodeService` (start/cancel/end, stored state, recorders and
error answers come from there; see its docstring for what the sim keeps in its own shell and why). After every
frame the episode's state (start, pose, step, trajectory, task) is written to the store under
``eqa.store.episode_state_key("sim", episode_id)`` (``eqa:sim:episode:{id}``, one :mod:`eqa.codec` envelope
that names the robot), so a sim restarted between two steps continues the episode at the next goal; a
restarted sim also takes up the recent states it finds there at start (the newest one per robot). States in
any other format (e.g. JSON under ``eqa:sim:robot:{robot}``) are not read.

A message lost while a service restarted would stall an episode. The sim watches the liveliness of the mapper,
planner and stopper instances (and its own shard): when one vanishes or (re)appears, the current frame of each
robot whose owner changed is sent again a moment later (:class:`eqa.sharding.Redrive`, ``EQA_STEP_REDRIVE``), and
a restarted sim sends the frames of the episodes it takes up from the store; the mapper, stopper and planner
answer a repeated step by publishing their output for it again (computed once: step claims and stored answers),
so the goal comes back within about a second of the new instance being up. As the last resort the sim sends the
frame of a step again when no goal came back within ``EQA_STEP_RESEND_S`` (at most ``EQA_STEP_RESENDS_MAX`` times
per step); after the last resend the gateway's watchdog ends the episode with a reason.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from eqa import dataflow, keys, metrics
from eqa.bus import Bus
from eqa.codec import CodecError, unpackb
from eqa.episode_service import EpisodeService
from eqa.messages import EpisodeCancel, EpisodeEnd, EpisodeStart, Frame, Goal, Pose2D, SkillReport
from eqa.recording import ENTITIES
from eqa.robot import goal_not_taken
from eqa.service import SHELL_GROUPS
from eqa.settings import (
    FleetSettings,
    Ros2Settings,
    SettingsGroup,
    SimulatorSettings,
)
from eqa.sharding import Redrive
from eqa.store import (
    EPISODE_STATE_TTL_S,
    Store,
    episode_end_key,
    episode_state_key,
    task_metrics_key,
    task_trace_key,
)
from services.sim import hmeqa, skills
from services.sim.camera import camera_pose, intrinsics
from services.sim.library import load_or_generate
from services.sim.motion import START_CLEARANCE, pose_error, sample_start_pose
from services.sim.render import Renderer
from services.sim.scene import CHANGED_ID, GEN_ID, Scene, SceneLoadError, SceneNotFound, load_mesh_scene
from services.sim.task_runner import SimTask

log = logging.getLogger(__name__)
MAX_CACHED_SCENES = 4
REDRIVE_TICK_S = 0.1  # how often due re-sends are looked for (a dict lookup when none is pending)


@dataclass
class _Episode:
    episode_id: str
    scene: Scene
    renderer: Renderer
    pose: Pose2D
    max_steps: int
    start: EpisodeStart
    step: int = 0
    trajectory: list[tuple[float, float]] = field(default_factory=list)
    emitted_at: float = field(default_factory=time.monotonic)  # when the current step's frame was sent
    resends: int = 0  # of the current step
    task: SimTask | None = None  # a task episode's skills and metrics
    skill: SkillReport | None = None  # the skill outcome of the current step (on its frame, resends too)
    collisions: int = 0  # base motions that hit an obstacle (services.sim.skills.path_collides), every episode


def load_scene(settings: SettingsGroup, scene_id: str, floor: int = 0) -> Scene:
    """A scene by id: generated houses from ``scenes_path``; HM3D scans from ``hm3d_dir`` (floor height
    from ``scene_init_poses.csv`` there when present); other meshes from ``scenes_path``."""
    if not (GEN_ID.match(scene_id) or CHANGED_ID.match(scene_id)) and settings.hm3d_dir is not None:
        path = hmeqa.scan_path(settings.hm3d_dir, scene_id)
        if path is not None:
            floor_z = 0.0
            poses_file = Path(settings.hm3d_dir) / hmeqa.POSES_FILE
            if poses_file.is_file():
                init = hmeqa.load_init_poses(poses_file).get((scene_id, floor))
                floor_z = init.floor_height if init else 0.0
            return load_mesh_scene(path, scene_id=scene_id, floor_z=floor_z)
    return load_or_generate(scene_id, settings.scenes_path, settings.hm3d_dir)


class SimService(EpisodeService[_Episode]):
    """Simulator: scenes, RGB-D + instance rendering, robot motion."""

    name = "sim"
    description = "Simulator: renders RGB, depth and instance ids of generated houses or real meshes."
    error_stream = keys.SIM_ERROR
    answer_invalid_start = True
    persist_answers = False  # the sim answers no step input; it sends its frames again itself
    # Ros2Settings: the robots a ROS 2 robot drives are left alone here
    settings_groups = (*SHELL_GROUPS, FleetSettings, SimulatorSettings, Ros2Settings)

    def __init__(self, settings: SettingsGroup, bus: Bus | None = None, store: Store | None = None) -> None:
        super().__init__(settings, bus, store)
        self._scenes: OrderedDict[tuple[str, int], Renderer] = OrderedDict()
        self._K = intrinsics(self.settings.sim_width, self.settings.sim_height)
        self._redrive: Redrive | None = None

    def owns(self, robot: str) -> bool:
        # A robot of EQA_ROS2_ROBOTS is a real one: the ROS 2 bridge keeps the contract for it.
        return robot not in self.settings.ros2_robots and super().owns(robot)

    def wants(self, robot: str) -> bool:
        return robot not in self.settings.ros2_robots and super().wants(robot)

    def setup_episodes(self) -> None:
        # Robots are shared among the live sim instances by the base's Shard (EQA_SHARD): this one drives only
        # its own, claims each step it renders, and takes a robot that moves here up from the store.
        self.on(keys.PLANNER_GOAL, self.on_goal)
        if self.settings.step_redrive:
            # an instance downstream (re)appears or vanishes: the current frame of each robot it takes or held
            # is sent again within a second, not after EQA_STEP_RESEND_S (that timer stays the last resort)
            self._redrive = Redrive(s for s in dataflow.STATEFUL if s != self.name)
            self.bus.watch_alive(keys.ALIVE_ANY, lambda service, instance, up: self.submit(
                self._downstream_changed, service, instance, up))
            self.every(REDRIVE_TICK_S, self._redrive_due)
        self.submit(self._resume_stored)
        if self.settings.step_resend_s > 0:
            self.every(min(1.0, self.settings.step_resend_s / 4), self._resend_stale)

    def teardown(self) -> None:
        super().teardown()
        self.episodes.clear()
        self.meta.clear()

    # ---- helpers -----------------------------------------------------------------------------------------
    def renderer(self, scene_id: str, floor: int = 0) -> Renderer:
        """The cached renderer of a scene (at most a few scenes are kept)."""
        key = (scene_id, int(floor))
        r = self._scenes.get(key)
        if r is None:
            r = Renderer(load_scene(self.settings, scene_id, floor))
            self._scenes[key] = r
            while len(self._scenes) > MAX_CACHED_SCENES:
                self._scenes.popitem(last=False)
        else:
            self._scenes.move_to_end(key)
        return r

    def episode_of(self, robot: str) -> _Episode | None:
        """The robot's episode in memory (the sim drives one episode per robot)."""
        for eid, meta in list(self.meta.items()):
            if meta.robot == robot and eid in self.episodes:
                return self.episodes[eid]
        return None

    def _drop_memory(self, robot: str) -> None:
        """Forget the robot's episodes in memory (their stored state stays: another instance renders them)."""
        for eid, meta in list(self.meta.items()):
            if meta.robot == robot:
                self._forget(eid)

    # ---- state (EpisodeService hooks) ----------------------------------------------------------------------
    def dump_state(self, state: _Episode, **extra: Any) -> Any:
        data: dict[str, Any] = {"start": state.start.model_dump(mode="json"), "pose": state.pose.model_dump(),
                                "step": state.step, "trajectory": [list(p) for p in state.trajectory],
                                "collisions": state.collisions, "saved_at": time.time()}
        if state.task is not None:
            data["task"] = state.task.to_json()
            data["skill"] = state.skill.model_dump(mode="json") if state.skill is not None else None
        return data

    def load_state(self, episode_id: str, data: Any) -> _Episode:
        try:
            start = EpisodeStart.model_validate(data["start"])
            if start.episode_id != episode_id:
                raise ValueError(f"the stored start is of episode {start.episode_id}")
            renderer = self.renderer(start.question.scene, start.question.floor)
            ep = _Episode(episode_id, renderer.scene, renderer, Pose2D.model_validate(data["pose"]),
                          start.max_steps, start, step=int(data["step"]),
                          trajectory=[(float(p[0]), float(p[1])) for p in data["trajectory"]],
                          collisions=int(data.get("collisions", 0)))
            if data.get("task"):
                ep.task = SimTask.from_json(data["task"])
                ep.skill = SkillReport.model_validate(data["skill"]) if data.get("skill") else None
        except Exception as exc:
            raise ValueError(f"{type(exc).__name__}: {exc}") from exc
        return ep

    def answered_step(self, episode_id: str, state: _Episode) -> int:
        """The goal the current frame answers (the sim's step k answers the planner's goal of step k - 1)."""
        return state.step - 1

    def _resume_stored(self) -> None:
        """At start: take up the robots' episodes stored by a previous process within the watchdog's time
        (older ones the gateway has failed already; of several of one robot the newest); their frames are sent
        again if no goal comes."""
        prefix = episode_state_key(self.name, "")
        newest: dict[str, tuple[float, str]] = {}
        for key in self.store.keys(prefix):
            episode_id = key[len(prefix):]
            raw = self.store.get(key)
            if raw is None or episode_id in self.episodes:
                continue
            try:
                body = unpackb(raw)
                robot = str(body["robot"])
                saved_at = float(body["state"].get("saved_at", 0.0))
            except (CodecError, KeyError, TypeError, ValueError, AttributeError):
                continue  # restoring it reports and drops it
            if self.episode_of(robot) is not None or not self.owns(robot):
                continue
            if time.time() - saved_at >= self.settings.episode_timeout_s:
                continue
            if self.store.get(episode_end_key(episode_id)) is not None:  # it ended while this sim was down
                self.store.delete(key)
                continue
            if robot not in newest or saved_at > newest[robot][0]:
                newest[robot] = (saved_at, episode_id)
        for robot, (_, episode_id) in newest.items():
            if self.episode(episode_id) is not None:
                step = self.episodes[episode_id].step
                log.info("robot %s: episode %s restored at step %d", robot, episode_id, step)
                if self._redrive is not None:  # its frame may never have reached anyone
                    self._redrive.schedule({robot: (episode_id, step)}, time.monotonic())

    def _driven(self) -> dict[str, tuple[str, int]]:
        """``robot -> (episode, current step)`` of the episodes this instance drives."""
        return {meta.robot: (eid, self.episodes[eid].step) for eid, meta in list(self.meta.items())
                if eid in self.episodes and self.owns(meta.robot)}

    def _downstream_changed(self, service: str, instance: str, up: bool) -> None:
        if self._redrive is None:
            return
        robots = self._redrive.changed(service, instance, up, self._driven(), time.monotonic())
        if robots:
            log.info("%s %s %s: current frames of %s to be sent again", service, instance,
                     "appeared" if up else "vanished", ", ".join(sorted(robots)))

    def _redrive_due(self) -> None:
        """Send again the frames :class:`eqa.sharding.Redrive` says are due, unless the robot moved on since."""
        if self._redrive is None or not self._redrive.pending():
            return
        now = time.monotonic()
        for robot, (episode_id, step) in self._redrive.due(now).items():  # type: ignore[misc]
            ep = self.episodes.get(episode_id)
            if ep is None or ep.step != step or not self.owns(robot):
                continue
            ep.emitted_at = now  # the resend timer starts again from here
            log.info("robot %s episode %s: instances downstream changed; frame sent again for step %d", robot,
                     episode_id, step)
            metrics.inc(metrics.RESENDS, self.name, "redrive")
            self.publish(robot, keys.SIM_FRAME, self.render_frame(ep))

    def _resend_stale(self) -> None:
        """Send the current frame again for every episode whose goal has not come back in time."""
        now = time.monotonic()
        for eid, ep in list(self.episodes.items()):
            meta = self.meta.get(eid)
            if meta is None or now - ep.emitted_at < self.settings.step_resend_s:
                continue
            robot = meta.robot
            if not self.owns(robot):  # moved away: its new owner resends
                continue
            if ep.resends >= self.settings.step_resends_max:
                if ep.resends == self.settings.step_resends_max:
                    ep.resends += 1
                    log.error("robot %s episode %s: no goal for step %d after %d resends; waiting for the "
                              "gateway's watchdog", robot, ep.episode_id, ep.step, self.settings.step_resends_max)
                continue
            ep.resends += 1
            ep.emitted_at = now
            metrics.inc(metrics.RESENDS, self.name, "frame")
            log.warning("robot %s episode %s: no goal for step %d within %g s; frame sent again (%d of %d)",
                        robot, ep.episode_id, ep.step, self.settings.step_resend_s, ep.resends,
                        self.settings.step_resends_max)
            self.publish(robot, keys.SIM_FRAME, self.render_frame(ep))

    # ---- sharding ----------------------------------------------------------------------------------------
    def _claim(self, robot: str, episode_id: str, step: int) -> bool:
        """Claim rendering ``step``; when the step before was rendered elsewhere, drop the copy in memory so the
        stored state is read."""
        if self.shard is None:
            return True
        claim = self.shard.claim(episode_id, step)
        if not claim.won:
            log.info("robot %s episode %s step %d is %s's; not rendered here", robot, episode_id, step, claim.holder)
            return False
        if claim.stale:
            self._drop_memory(robot)
        return True

    def _robots_moved(self, gained: set[str], lost: set[str]) -> None:
        super()._robots_moved(gained, lost)
        if gained:
            self._resume_stored()
        for robot in gained:  # its owner died before it stored the episode's first step
            if self.episode_of(robot) is not None:
                continue
            start = self.shard.latest_start(robot) if self.shard is not None else None
            if isinstance(start, EpisodeStart) and self.store.get(episode_end_key(start.episode_id)) is None:
                log.info("robot %s moved here before its episode %s began; starting it", robot, start.episode_id)
                self._on_start(robot, start)

    # ---- handlers ----------------------------------------------------------------------------------------
    def start_episode(self, robot: str, start: EpisodeStart) -> _Episode | None:
        """Start an episode (the robot's previous one ends here). Any failure answers the episode with an
        ErrorReply at once (the gateway fails it and frees the robot), never silence until the watchdog."""
        if not self._claim(robot, start.episode_id, 0):
            return None
        for eid, meta in list(self.meta.items()):
            if meta.robot == robot:
                self.drop(eid)
        q = start.question
        try:
            renderer = self.renderer(q.scene, q.floor)
        except (SceneNotFound, SceneLoadError, hmeqa.HMEQAError) as exc:
            self.error(robot, start.episode_id, 0, str(exc))
            return None
        scene = renderer.scene
        if q.start_pose is not None:
            pose = q.start_pose
            reason = pose_error(scene, pose)
            if reason is not None:
                self.error(robot, start.episode_id, 0, f"start pose refused: {reason}")
                return None
        else:
            try:
                pose = sample_start_pose(scene, np.random.default_rng(start.seed), START_CLEARANCE)
            except ValueError as exc:
                self.error(robot, start.episode_id, 0, str(exc))
                return None
        if start.task is not None and not start.task.object_ids:
            from services.sim.tasks import scene_lacks

            lacks = scene_lacks(start.task, scene)
            if lacks is not None:  # its skills could never succeed: refused like a bad start pose
                self.error(robot, start.episode_id, 0, f"task refused: {lacks}")
                return None
        ep = _Episode(start.episode_id, scene, renderer, pose, start.max_steps, start)
        ep.task = SimTask.from_start(start, scene, pose)
        return ep

    def started(self, robot: str, episode_id: str, state: _Episode) -> None:
        self._log_static(state)
        self._emit(robot, state)

    def on_goal(self, robot: str, goal: Goal) -> None:
        if goal.done or goal.episode_id in self._ended:
            ep = self.episodes.get(goal.episode_id)
            if goal.done and ep is not None and ep.task is not None and self.owns(robot):  # the trace keeps the end
                ep.task.episode.end_reason = goal.reason[:300]
                self.store.set_json(task_trace_key(ep.episode_id), ep.task.episode.trace_doc(),
                                    ttl_s=EPISODE_STATE_TTL_S)
            return
        if not self.owns(robot) or not self._claim(robot, goal.episode_id, goal.step + 1):
            return
        ep = self.episodes.get(goal.episode_id)
        if ep is None:
            ep = self.episode(goal.episode_id)  # from the store (a restarted sim, or the robot moved here)
            if ep is None:
                log.debug("goal for unknown episode %s of robot %s ignored", goal.episode_id, robot)
                return
            for eid, meta in list(self.meta.items()):  # one episode per robot in memory
                if meta.robot == robot and eid != goal.episode_id:
                    self._forget(eid)
        if goal.step != ep.step:
            log.warning("robot %s: goal for step %d while at step %d ignored", robot, goal.step, ep.step)
            return
        reason = goal_not_taken(goal.pose, ep.step, ep.max_steps)
        if reason is not None:
            self.error(robot, ep.episode_id, goal.step, reason)
            return
        assert goal.pose is not None
        reason = pose_error(ep.scene, goal.pose)
        if reason is not None:
            self.error(robot, ep.episode_id, goal.step, f"goal refused: {reason}")
            return
        before = ep.pose
        ep.pose = goal.pose
        ep.step += 1
        self._emit(robot, ep, goal, before)

    def finish_episode(self, robot: str, msg: EpisodeCancel | EpisodeEnd, state: _Episode) -> None:
        if isinstance(msg, EpisodeCancel):
            log.info("robot %s: episode %s cancelled (%s)", robot, msg.episode_id, msg.reason)
        if self.shard is not None and self.shard.claims is not None:  # they would expire; not wait for it
            self.shard.claims.forget(state.episode_id, state.step + 1)

    # ---- rendering ---------------------------------------------------------------------------------------
    def render_frame(self, ep: _Episode) -> Frame:
        w, h = self.settings.sim_width, self.settings.sim_height
        T = camera_pose(ep.pose)
        held = ep.task.episode.held_id if ep.task is not None else None  # a held object is not where it was
        out = ep.renderer.render(T, self._K, w, h, frozenset() if held is None else frozenset({held}))
        return Frame(
            episode_id=ep.episode_id, step=ep.step, pose=ep.pose, camera_pose=T, intrinsics=self._K,
            rgb=out.rgb, depth=out.depth, instances=out.instances, labels=ep.renderer.labels(out.instances),
            scene=ep.scene.id, floor_area_m2=ep.scene.floor_area_m2, skill=ep.skill,
        )

    @metrics.timed_step("sim", "goal")
    def _emit(self, robot: str, ep: _Episode, goal: Goal | None = None, before: Pose2D | None = None) -> None:
        frame = self.render_frame(ep)
        if ep.task is not None and frame.instances is not None:
            if goal is not None and before is not None:  # the motion's collisions, then the goal's skill
                ep.skill = ep.task.after_goal(ep.scene, before, goal, frame.instances)
                if ep.skill is not None and ep.skill.skill == "pick" and ep.skill.success:
                    frame = self.render_frame(ep)  # the picked object is in the gripper now, not in view
                frame.skill = ep.skill
                if ep.skill is not None:
                    log.info("episode %s step %d: %s %s (%s)", ep.episode_id, ep.step, ep.skill.skill,
                             "succeeded" if ep.skill.success else "failed", ep.skill.reason)
            ep.task.observe(ep.scene, ep.pose, frame.instances)
        if goal is not None and before is not None:
            self._count_collision(ep, before, goal)
        ep.emitted_at, ep.resends = time.monotonic(), 0
        ep.trajectory.append((ep.pose.x, ep.pose.y))
        if ep.task is not None:
            ep.task.record(ep.step, ep.pose, goal, frame.skill)
            self.store.set_json(task_metrics_key(ep.episode_id), ep.task.metrics(), ttl_s=EPISODE_STATE_TTL_S)
            self.store.set_json(task_trace_key(ep.episode_id), ep.task.episode.trace_doc(), ttl_s=EPISODE_STATE_TTL_S)
        self.save(ep.episode_id)
        self.publish(robot, keys.SIM_FRAME, frame)
        self._log_step(ep, frame)

    def _count_collision(self, ep: _Episode, before: Pose2D, goal: Goal) -> None:
        """One collision model for question and task episodes (docs/results/helios-collisions.md): a base
        motion counts one collision when its path passes closer than the robot's collision radius to the true
        scene. A task episode's count is its TaskEpisode's (the same test, made in ``after_goal``); a question
        episode's is made here. Questions have no collision metric (EQA): the count is kept with the episode's
        state and logged, and their planner keeps its own clearances."""
        if ep.task is not None:
            ep.collisions = ep.task.episode.collisions
            return
        assert goal.pose is not None
        if skills.path_collides(ep.scene, skills.motion_path((before.x, before.y), goal.path,
                                                             (goal.pose.x, goal.pose.y))):
            ep.collisions += 1
            log.warning("episode %s step %d: the motion hit an obstacle (%d collisions)", ep.episode_id, ep.step,
                        ep.collisions)

    def _log_static(self, ep: _Episode) -> None:
        recorder = self.recorders.get(ep.episode_id)
        if recorder is None or not recorder.enabled:
            return
        import rerun as rr

        sc = ep.scene
        if sc.triangle_colors is not None and len(sc.triangles) < 200_000:
            recorder.log("world/scene", rr.Mesh3D(vertex_positions=sc.vertices[sc.triangles].reshape(-1, 3),
                                             vertex_colors=np.repeat(sc.triangle_colors, 3, axis=0)), static=True)

    def _log_step(self, ep: _Episode, frame: Frame) -> None:
        recorder = self.recorders.get(ep.episode_id)
        if recorder is None or not recorder.enabled:
            return
        import rerun as rr

        recorder.set_step(frame.step)
        recorder.log("camera/rgb", rr.Image(frame.rgb))
        recorder.log("camera/depth", rr.DepthImage(frame.depth, meter=1.0))
        T = frame.camera_pose
        recorder.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        recorder.log("world/camera", rr.Pinhole(image_from_camera=frame.intrinsics,
                                           resolution=[frame.rgb.shape[1], frame.rgb.shape[0]]))
        p = frame.pose
        recorder.log("world/robot", rr.Arrows3D(origins=[[p.x, p.y, 0.05]],
                                           vectors=[[0.5 * np.cos(p.yaw), 0.5 * np.sin(p.yaw), 0.0]]))
        pts = [[x, y, 0.05] for x, y in ep.trajectory]
        recorder.log("world/trajectory", rr.LineStrips3D([pts]))
        if frame.skill is not None:
            s = frame.skill
            recorder.log("sim/task", rr.TextLog(f"{s.skill} {'succeeded' if s.success else 'failed'}: {s.reason}"))
        if ep.task is not None and ep.task.episode.trace:
            e = ep.task.episode.trace[-1]
            nums = ", ".join(f"{k} {v:.3g}" for k, v in e["numbers"].items())
            text = (f"step {e['step']}: {e['phase'] or 'start'}" + (f", {e['skill']}" if e["skill"] else "")
                    + (f" on #{e['target']}" if e["target"] is not None else "") + (f" ({nums})" if nums else "")
                    + (" -- COLLISION" if e["collided"] else ""))
            recorder.log(ENTITIES["task_phase"], rr.TextLog(text, level="WARN" if e["collided"] else "INFO"))
            for k in ("FindObj", "Pick", "FindRec", "Place", "collisions", "pick_attempts"):
                recorder.log(f"{ENTITIES['task_flags']}/{k}", rr.Scalars([float(e[k])]))
