"""ROS 2 messages without ROS 2: the standard message definitions and CDR of ``rosbags`` (its ROS 2 Jazzy type
store), shared by the MCAP export and the ROS 2 bridge.

Frames and units follow ROS (REP 103/105): metres, radians, right-handed; ``map`` is the world frame of the
episode (x/y horizontal, z up, the sim's world frame), ``base_link`` the robot base, and camera frames are
optical frames (x right, y down, z forward), the OpenCV convention the sim renders in. Stamps are
``builtin_interfaces/Time`` (seconds + nanoseconds since the epoch).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
T = TYPESTORE.types

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
PATH = "nav_msgs/msg/Path"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"

MAP_FRAME = "map"
BASE_FRAME = "base_link"
CAMERA_FRAME = "camera_optical_frame"


@lru_cache(maxsize=64)
def msgdef(typename: str) -> str:
    """The ``ros2msg`` definition of a type with its dependencies (the text an MCAP schema record holds)."""
    return TYPESTORE.generate_msgdef(typename, ros_version=2)[0]


# rosbags' type store of each distribution with type hashes (Humble has none; rolling follows the newest store)
_STORES = {"jazzy": Stores.ROS2_JAZZY, "kilted": Stores.ROS2_KILTED, "rolling": Stores.LATEST}


@lru_cache(maxsize=8)
def _typestore(distro: str) -> Any:
    if distro not in _STORES:
        raise ValueError(f"no type hashes for ROS 2 {distro!r}; known: {', '.join(_STORES)}")
    return TYPESTORE if distro == "jazzy" else get_typestore(_STORES[distro])


@lru_cache(maxsize=128)
def type_hash(typename: str, distro: str = "jazzy") -> str:
    """The RIHS01 type hash of a type in ``distro``'s definitions (REP 2011; the last part of an rmw_zenoh key
    expression from Iron on)."""
    return str(_typestore(distro).hash_rihs01(typename))


def dds_type_name(typename: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the type part of an rmw_zenoh key)."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def serialize(msg: object, typename: str) -> bytes:
    """Little-endian CDR with its 4-byte encapsulation header (what rmw_zenoh and ros2 bag carry)."""
    return bytes(TYPESTORE.serialize_cdr(msg, typename))


def deserialize(data: bytes, typename: str) -> Any:
    return TYPESTORE.deserialize_cdr(data, typename)


def stamp(t_ns: int) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))


def stamp_ns(st: Any) -> int:
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def header(t_ns: int, frame_id: str) -> Any:
    return T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=frame_id)


def quat_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def yaw_from_quat(x: float, y: float, z: float, w: float) -> float:
    """Heading (rotation about z) of a quaternion, ZYX convention."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quat_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation matrix (Shepperd's method, numerically safe on every branch)."""
    m = np.asarray(r, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return float(x), float(y), float(z), float(w)


def matrix_from_quat(x: float, y: float, z: float, w: float) -> np.ndarray:
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose(x: float, y: float, z: float, q: tuple[float, float, float, float]) -> Any:
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def pose_stamped(t_ns: int, frame_id: str, x: float, y: float, z: float = 0.0, yaw: float = 0.0) -> Any:
    return T[POSE_STAMPED](header=header(t_ns, frame_id), pose=pose(x, y, z, quat_from_yaw(yaw)))


def pose_stamped_matrix(t_ns: int, frame_id: str, m: np.ndarray) -> Any:
    """A PoseStamped of a 4x4 rigid transform (e.g. camera-to-world)."""
    t = np.asarray(m, dtype=np.float64)
    q = quat_from_matrix(t[:3, :3])
    return T[POSE_STAMPED](header=header(t_ns, frame_id), pose=pose(t[0, 3], t[1, 3], t[2, 3], q))


def path(t_ns: int, frame_id: str, poses: list[Any]) -> Any:
    return T[PATH](header=header(t_ns, frame_id), poses=poses)


def transform_stamped(t_ns: int, parent: str, child: str, m: np.ndarray) -> Any:
    """A ``geometry_msgs/TransformStamped`` of the 4x4 rigid transform ``m`` (child-to-parent, tf2's sense)."""
    t = np.asarray(m, dtype=np.float64)
    q = quat_from_matrix(t[:3, :3])
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(t_ns, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(t[0, 3]), y=float(t[1, 3]), z=float(t[2, 3])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))


def tf_message(transforms: list[Any]) -> Any:
    return T[TF_MESSAGE](transforms=transforms)


def planar(x: float, y: float, yaw: float) -> np.ndarray:
    """4x4 transform of a pose on the floor (x, y, rotation ``yaw`` about z)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def string(text: str) -> Any:
    return T[STRING](data=text)


IMAGE_ENCODINGS: dict[str, tuple[np.dtype[Any], int]] = {
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "mono8": (np.dtype(np.uint8), 1),
    "16UC1": (np.dtype("<u2"), 1),
    "32FC1": (np.dtype("<f4"), 1),
}


def image(t_ns: int, frame_id: str, arr: np.ndarray, encoding: str) -> Any:
    """A ``sensor_msgs/Image`` of an HxW or HxWxC array in one of :data:`IMAGE_ENCODINGS` (little-endian)."""
    dtype, channels = IMAGE_ENCODINGS[encoding]
    a = np.ascontiguousarray(arr, dtype=dtype)
    h, w = a.shape[:2]
    if (a.shape[2] if a.ndim == 3 else 1) != channels:
        raise ValueError(f"{encoding} needs {channels} channel(s), got shape {a.shape}")
    return T[IMAGE](
        header=header(t_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * channels * dtype.itemsize,
        data=np.frombuffer(a.tobytes(), dtype=np.uint8),
    )


def camera_info(t_ns: int, frame_id: str, k: np.ndarray, width: int, height: int) -> Any:
    """A ``sensor_msgs/CameraInfo`` of a distortion-free pinhole (``plumb_bob`` with zero coefficients)."""
    kk = np.asarray(k, dtype=np.float64).reshape(3, 3)
    p = np.zeros((3, 4))
    p[:, :3] = kk
    return T[CAMERA_INFO](
        header=header(t_ns, frame_id),
        height=int(height),
        width=int(width),
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=kk.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=p.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def occupancy_grid(
    t_ns: int, frame_id: str, cells: np.ndarray, resolution: float, origin_x: float, origin_y: float
) -> Any:
    """A ``nav_msgs/OccupancyGrid`` of int8 ``cells`` (rows = +y from the origin, -1 unknown, 0..100)."""
    c = np.ascontiguousarray(cells, dtype=np.int8)
    rows, cols = c.shape
    info = T["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp(t_ns),
        resolution=float(resolution),
        width=cols,
        height=rows,
        origin=pose(origin_x, origin_y, 0.0, (0.0, 0.0, 0.0, 1.0)),
    )
    return T[OCCUPANCY_GRID](header=header(t_ns, frame_id), info=info, data=c.reshape(-1))
