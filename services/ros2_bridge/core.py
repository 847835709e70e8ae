"""The pure core of the ROS 2 bridge: rmw_zenoh names, checking and converting ROS messages, arrival at a goal,
and the step's Frame. No I/O; the shell (``service.py``) wires it to Zenoh.

**rmw_zenoh wire format** targeted: rmw_zenoh_cpp 0.1.2 and later on Humble, 0.2.4 and later on Jazzy, 0.6.0 and
later on Kilted and Rolling (the releases whose attachment has no key strings; ros2/rmw_zenoh PR 601 and its
backports; earlier ones are not spoken). From ros2/rmw_zenoh ``rmw_zenoh_cpp/src/detail``:

* a topic is the key expression ``<domain_id>/<fully qualified name without the leading slash>/<DDS type
  name>/<type hash>`` (``liveliness_utils.cpp`` ``TopicInfo``), the hash being the RIHS01 hash of the type on Iron
  and later and the constant ``TypeHashNotSupported`` on Humble (which has no type hashes), so a Humble robot and
  a Jazzy one subscribe to different keys for the same topic;
* each publication carries an attachment (``attachment_helpers.cpp``, zenoh-cpp's ``ext::Serializer``): int64
  sequence number, int64 source timestamp (ns since the epoch), the 16-byte publisher GID as a sequence (LEB128
  length ``0x10``, then the bytes); all little-endian. The sequence number counts per publisher from 1; a
  subscription reports MESSAGE_LOST when a publisher's numbers jump;
* every node, publisher and subscription declares a liveliness token ``@ros2_lv/<domain>/<session zid>/<node
  id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``, each ``/`` inside a
  component written ``%`` and an empty component as ``%``; the QoS component leaves defaults empty;
* an entity's GID is the XXH3-128 hash of its liveliness token's key expression, low 64 bits then high 64 bits,
  each little-endian (``Entity::Entity``), so a subscriber can match a sample's GID to the publisher it saw.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import xxhash

from eqa import ros
from eqa.messages import Pose2D

QOS_DEFAULT = "::,10:,:,:,,"  # reliability, durability, history depth 10, deadline, lifespan, liveliness: defaults
HASH_NOT_SUPPORTED = "TypeHashNotSupported"  # the hash component of every key on Humble


class RosInputError(ValueError):
    """A ROS message the bridge refuses; ``code`` is the counted reason, the message says what was wrong."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


# ---- names ----------------------------------------------------------------------------------------------------
def fully_qualified(namespace: str, topic: str) -> str:
    """``/ns`` + ``topic`` -> ``/ns/topic`` (an absolute ``topic`` stays as it is)."""
    if topic.startswith("/"):
        return "/" + topic.strip("/")
    ns = namespace.strip("/")
    return "/" + "/".join(p for p in (ns, topic.strip("/")) if p)


def key_hash(distro: str, typename: str) -> str:
    """The type hash component of a key expression or token on ``distro``."""
    return HASH_NOT_SUPPORTED if distro == "humble" else ros.type_hash(typename, distro)


def topic_key(domain: int, fqn: str, typename: str, type_hash: str | None = None) -> str:
    """The rmw_zenoh key expression of a topic; ``type_hash=None`` matches any hash (every distribution)."""
    return f"{domain}/{fqn.strip('/')}/{ros.dds_type_name(typename)}/{type_hash or '*'}"


def mangle(name: str) -> str:
    """A name as one liveliness-token component: ``/`` as ``%``, the empty name as ``%``."""
    return name.replace("/", "%") or "%"


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    return f"@ros2_lv/{domain}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace.rstrip('/'))}/{node}"


def endpoint_token(domain: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                   fqn: str, typename: str, distro: str = "jazzy") -> str:
    """The liveliness token of a publisher (``MP``) or subscription (``MS``), with ``distro``'s hash form."""
    if kind not in ("MP", "MS"):
        raise ValueError(f"endpoint kind must be MP or MS, got {kind!r}")
    return (f"@ros2_lv/{domain}/{zid}/{node_id}/{entity_id}/{kind}/%/{mangle(namespace.rstrip('/'))}/{node}/"
            f"{mangle(fqn)}/{ros.dds_type_name(typename)}/{key_hash(distro, typename)}/{QOS_DEFAULT}")


def gid(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh gives the entity of a liveliness token: XXH3-128 of the key expression, low
    64 bits then high 64 bits, little-endian."""
    h = xxhash.xxh3_128_intdigest(token.encode())
    return (h & (2**64 - 1)).to_bytes(8, "little") + (h >> 64).to_bytes(8, "little")


def attachment(sequence: int, timestamp_ns: int, gid: bytes) -> bytes:
    """The rmw_zenoh publication attachment: int64 sequence number, int64 source timestamp, the GID as a
    sequence (LEB128 length, one byte for 16, then the bytes)."""
    if len(gid) != 16:
        raise ValueError("a GID is 16 bytes")
    return struct.pack("<qqB", sequence, timestamp_ns, len(gid)) + gid


@dataclass
class Publisher:
    """One rmw_zenoh publisher: its key expression, its liveliness token, the GID derived from the token and its
    own sequence numbers (from 1, one per publication, as rmw_zenoh's publishers count)."""

    key: str
    token: str
    gid: bytes = b""
    sequence: int = 0  # of the last publication

    def __post_init__(self) -> None:
        self.gid = gid(self.token)

    def next_attachment(self, timestamp_ns: int) -> bytes:
        self.sequence += 1
        return attachment(self.sequence, timestamp_ns, self.gid)


# ---- messages in ---------------------------------------------------------------------------------------------
def _finite(*vals: float) -> bool:
    return all(math.isfinite(float(v)) for v in vals)


def image_array(msg: Any, kind: str, max_pixels: int, depth_unit_m: float) -> np.ndarray:
    """A ``sensor_msgs/Image`` as the Frame's array: colour -> HxWx3 uint8 RGB (``rgb8``/``bgr8``); depth ->
    HxW float32 metres (``32FC1`` metres or ``16UC1`` x ``depth_unit_m``; 0 = no reading, as the sim)."""
    enc = str(msg.encoding)
    allowed = ("rgb8", "bgr8") if kind == "rgb" else ("16UC1", "32FC1")
    if enc not in allowed:
        raise RosInputError("encoding", f"{kind} image encoding {enc!r}; the bridge takes {' or '.join(allowed)}")
    h, w = int(msg.height), int(msg.width)
    if h < 1 or w < 1:
        raise RosInputError("size", f"{kind} image of {w}x{h} pixels")
    if h * w > max_pixels:
        raise RosInputError("huge", f"{kind} image of {w}x{h} pixels, over EQA_ROS2_MAX_IMAGE_PIXELS={max_pixels}")
    dtype, channels = ros.IMAGE_ENCODINGS[enc]
    row = w * channels * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if int(msg.step) < row or data.size != int(msg.step) * h:
        raise RosInputError("size", f"{kind} image {w}x{h} {enc}: step {msg.step} and {data.size} data bytes "
                            f"do not match (need step >= {row} and step*height bytes)")
    rows = data.reshape(h, int(msg.step))[:, :row]
    dt = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    arr = np.frombuffer(rows.tobytes(), dtype=dt).reshape((h, w, channels) if channels > 1 else (h, w))
    if kind == "rgb":
        return np.ascontiguousarray(arr[..., ::-1] if enc == "bgr8" else arr, dtype=np.uint8)
    depth = arr.astype(np.float32) * np.float32(depth_unit_m) if enc == "16UC1" else arr.astype(np.float32)
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0)).astype(np.float32)
    return depth


def intrinsics(msg: Any) -> tuple[np.ndarray, int, int]:
    """``sensor_msgs/CameraInfo`` -> (K, width, height); a pinhole with finite, positive focal lengths."""
    k = np.asarray(msg.k, dtype=np.float64)
    if k.size != 9 or not np.isfinite(k).all():
        raise RosInputError("camera_info", "camera_info K is not 9 finite numbers")
    K = k.reshape(3, 3)
    w, h = int(msg.width), int(msg.height)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 or w < 1 or h < 1:
        raise RosInputError("camera_info", f"camera_info is not a pinhole of a {w}x{h} image (K={K.tolist()})")
    return K, w, h


def odometry_pose(msg: Any) -> tuple[Pose2D, int]:
    p, o = msg.pose.pose.position, msg.pose.pose.orientation
    return _pose2d(p.x, p.y, o.x, o.y, o.z, o.w, "odometry"), ros.stamp_ns(msg.header.stamp)


def tf_pose(msg: Any, map_frame: str, base_frame: str) -> tuple[Pose2D, int] | None:
    """The ``map_frame`` -> ``base_frame`` transform of a TFMessage, or None when it holds none."""
    for t in msg.transforms:
        if t.header.frame_id.lstrip("/") == map_frame and t.child_frame_id.lstrip("/") == base_frame:
            tr, q = t.transform.translation, t.transform.rotation
            return _pose2d(tr.x, tr.y, q.x, q.y, q.z, q.w, "tf"), ros.stamp_ns(t.header.stamp)
    return None


def _pose2d(x: float, y: float, qx: float, qy: float, qz: float, qw: float, what: str) -> Pose2D:
    if not _finite(x, y, qx, qy, qz, qw):
        raise RosInputError("nan_pose", f"{what} pose is not finite")
    if abs(math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw) - 1.0) > 0.01:
        raise RosInputError("nan_pose", f"{what} orientation is not a unit quaternion")
    return Pose2D(x=float(x), y=float(y), yaw=ros.yaw_from_quat(qx, qy, qz, qw))


def check_stamp(stamp_ns: int, now_ns: int, max_age_s: float, what: str) -> None:
    age = (now_ns - stamp_ns) / 1e9
    if stamp_ns <= 0 or age > max_age_s:
        raise RosInputError("stale", f"{what} stamp is {age:.1f} s old (EQA_ROS2_MAX_STAMP_AGE_S={max_age_s:g})")
    if age < -max_age_s:
        raise RosInputError("stale", f"{what} stamp is {-age:.1f} s in the future (clocks not in sync?)")


# ---- arrival ---------------------------------------------------------------------------------------------------
def _yaw_diff(a: float, b: float) -> float:
    return abs(math.atan2(math.sin(a - b), math.cos(a - b)))


@dataclass
class Arrival:
    """Whether the base reached a goal: within ``tol_m`` and ``tol_yaw`` of it, and stayed so (moving less than
    ``tol_m / 4``) for ``settle_s``; ``timeout_s`` after the goal was sent it is refused."""

    goal: Pose2D
    sent_at: float
    tol_m: float
    tol_yaw: float
    settle_s: float
    timeout_s: float
    _inside_since: float | None = None
    _anchor: Pose2D | None = None
    _poses: deque[tuple[float, Pose2D]] = field(default_factory=lambda: deque(maxlen=256))

    def near(self, p: Pose2D) -> bool:
        return (math.hypot(p.x - self.goal.x, p.y - self.goal.y) <= self.tol_m
                and _yaw_diff(p.yaw, self.goal.yaw) <= self.tol_yaw)

    def update(self, p: Pose2D, now: float) -> str:
        """``"arrived"``, ``"timeout"`` or ``"moving"`` after the base pose ``p`` at time ``now``."""
        if self.near(p):
            moved = self._anchor is not None and math.hypot(p.x - self._anchor.x, p.y - self._anchor.y) > self.tol_m / 4
            if self._inside_since is None or moved:
                self._inside_since, self._anchor = now, p
            if now - self._inside_since >= self.settle_s:
                return "arrived"
        else:
            self._inside_since = self._anchor = None
        return "timeout" if now - self.sent_at > self.timeout_s else "moving"


# ---- frames ----------------------------------------------------------------------------------------------------
def base_to_camera(height_m: float, tilt_deg: float) -> np.ndarray:
    """4x4 optical-frame pose of the camera in the base frame: ``height_m`` above the base, looking forward
    (base +x), pitched by ``tilt_deg`` (negative = down); optical axes x right, y down, z forward."""
    ct, st = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    forward = np.array([ct, 0.0, st])
    right = np.array([0.0, -1.0, 0.0])
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, forward, (0.0, 0.0, height_m)
    return T


def camera_to_world(base: Pose2D, base_T_cam: np.ndarray) -> np.ndarray:
    return ros.planar(base.x, base.y, base.yaw) @ base_T_cam


def check_frame(rgb: np.ndarray, depth: np.ndarray, info: tuple[np.ndarray, int, int]) -> None:
    """Colour, depth and camera_info describe the same image."""
    _, w, h = info
    if rgb.shape[:2] != depth.shape or rgb.shape[:2] != (h, w):
        raise RosInputError("mismatch", f"colour {rgb.shape[1]}x{rgb.shape[0]}, depth {depth.shape[1]}x"
                            f"{depth.shape[0]} and camera_info {w}x{h} differ (register depth to colour)")


def goal_pose_stamped(goal: Pose2D, t_ns: int, frame_id: str) -> bytes:
    """A Goal's pose as CDR ``geometry_msgs/PoseStamped`` (z = 0, yaw about z)."""
    if not _finite(goal.x, goal.y, goal.yaw):
        raise ValueError("a goal pose must be finite")
    return ros.serialize(ros.pose_stamped(t_ns, frame_id, goal.x, goal.y, 0.0, goal.yaw), ros.POSE_STAMPED)
