"""The ROS 2 bridge: a ROS 2 robot on rmw_zenoh takes the sim's place for the robots of ``EQA_ROS2_ROBOTS``.

Per robot it subscribes (rmw_zenoh key expressions, CDR payloads) to the colour and depth
``sensor_msgs/Image``, the ``sensor_msgs/CameraInfo`` and the base pose (``nav_msgs/Odometry``, or
``tf2_msgs/TFMessage`` with ``EQA_ROS2_POSE_TYPE=tf``) under ``EQA_ROS2_NAMESPACE``, and publishes each goal as
``geometry_msgs/PoseStamped`` on ``EQA_ROS2_GOAL_TOPIC``. It keeps the sim's contract on the EQA bus
(docs/robots.md): on ``EpisodeStart`` it sends step 0's ``Frame`` as soon as a fresh, consistent RGB-D frame and
pose are in; on a ``Goal`` it sends the goal to the robot, waits for arrival (within tolerance and settled,
:class:`core.Arrival`) and sends the next step's ``Frame``; a goal not reached within ``EQA_ROS2_GOAL_TIMEOUT_S``,
or no usable frame within ``EQA_ROS2_FRAME_TIMEOUT_S``, is answered with an ``ErrorReply`` on ``sim/error`` (the
planner replans, as after a goal the sim refuses; at step 0 the gateway fails the episode). ROS input that is
refused (wrong encoding, mismatched sizes, non-finite poses, stale stamps, huge images, undecodable CDR) is
logged and counted by reason (:attr:`Ros2BridgeService.refused`), and the reason of the last one goes into the
error answer. It declares rmw_zenoh liveliness tokens (a node ``eqa_bridge_<robot>`` with its publisher and
subscriptions) so ROS 2 tools list it. Each robot runs its own ROS 2 distribution (``EQA_ROS2_DISTRO``,
``EQA_ROS2_DISTROS``): its goal key and tokens carry that distribution's type hash form (``TypeHashNotSupported``
on Humble), and its goal publisher has its own GID and sequence numbers (:class:`core.Publisher`), as each
rmw_zenoh publisher does. Task episodes need the robot's pick/place hook
(``EQA_ROS2_PICK_PLACE_SERVICE``); without one they are refused at start with a message saying so.

The bridge keeps its state in memory (one process serves its robots; no sharding): a restarted bridge answers
no running episode, and the gateway's watchdog ends it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from eqa import keys, ros
from eqa.bus import Bus
from eqa.messages import EpisodeCancel, EpisodeEnd, EpisodeStart, ErrorReply, Frame, Goal, Pose2D
from eqa.robot import goal_not_taken
from eqa.service import SHELL_GROUPS, Service
from eqa.settings import Ros2Settings, SettingsGroup
from eqa.store import Store
from services.ros2_bridge import core

log = logging.getLogger(__name__)
TICK_S = 0.05
SOURCE = "ros2_bridge"
MAX_PAYLOAD_OVERHEAD = 4096  # bytes of a ROS image message beyond its pixels (header, strings)


@dataclass
class _Latest:
    value: Any
    stamp_ns: int
    received: float


@dataclass
class _Robot:
    name: str
    namespace: str
    distro: str
    rgb: _Latest | None = None
    depth: _Latest | None = None
    info: _Latest | None = None
    pose: _Latest | None = None
    episode_id: str | None = None
    step: int = 0
    max_steps: int = 1
    phase: str = "idle"  # idle (waiting for a goal), moving, capturing
    since: float = 0.0  # when the phase began
    arrival: core.Arrival | None = None
    goal_step: int = -1
    last_refusal: str = ""


class Ros2BridgeService(Service):
    """ROS 2 robots (rmw_zenoh) in the sim's place."""

    name = "ros2_bridge"
    settings_groups = (*SHELL_GROUPS, Ros2Settings)
    description = "ROS 2 bridge: robots on rmw_zenoh keep the sim's contract (frames, goals, refusals)."

    def __init__(self, settings: SettingsGroup, bus: Bus | None = None, store: Store | None = None) -> None:
        super().__init__(settings, bus, store)
        s = self.settings
        self.robots = {r: _Robot(r, s.ros2_namespace.format(robot=r), s.ros2_distro_of(r)) for r in s.ros2_robots}
        self.refused: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._tokens: list[Any] = []
        # per robot: the Zenoh publisher of its goals and the rmw_zenoh publisher it stands for (own key in the
        # robot's hash form, own GID and sequence numbers: a subscriber tracks both per publisher)
        self._goal_pubs: dict[str, tuple[Any, core.Publisher]] = {}
        self._base_T_cam = core.base_to_camera(s.ros2_camera_height_m, s.ros2_camera_tilt_deg)
        self._max_payload = s.ros2_max_image_pixels * 4 + MAX_PAYLOAD_OVERHEAD

    # ---- wiring --------------------------------------------------------------------------------------------
    def wants(self, robot: str) -> bool:
        return robot in self.robots

    def setup(self) -> None:
        if not self.robots:
            log.warning("EQA_ROS2_ROBOTS is empty: the bridge serves no robot")
        self.on(keys.EPISODE_START, self.on_start, prefilter=True)
        self.on(keys.EPISODE_CANCEL, self.on_finish, prefilter=True)
        self.on(keys.EPISODE_END, self.on_finish, prefilter=True)
        self.on(keys.PLANNER_GOAL, self.on_goal, prefilter=True)
        s = self.settings
        sess: zenoh.Session = self.bus.session
        zid = str(sess.info.zid())
        pose_type = ros.ODOMETRY if s.ros2_pose_type == "odometry" else ros.TF_MESSAGE
        inputs = (("rgb", s.ros2_rgb_topic, ros.IMAGE), ("depth", s.ros2_depth_topic, ros.IMAGE),
                  ("info", s.ros2_info_topic, ros.CAMERA_INFO), ("pose", s.ros2_pose_topic, pose_type))
        for node_id, rb in enumerate(self.robots.values()):
            node = f"eqa_bridge_{rb.name}".replace("-", "_")
            self._tokens.append(sess.liveliness().declare_token(
                core.node_token(s.ros2_domain_id, zid, node_id, rb.namespace, node)))
            for entity_id, (kind, topic, typename) in enumerate(inputs, start=1):
                fqn = core.fully_qualified(rb.namespace, topic)
                key = core.topic_key(s.ros2_domain_id, fqn, typename)
                self._tokens.append(sess.declare_subscriber(key, self._receiver(rb.name, kind, typename)))
                self._tokens.append(sess.liveliness().declare_token(core.endpoint_token(
                    s.ros2_domain_id, zid, node_id, entity_id, "MS", rb.namespace, node, fqn, typename, rb.distro)))
            goal_fqn = core.fully_qualified(rb.namespace, s.ros2_goal_topic)
            goal_hash = core.key_hash(rb.distro, ros.POSE_STAMPED)
            rmw = core.Publisher(
                core.topic_key(s.ros2_domain_id, goal_fqn, ros.POSE_STAMPED, goal_hash),
                core.endpoint_token(s.ros2_domain_id, zid, node_id, len(inputs) + 1, "MP", rb.namespace, node,
                                    goal_fqn, ros.POSE_STAMPED, rb.distro))
            self._goal_pubs[rb.name] = (sess.declare_publisher(rmw.key, encoding=zenoh.Encoding("application/cdr")),
                                        rmw)
            self._tokens.append(sess.liveliness().declare_token(rmw.token))
            log.info("robot %s (ROS 2 %s): topics under %s (domain %d), goals on %s", rb.name, rb.distro,
                     rb.namespace, s.ros2_domain_id, rmw.key)
        self.every(TICK_S, self._tick)

    def teardown(self) -> None:
        for t in reversed(self._tokens + [pub for pub, _ in self._goal_pubs.values()]):
            try:
                t.undeclare()
            except Exception:  # the session may be closing already
                log.debug("undeclare failed", exc_info=True)
        self._tokens.clear()
        self._goal_pubs.clear()

    def _receiver(self, robot: str, kind: str, typename: str) -> Any:
        def on_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            if len(payload) > self._max_payload:  # refused before it is decoded
                self._refuse(robot, core.RosInputError("huge", f"{kind} message of {len(payload)} bytes"))
                return
            self.submit(self._take, robot, kind, typename, payload, time.monotonic())

        return on_sample

    # ---- ROS input -----------------------------------------------------------------------------------------
    def _refuse(self, robot: str, err: core.RosInputError) -> None:
        with self._lock:
            self.refused[err.code] += 1
            n = self.refused[err.code]
        rb = self.robots[robot]
        rb.last_refusal = str(err)
        if n <= 5 or n % 100 == 0:
            log.warning("robot %s: ROS input refused (%s, %d so far): %s", robot, err.code, n, err)

    def _take(self, robot: str, kind: str, typename: str, payload: bytes, received: float) -> None:
        rb = self.robots[robot]
        s = self.settings
        try:
            try:
                msg = ros.deserialize(payload, typename)
            except Exception as exc:
                raise core.RosInputError("cdr", f"{kind}: not a CDR {typename} ({type(exc).__name__})") from exc
            now_ns = time.time_ns()
            if kind == "pose":
                got = core.odometry_pose(msg) if typename == ros.ODOMETRY else core.tf_pose(
                    msg, s.ros2_map_frame, s.ros2_base_frame)
                if got is None:
                    return
                pose, stamp = got
                core.check_stamp(stamp, now_ns, s.ros2_max_stamp_age_s, "pose")
                rb.pose = _Latest(pose, stamp, received)
                return
            stamp = ros.stamp_ns(msg.header.stamp)
            core.check_stamp(stamp, now_ns, s.ros2_max_stamp_age_s, kind)
            if kind == "info":
                rb.info = _Latest(core.intrinsics(msg), stamp, received)
            else:
                arr = core.image_array(msg, kind, s.ros2_max_image_pixels, s.ros2_depth_unit_m)
                setattr(rb, kind, _Latest(arr, stamp, received))
        except core.RosInputError as err:
            self._refuse(robot, err)

    # ---- EQA bus -------------------------------------------------------------------------------------------
    def _error(self, robot: str, episode_id: str, step: int, reason: str) -> None:
        log.warning("robot %s episode %s step %d: %s", robot, episode_id, step, reason)
        self.publish(robot, keys.SIM_ERROR, ErrorReply(source=SOURCE, reason=reason, episode_id=episode_id, step=step))

    def on_start(self, robot: str, start: EpisodeStart) -> None:
        rb = self.robots[robot]
        if start.task is not None and not self.settings.ros2_pick_place_service:
            self._error(robot, start.episode_id, 0, f"robot {robot} has no pick/place hook "
                        "(EQA_ROS2_PICK_PLACE_SERVICE, docs/robots.md): task episodes cannot run on it")
            return
        if start.task is not None:
            self._error(robot, start.episode_id, 0, "the pick/place hook is documented (docs/robots.md) but this "
                        "bridge does not call it yet: task episodes cannot run on ROS 2 robots")
            return
        rb.episode_id, rb.step, rb.max_steps = start.episode_id, 0, start.max_steps
        rb.goal_step, rb.arrival, rb.last_refusal = -1, None, ""
        self._phase(rb, "capturing")
        log.info("robot %s: episode %s started; waiting for a fresh frame", robot, start.episode_id)

    def on_finish(self, robot: str, msg: EpisodeCancel | EpisodeEnd) -> None:
        rb = self.robots[robot]
        if rb.episode_id == msg.episode_id:
            rb.episode_id, rb.arrival = None, None
            self._phase(rb, "idle")

    def on_goal(self, robot: str, goal: Goal) -> None:
        rb = self.robots[robot]
        if goal.done or goal.episode_id != rb.episode_id:
            return
        if goal.step != rb.step or rb.phase != "idle":
            log.info("robot %s: goal for step %d while at step %d (%s) ignored", robot, goal.step, rb.step, rb.phase)
            return
        refused = goal_not_taken(goal.pose, rb.step, rb.max_steps)
        if refused is not None:
            self._error(robot, goal.episode_id, goal.step, refused)
            return
        assert goal.pose is not None
        s = self.settings
        try:
            data = core.goal_pose_stamped(goal.pose, time.time_ns(), s.ros2_map_frame)
        except ValueError as exc:
            self._error(robot, goal.episode_id, goal.step, f"goal refused: {exc}")
            return
        pub, rmw = self._goal_pubs[robot]
        pub.put(data, attachment=rmw.next_attachment(time.time_ns()))
        rb.goal_step = goal.step
        rb.arrival = core.Arrival(goal.pose, time.monotonic(), s.ros2_arrive_tolerance_m,
                                  math.radians(s.ros2_arrive_yaw_tolerance_deg), s.ros2_settle_s,
                                  s.ros2_goal_timeout_s)
        self._phase(rb, "moving")

    def _phase(self, rb: _Robot, phase: str) -> None:
        rb.phase, rb.since = phase, time.monotonic()

    # ---- the step ------------------------------------------------------------------------------------------
    def _tick(self) -> None:
        now = time.monotonic()
        for rb in self.robots.values():
            if rb.episode_id is None:
                continue
            if rb.phase == "moving" and rb.arrival is not None:
                if rb.pose is None or rb.pose.received < rb.arrival.sent_at:
                    state = "timeout" if now - rb.arrival.sent_at > rb.arrival.timeout_s else "moving"
                else:
                    state = rb.arrival.update(rb.pose.value, now)
                if state == "arrived":
                    self._phase(rb, "capturing")
                elif state == "timeout":
                    self._phase(rb, "idle")
                    where = "no pose came" if rb.pose is None else (
                        f"the base is at ({rb.pose.value.x:.2f}, {rb.pose.value.y:.2f})")
                    g = rb.arrival.goal
                    self._error(rb.name, rb.episode_id, rb.goal_step, f"goal ({g.x:.2f}, {g.y:.2f}) not reached "
                                f"within {self.settings.ros2_goal_timeout_s:g} s; {where}")
            elif rb.phase == "capturing":
                frame = self._frame(rb)
                if frame is not None:
                    if rb.goal_step >= 0:
                        rb.step = rb.goal_step + 1
                    frame.step = rb.step
                    self._phase(rb, "idle")
                    self.publish(rb.name, keys.SIM_FRAME, frame)
                elif now - rb.since > self.settings.ros2_frame_timeout_s:
                    self._phase(rb, "idle")
                    why = f"; the last ROS input refused: {rb.last_refusal}" if rb.last_refusal else ""
                    self._error(rb.name, rb.episode_id, max(rb.goal_step, 0),
                                f"no fresh, consistent RGB-D frame and pose within "
                                f"{self.settings.ros2_frame_timeout_s:g} s{why}")

    def _frame(self, rb: _Robot) -> Frame | None:
        """The step's Frame once colour, depth, camera_info and pose all arrived after the phase began, with
        stamps within EQA_ROS2_MAX_STAMP_SKEW_S of each other."""
        parts = (rb.rgb, rb.depth, rb.info, rb.pose)
        if any(p is None or p.received < rb.since for p in parts):
            return None
        rgb, depth, info, pose = parts
        assert rgb is not None and depth is not None and info is not None and pose is not None
        stamps = [rgb.stamp_ns, depth.stamp_ns, pose.stamp_ns]
        if (max(stamps) - min(stamps)) / 1e9 > self.settings.ros2_max_stamp_skew_s:
            return None  # wait for a consistent set (a timeout answers when none comes)
        try:
            core.check_frame(rgb.value, depth.value, info.value)
        except core.RosInputError as err:
            self._refuse(rb.name, err)
            rb.rgb = rb.depth = None
            return None
        assert rb.episode_id is not None
        K = info.value[0]
        return Frame(episode_id=rb.episode_id, step=rb.step, pose=Pose2D.model_validate(pose.value.model_dump()),
                     camera_pose=core.camera_to_world(pose.value, self._base_T_cam), intrinsics=np.array(K),
                     rgb=rgb.value, depth=depth.value)
