"""A test ROS 2 robot that speaks rmw_zenoh without ROS 2 and without the bridge's code: it stands for a real
robot (ROS 2 itself cannot be installed here).

Independent of the bridge: the topic key expressions are built by ``pamoja-ros2`` (a third-party rmw_zenoh key
assembler: ``<domain>/<name>/<DDS type>/<RIHS01 hash>``), the type hashes and the CDR of the messages it
publishes by ``rosbags``, and the goals it receives are decoded here by hand from the CDR byte layout of
``geometry_msgs/PoseStamped`` (encapsulation header, int32 sec, uint32 nanosec, string frame_id, 7 float64).
``zenoh-ros2-sdk`` was read and not used: it downloads message definitions from git at run time. The views are
rendered by the simulator's renderer (services/sim/render.py) at the robot's pose.

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
from rosbags.typesys import Stores, get_typestore

from services.sim.camera import camera_pose, intrinsics
from services.sim.render import Renderer
from services.sim.scene import Scene

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types


def key(domain: int, fqn: str, typename: str) -> str:
    k = pr.entity_key(domain, fqn, typename, TS.hash_rihs01(typename))
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


def _stamp(t_ns: int) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


def _header(t_ns: int, frame: str) -> Any:
    return T["std_msgs/msg/Header"](stamp=_stamp(t_ns), frame_id=frame)


class TestRobot:
    def __init__(self, session: zenoh.Session, scene: Scene, start: tuple[float, float, float], *,
                 namespace: str = "/robot0", domain: int = 0, width: int = 160, height: int = 120,
                 behaviour: str = "good", rate_hz: float = 8.0, travel_s: float = 0.4) -> None:
        self.s, self.ns, self.domain = session, namespace, domain
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
        self._sub = session.declare_subscriber(key(domain, f"{namespace}/goal_pose", "geometry_msgs/msg/PoseStamped"),
                                               self._on_goal)
        self._thread = threading.Thread(target=self._run, name="test-robot", daemon=True)

    def _pub(self, topic: str, typename: str) -> tuple[Any, str]:
        return self.s.declare_publisher(key(self.domain, f"{self.ns}/{topic}", typename)), typename

    def _put(self, name: str, msg: Any) -> None:
        pub, typename = self._pubs[name]
        pub.put(bytes(TS.serialize_cdr(msg, typename)))

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
        self._put("rgb", T["sensor_msgs/msg/Image"](
            header=hdr, height=self.h, width=self.w, encoding=rgb_enc, is_bigendian=0, step=self.w * 3,
            data=np.frombuffer(bgr.tobytes(), np.uint8)))
        self._put("depth", T["sensor_msgs/msg/Image"](
            header=_header(stamp, "camera_optical_frame"), height=depth_h, width=self.w, encoding="16UC1",
            is_bigendian=0, step=self.w * 2, data=np.frombuffer(depth_mm[:depth_h].tobytes(), np.uint8)))
        p = np.zeros((3, 4))
        p[:, :3] = self.K
        self._put("info", T["sensor_msgs/msg/CameraInfo"](
            header=hdr, height=self.h, width=self.w, distortion_model="plumb_bob", d=np.zeros(5),
            k=self.K.reshape(-1), r=np.eye(3).reshape(-1), p=p.reshape(-1), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
        q = (0.0, 0.0, math.sin(self.yaw / 2), math.cos(self.yaw / 2))
        cov = np.zeros(36)
        self._put("odom", T["nav_msgs/msg/Odometry"](
            header=_header(stamp, "map"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=odom_x, y=self.y, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])), covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)), covariance=cov)))
