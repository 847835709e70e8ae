"""The simulator service: renders the robot's view for each episode step.

On ``EpisodeStart`` it loads (or generates) the question's scene, places the robot at the question's
start pose (or samples one with 0.5 m clearance, seeded by ``EpisodeStart.seed``) and publishes step 0;
on a ``Goal`` of that episode it moves the robot to the goal pose and publishes the next step. A bad scene,
a pose in collision, off the floor or not finite, or a mesh that does not parse gets an ``ErrorReply`` on
``sim/error`` (with episode and step), and the service goes on serving every robot.

After every frame the robot's state (episode start, pose, step, trajectory) is written to the store under
``eqa:sim:robot:{robot}``, so a sim restarted between two steps continues the episode at the next goal; a
restarted sim also takes up the recent states it finds there at start.

A message lost while a service restarted would stall an episode: the sim sends the frame of a step again when
no goal came back within ``EQA_STEP_RESEND_S`` (at most ``EQA_STEP_RESENDS_MAX`` times per step), and the
mapper, stopper and planner answer a repeated step by publishing their output for it again, so the goal comes
back and the episode goes on. After the last resend the gateway's watchdog ends the episode with a reason.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from eqa import keys
from eqa.bus import Bus
from eqa.codec import unpackb
from eqa.messages import EpisodeCancel, EpisodeEnd, EpisodeStart, ErrorReply, Frame, Goal, Pose2D, SkillReport
from eqa.recording import EpisodeRecorder
from eqa.service import Service
from eqa.settings import Settings
from eqa.sharding import Shard
from eqa.store import EPISODE_STATE_TTL_S, Store, episode_end_key, task_metrics_key
from services.sim import hmeqa
from services.sim.camera import camera_pose, intrinsics
from services.sim.library import load_or_generate
from services.sim.motion import START_CLEARANCE, pose_error, sample_start_pose
from services.sim.render import Renderer
from services.sim.scene import GEN_ID, Scene, SceneLoadError, SceneNotFound, load_mesh_scene
from services.sim.task_runner import SimTask

log = logging.getLogger(__name__)
MAX_CACHED_SCENES = 4


def state_key(robot: str) -> str:
    return f"eqa:sim:robot:{robot}"


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
    recorder: EpisodeRecorder | None = None
    emitted_at: float = field(default_factory=time.monotonic)  # when the current step's frame was sent
    resends: int = 0  # of the current step
    task: SimTask | None = None  # a task episode's skills and metrics (issue 17)
    skill: SkillReport | None = None  # the skill outcome of the current step (on its frame, resends too)


def load_scene(settings: Settings, scene_id: str, floor: int = 0) -> Scene:
    """A scene by id: generated houses from ``scenes_path``; HM3D scans from ``hm3d_dir`` (floor height
    from ``scene_init_poses.csv`` there when present); other meshes from ``scenes_path``."""
    if not GEN_ID.match(scene_id) and settings.hm3d_dir is not None:
        path = hmeqa.scan_path(settings.hm3d_dir, scene_id)
        if path is not None:
            floor_z = 0.0
            poses_file = Path(settings.hm3d_dir) / hmeqa.POSES_FILE
            if poses_file.is_file():
                init = hmeqa.load_init_poses(poses_file).get((scene_id, floor))
                floor_z = init.floor_height if init else 0.0
            return load_mesh_scene(path, scene_id=scene_id, floor_z=floor_z)
    return load_or_generate(scene_id, settings.scenes_path, settings.hm3d_dir)


class SimService(Service):
    """Simulator: scenes, RGB-D + instance rendering, robot motion."""

    name = "sim"
    description = "Simulator: renders RGB, depth and instance ids of generated houses or real meshes."

    def __init__(self, settings: Settings, bus: Bus | None = None, store: Store | None = None) -> None:
        super().__init__(settings, bus, store)
        self._episodes: dict[str, _Episode] = {}
        self._scenes: OrderedDict[tuple[str, int], Renderer] = OrderedDict()
        self._K = intrinsics(settings.sim_width, settings.sim_height)
        self.shard: Shard | None = None

    def setup(self) -> None:
        # Robots shared among the live sim instances (eqa.sharding; EQA_SHARD): this one drives only its own,
        # claims each step it renders, and takes a robot that moves here up from the store.
        self.shard = Shard(self.bus, lambda: self.store, self.name, self.bus.instance,
                           on_moved=lambda gained, lost: self.submit(self._robots_moved, gained, lost),
                           enabled=self.settings.shard).start()
        self.on(keys.EPISODE_START, self.on_start, on_invalid=self.on_invalid_start)
        self.on(keys.PLANNER_GOAL, self.on_goal)
        self.on(keys.EPISODE_CANCEL, self.on_cancel)
        self.on(keys.EPISODE_END, self.on_end)
        self.submit(self._resume_stored)
        if self.settings.step_resend_s > 0:
            self.every(min(1.0, self.settings.step_resend_s / 4), self._resend_stale)

    def teardown(self) -> None:
        for ep in self._episodes.values():
            if ep.recorder is not None:
                ep.recorder.close()
        self._episodes.clear()

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

    def _error(self, robot: str, episode_id: str | None, step: int | None, reason: str) -> None:
        log.warning("robot %s episode %s step %s: %s", robot, episode_id, step, reason)
        self.publish(robot, keys.SIM_ERROR, ErrorReply(source="sim", episode_id=episode_id, step=step, reason=reason))

    def _close(self, robot: str) -> None:
        ep = self._episodes.pop(robot, None)
        if ep is not None and ep.recorder is not None:
            ep.recorder.close()
        self.store.delete(state_key(robot))

    def _save(self, robot: str, ep: _Episode) -> None:
        state = {"start": ep.start.model_dump(mode="json"), "pose": ep.pose.model_dump(), "step": ep.step,
                 "trajectory": ep.trajectory, "saved_at": time.time()}
        if ep.task is not None:
            state["task"] = ep.task.to_json()
            state["skill"] = ep.skill.model_dump(mode="json") if ep.skill is not None else None
            self.store.set_json(task_metrics_key(ep.episode_id), ep.task.metrics(), ttl_s=EPISODE_STATE_TTL_S)
        self.store.set_json(state_key(robot), state, ttl_s=EPISODE_STATE_TTL_S)

    def _restore(self, robot: str, episode_id: str, state: dict[str, Any] | None = None) -> _Episode | None:
        """The robot's episode from the store (a restarted sim; ``state``: already read), or None."""
        state = state if state is not None else self.store.get_json(state_key(robot))
        if not state or state.get("start", {}).get("episode_id") != episode_id:
            return None
        try:
            start = EpisodeStart.model_validate(state["start"])
            renderer = self.renderer(start.question.scene, start.question.floor)
        except Exception as exc:
            log.error("robot %s: stored state of %s unusable: %s", robot, episode_id, exc)
            return None
        ep = _Episode(episode_id, renderer.scene, renderer, Pose2D.model_validate(state["pose"]), start.max_steps,
                      start, step=int(state["step"]), trajectory=[tuple(p) for p in state["trajectory"]])
        if state.get("task"):
            ep.task = SimTask.from_json(state["task"])
            ep.skill = SkillReport.model_validate(state["skill"]) if state.get("skill") else None
        if start.record and self.settings.record:
            ep.recorder = EpisodeRecorder(self.settings, episode_id, f"sim-resume{ep.step}", enabled=True)
        self._episodes[robot] = ep
        log.info("robot %s: episode %s restored at step %d", robot, episode_id, ep.step)
        return ep

    def _resume_stored(self) -> None:
        """At start: take up the robots' episodes stored by a previous process within the watchdog's time
        (older ones the gateway has failed already); their frames are sent again if no goal comes."""
        prefix = state_key("")
        for key in self.store.keys(prefix):
            robot = key[len(prefix):]
            if robot in self._episodes or not self.owns(robot):
                continue
            state = self.store.get_json(key)
            if not isinstance(state, dict):
                continue
            age = time.time() - float(state.get("saved_at", 0.0))
            episode_id = state.get("start", {}).get("episode_id")
            if not episode_id or age >= self.settings.episode_timeout_s:
                continue
            if self.store.get(episode_end_key(episode_id)) is not None:  # it ended while this sim was down
                self.store.delete(key)
                continue
            self._restore(robot, episode_id, state)

    def _resend_stale(self) -> None:
        """Send the current frame again for every episode whose goal has not come back in time."""
        now = time.monotonic()
        for robot, ep in list(self._episodes.items()):
            if now - ep.emitted_at < self.settings.step_resend_s:
                continue
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
            log.warning("robot %s episode %s: no goal for step %d within %g s; frame sent again (%d of %d)",
                        robot, ep.episode_id, ep.step, self.settings.step_resend_s, ep.resends,
                        self.settings.step_resends_max)
            self.publish(robot, keys.SIM_FRAME, self.render_frame(ep))

    # ---- sharding ----------------------------------------------------------------------------------------
    def owns(self, robot: str) -> bool:
        return self.shard is None or self.shard.owns(robot)

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

    def _drop_memory(self, robot: str) -> None:
        ep = self._episodes.pop(robot, None)
        if ep is not None and ep.recorder is not None:
            ep.recorder.close()

    def _robots_moved(self, gained: set[str], lost: set[str]) -> None:
        for robot in lost:
            self._drop_memory(robot)
        if gained:
            self._resume_stored()
        for robot in gained - set(self._episodes):  # its owner died before it stored the episode's first step
            start = self.shard.latest_start(robot) if self.shard is not None else None
            if isinstance(start, EpisodeStart) and self.store.get(episode_end_key(start.episode_id)) is None:
                log.info("robot %s moved here before its episode %s began; starting it", robot, start.episode_id)
                self.on_start(robot, start)

    # ---- handlers ----------------------------------------------------------------------------------------
    def on_start(self, robot: str, msg: EpisodeStart) -> None:
        """Start an episode. Any failure answers the episode with an ErrorReply at once (the gateway fails it
        and frees the robot), never silence until the watchdog."""
        if not self.owns(robot):
            if self.shard is not None:
                self.shard.remember_start(msg.episode_id, msg)
            return
        if not self._claim(robot, msg.episode_id, 0):
            return
        try:
            self._start_episode(robot, msg)
        except Exception as exc:
            log.exception("robot %s: episode %s could not start", robot, msg.episode_id)
            self._episodes.pop(robot, None)
            self._error(robot, msg.episode_id, 0, f"episode could not start: {type(exc).__name__}: {exc}"[:1000])

    def on_invalid_start(self, robot: str, payload: bytes, reason: str) -> None:
        """An EpisodeStart that does not validate (a pose out of range, a bad scene id): answer its episode at
        once when its id can be read, so the gateway fails it and frees the robot (no wait for the watchdog)."""
        try:
            raw = unpackb(payload, max_decoded=0)  # an EpisodeStart carries no arrays
            episode_id = keys.check_id(raw.get("episode_id"), "episode id")
        except Exception:
            return
        self._error(robot, episode_id, 0, f"episode start refused: {reason}"[:1000])

    def _start_episode(self, robot: str, msg: EpisodeStart) -> None:
        self._close(robot)
        q = msg.question
        try:
            renderer = self.renderer(q.scene, q.floor)
        except (SceneNotFound, SceneLoadError, hmeqa.HMEQAError) as exc:
            self._error(robot, msg.episode_id, 0, str(exc))
            return
        scene = renderer.scene
        if q.start_pose is not None:
            pose = q.start_pose
            reason = pose_error(scene, pose)
            if reason is not None:
                self._error(robot, msg.episode_id, 0, f"start pose refused: {reason}")
                return
        else:
            try:
                pose = sample_start_pose(scene, np.random.default_rng(msg.seed), START_CLEARANCE)
            except ValueError as exc:
                self._error(robot, msg.episode_id, 0, str(exc))
                return
        ep = _Episode(msg.episode_id, scene, renderer, pose, msg.max_steps, msg)
        ep.task = SimTask.from_start(msg)
        if msg.record and self.settings.record:
            ep.recorder = EpisodeRecorder(self.settings, msg.episode_id, "sim", enabled=True)
            self._log_static(ep)
        self._episodes[robot] = ep
        self._emit(robot, ep)

    def on_goal(self, robot: str, goal: Goal) -> None:
        if goal.done:
            return
        if not self.owns(robot) or not self._claim(robot, goal.episode_id, goal.step + 1):
            return
        ep = self._episodes.get(robot)
        if ep is None or ep.episode_id != goal.episode_id:
            ep = self._restore(robot, goal.episode_id)
        if ep is None:
            log.debug("goal for unknown episode %s of robot %s ignored", goal.episode_id, robot)
            return
        if goal.done:
            return
        if goal.step != ep.step:
            log.warning("robot %s: goal for step %d while at step %d ignored", robot, goal.step, ep.step)
            return
        if goal.pose is None:
            self._error(robot, ep.episode_id, goal.step, "goal has no pose and is not done")
            return
        if ep.step + 1 >= ep.max_steps:
            self._error(robot, ep.episode_id, goal.step, f"step limit {ep.max_steps} reached")
            return
        reason = pose_error(ep.scene, goal.pose)
        if reason is not None:
            self._error(robot, ep.episode_id, goal.step, f"goal refused: {reason}")
            return
        before = ep.pose
        ep.pose = goal.pose
        ep.step += 1
        self._emit(robot, ep, goal, before)

    def on_cancel(self, robot: str, msg: EpisodeCancel) -> None:
        if not self.owns(robot):
            self._drop_memory_of(robot, msg.episode_id)
            return
        ep = self._episodes.get(robot)
        if ep is not None and ep.episode_id == msg.episode_id:
            log.info("robot %s: episode %s cancelled (%s)", robot, msg.episode_id, msg.reason)
            self._forget_claims(ep)
            self._close(robot)
        else:
            self._forget(robot, msg.episode_id)

    def on_end(self, robot: str, msg: EpisodeEnd) -> None:
        if not self.owns(robot):
            self._drop_memory_of(robot, msg.episode_id)
            return
        ep = self._episodes.get(robot)
        if ep is not None and ep.episode_id == msg.episode_id:
            self._forget_claims(ep)
            self._close(robot)
        else:
            self._forget(robot, msg.episode_id)

    def _forget_claims(self, ep: _Episode) -> None:
        if self.shard is not None and self.shard.claims is not None:  # they would expire; not wait for it
            self.shard.claims.forget(ep.episode_id, ep.step + 1)

    def _drop_memory_of(self, robot: str, episode_id: str) -> None:
        ep = self._episodes.get(robot)
        if ep is not None and ep.episode_id == episode_id:
            self._drop_memory(robot)

    def _forget(self, robot: str, episode_id: str) -> None:
        """Drop the stored state of an episode this process does not hold (it ended while we were down)."""
        state = self.store.get_json(state_key(robot))
        if state and state.get("start", {}).get("episode_id") == episode_id:
            self.store.delete(state_key(robot))

    # ---- rendering ---------------------------------------------------------------------------------------
    def render_frame(self, ep: _Episode) -> Frame:
        w, h = self.settings.sim_width, self.settings.sim_height
        T = camera_pose(ep.pose)
        out = ep.renderer.render(T, self._K, w, h)
        return Frame(
            episode_id=ep.episode_id, step=ep.step, pose=ep.pose, camera_pose=T, intrinsics=self._K,
            rgb=out.rgb, depth=out.depth, instances=out.instances, labels=ep.renderer.labels(out.instances),
            scene=ep.scene.id, floor_area_m2=ep.scene.floor_area_m2, skill=ep.skill,
        )

    def _emit(self, robot: str, ep: _Episode, goal: Goal | None = None, before: Pose2D | None = None) -> None:
        frame = self.render_frame(ep)
        if ep.task is not None and frame.instances is not None:
            if goal is not None and before is not None:  # the motion's collisions, then the goal's skill
                ep.skill = ep.task.after_goal(ep.scene, before, goal, frame.instances)
                frame.skill = ep.skill
                if ep.skill is not None:
                    log.info("episode %s step %d: %s %s (%s)", ep.episode_id, ep.step, ep.skill.skill,
                             "succeeded" if ep.skill.success else "failed", ep.skill.reason)
            ep.task.observe(ep.scene, ep.pose, frame.instances)
        ep.emitted_at, ep.resends = time.monotonic(), 0
        ep.trajectory.append((ep.pose.x, ep.pose.y))
        self._save(robot, ep)
        self.publish(robot, keys.SIM_FRAME, frame)
        self._log_step(ep, frame)

    def _log_static(self, ep: _Episode) -> None:
        rec = ep.recorder
        if rec is None or not rec.enabled:
            return
        import rerun as rr

        sc = ep.scene
        if sc.triangle_colors is not None and len(sc.triangles) < 200_000:
            rec.log("world/scene", rr.Mesh3D(vertex_positions=sc.vertices[sc.triangles].reshape(-1, 3),
                                             vertex_colors=np.repeat(sc.triangle_colors, 3, axis=0)), static=True)

    def _log_step(self, ep: _Episode, frame: Frame) -> None:
        rec = ep.recorder
        if rec is None or not rec.enabled:
            return
        import rerun as rr

        rec.set_step(frame.step)
        rec.log("camera/rgb", rr.Image(frame.rgb))
        rec.log("camera/depth", rr.DepthImage(frame.depth, meter=1.0))
        T = frame.camera_pose
        rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        rec.log("world/camera", rr.Pinhole(image_from_camera=frame.intrinsics,
                                           resolution=[frame.rgb.shape[1], frame.rgb.shape[0]]))
        p = frame.pose
        rec.log("world/robot", rr.Arrows3D(origins=[[p.x, p.y, 0.05]],
                                           vectors=[[0.5 * np.cos(p.yaw), 0.5 * np.sin(p.yaw), 0.0]]))
        pts = [[x, y, 0.05] for x, y in ep.trajectory]
        rec.log("world/trajectory", rr.LineStrips3D([pts]))
        if frame.skill is not None:
            s = frame.skill
            rec.log("sim/task", rr.TextLog(f"{s.skill} {'succeeded' if s.success else 'failed'}: {s.reason}"))
