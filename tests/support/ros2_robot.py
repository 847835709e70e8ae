"""A test ROS 2 robot that speaks rmw_zenoh without ROS 2 and without the bridge's code or libraries: it stands
for a real robot (ROS 2 itself cannot be installed here).

Independent of the bridge (which takes hashes and CDR from ``rosbags``): the type hashes come from the separate
RIHS01 implementation of tests/support/ros2_defs.py (checked there against hashes ROS 2 generated), the CDR of
what it publishes from ``mcap-ros2-support``'s serialiser fed those definitions, the topic keys from
``pamoja-ros2`` (a third-party rmw_zenoh key assembler: ``<domain>/<name>/<DDS type>/<RIHS01 hash>``) or, on
Humble, whose keys carry ``TypeHashNotSupported`` (which pamoja refuses), written out here; the goals it receives
are decoded by hand from the CDR byte layout of ``geometry_msgs/PoseStamped`` (encapsulation header, int32 sec,
uint32 nanosec, string frame_id, 7 float64) and their attachments by zenoh's own ``zenoh.ext`` deserialiser
(int64, int64, bytes: zenoh-cpp's ``ext::Serializer`` layout that rmw_zenoh writes). It subscribes to the goal
topic's exact key in its distribution's form, as rmw_zenoh does, so goals with another hash never reach it. The
views are rendered by the simulator's renderer (services/sim/render.py) at the robot's pose.

Behaviours: ``good`` drives to each goal in ``travel_s`` and publishes colour (``bgr8``), depth (``16UC1``
millimetres), camera_info and odometry at ``rate_hz``; ``stuck`` never moves; ``garbage`` publishes images of a
wrong encoding, depth of another size, NaN odometry and stale stamps.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from typing import Any

import numpy as np
import pamoja.ros2 as pr
import zenoh
import zenoh.ext as ze

from services.sim.camera import camera_pose, intrinsics
from services.sim.render import Renderer
from services.sim.scene import Scene
from support import ros2_defs


def key(domain: int, fqn: str, typename: str, distro: str = "jazzy") -> str:
    if distro == "humble":
        dds = pr.dds_type_name(typename)
        assert dds is not None, typename
        return f"{domain}/{fqn.strip('/')}/{dds}/TypeHashNotSupported"
    k = pr.entity_key(domain, fqn, typename, ros2_defs.rihs01(typename))
    assert k is not None, (fqn, typename)
    return str(k)


def decode_pose_stamped(data: bytes) -> tuple[int, str, tuple[float, ...]]:
    """(stamp ns, frame_id, (x, y, z, qx, qy, qz, qw)) of little-endian CDR ``geometry_msgs/PoseStamped``."""
    assert data[:2] == b"\x00\x01", "CDR_LE encapsulation"
    body = data[4:]
    sec, nsec, n = struct.unpack_from("<iII", body, 0)
    frame = body[12:12 + n - 1].decode()
    off = 12 + n
    off += (-off) % 8  # float64 alignment, relative to the body
    vals = struct.unpack_from("<7d", body, off)
    return sec * 1_000_000_000 + nsec, frame, vals


def decode_attachment(att: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh publication attachment."""
    seq, ts, gid = ze.z_deserialize(tuple[ze.Int64, ze.Int64, bytes], zenoh.ZBytes(att))
    return int(seq), int(ts), bytes(gid)


def _header(t_ns: int, frame: str) -> dict[str, Any]:
    return {"stamp": {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}, "frame_id": frame}


class TestRobot:
    def __init__(self, session: zenoh.Session, scene: Scene, start: tuple[float, float, float], *,
                 namespace: str = "/robot0", domain: int = 0, width: int = 160, height: int = 120,
                 behaviour: str = "good", rate_hz: float = 8.0, travel_s: float = 0.4, distro: str = "jazzy") -> None:
        self.s, self.ns, self.domain, self.distro = session, namespace, domain, distro
        self.renderer = Renderer(scene)
        self.w, self.h = width, height
        self.K = intrinsics(width, height)
        self.x, self.y, self.yaw = start
        self.behaviour, self.rate_hz, self.travel_s = behaviour, rate_hz, travel_s
        self.goals: list[tuple[int, str, tuple[float, ...]]] = []
        self.attachments: list[bytes] = []
        self._target: tuple[float, float, float, float] | None = None  # x, y, yaw, arrive_at
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._pubs = {
            "rgb": self._pub("camera/color/image_raw", "sensor_msgs/msg/Image"),
            "depth": self._pub("camera/depth/image_raw", "sensor_msgs/msg/Image"),
            "info": self._pub("camera/color/camera_info", "sensor_msgs/msg/CameraInfo"),
            "odom": self._pub("odom", "nav_msgs/msg/Odometry"),
        }
        self.goal_key = key(domain, f"{namespace}/goal_pose", "geometry_msgs/msg/PoseStamped", distro)
        self._sub = session.declare_subscriber(self.goal_key, self._on_goal)
        self._thread = threading.Thread(target=self._run, name="test-robot", daemon=True)

    def _pub(self, topic: str, typename: str) -> tuple[Any, str]:
        return self.s.declare_publisher(key(self.domain, f"{self.ns}/{topic}", typename, self.distro)), typename

    def _put(self, name: str, msg: dict[str, Any]) -> None:
        pub, typename = self._pubs[name]
        pub.put(ros2_defs.cdr(typename, msg))

    def _on_goal(self, sample: zenoh.Sample) -> None:
        g = decode_pose_stamped(sample.payload.to_bytes())
        att = sample.attachment
        with self._lock:
            self.goals.append(g)
            self.attachments.append(att.to_bytes() if att is not None else b"")
            if self.behaviour != "stuck":
                x, y, _z, qx, qy, qz, qw = g[2]
                yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
                self._target = (x, y, yaw, time.monotonic() + self.travel_s)

    def start(self) -> TestRobot:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._sub.undeclare()
        for pub, _ in self._pubs.values():
            pub.undeclare()

    def _run(self) -> None:
        while not self._stop.wait(1.0 / self.rate_hz):
            with self._lock:
                if self._target is not None and time.monotonic() >= self._target[3]:
                    self.x, self.y, self.yaw = self._target[:3]
                    self._target = None
            self._publish(time.time_ns())

    def _publish(self, t_ns: int) -> None:
        from eqa.messages import Pose2D

        pose = Pose2D(x=self.x, y=self.y, yaw=self.yaw)
        out = self.renderer.render(camera_pose(pose), self.K, self.w, self.h)
        bgr = np.ascontiguousarray(out.rgb[..., ::-1])
        depth_mm = np.clip(np.round(out.depth * 1000.0), 0, 65535).astype("<u2")
        rgb_enc, depth_h, odom_x, stamp = "bgr8", self.h, self.x, t_ns
        if self.behaviour == "garbage":
            rgb_enc, depth_h, odom_x, stamp = "yuv422", self.h // 2, float("nan"), t_ns - 3_600_000_000_000
        hdr = _header(t_ns, "camera_optical_frame")
        self._put("rgb", {"header": hdr, "height": self.h, "width": self.w, "encoding": rgb_enc, "is_bigendian": 0,
                          "step": self.w * 3, "data": bgr.tobytes()})
        self._put("depth", {"header": _header(stamp, "camera_optical_frame"), "height": depth_h, "width": self.w,
                            "encoding": "16UC1", "is_bigendian": 0, "step": self.w * 2,
                            "data": depth_mm[:depth_h].tobytes()})
        p = np.zeros((3, 4))
        p[:, :3] = self.K
        self._put("info", {"header": hdr, "height": self.h, "width": self.w, "distortion_model": "plumb_bob",
                           "d": [0.0] * 5, "k": self.K.reshape(-1).tolist(), "r": np.eye(3).reshape(-1).tolist(),
                           "p": p.reshape(-1).tolist(), "binning_x": 0, "binning_y": 0,
                           "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}})
        q = (0.0, 0.0, math.sin(self.yaw / 2), math.cos(self.yaw / 2))
        zero = {"x": 0.0, "y": 0.0, "z": 0.0}
        self._put("odom", {
            "header": _header(stamp, "map"), "child_frame_id": "base_link",
            "pose": {"pose": {"position": {"x": odom_x, "y": self.y, "z": 0.0},
                              "orientation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]}}, "covariance": [0.0] * 36},
            "twist": {"twist": {"linear": zero, "angular": zero}, "covariance": [0.0] * 36}})
