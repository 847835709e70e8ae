"""ROS 2 message definitions, their RIHS01 type hashes and their CDR, from nothing the bridge uses.

The bridge (eqa/ros.py) takes definitions, hashes and CDR from ``rosbags``. Here:

* the ``.msg`` definitions of the types the bridge speaks are written out from ROS 2's interface packages
  (common_interfaces, rcl_interfaces: field order, types and array sizes; comments, constants and defaults left
  out, as the hash leaves defaults out);
* the type hash is computed by a separate implementation of REP 2011's RIHS01 written from
  ``rosidl_generator_type_description`` (ros2/rosidl): each type's fields as ``{name, type: {type_id, capacity,
  string_capacity, nested_type_name}}`` with the ``type_description_interfaces/FieldType`` ids, the referenced
  types sorted by name, ``json.dumps(..., separators=(', ', ': '))``, SHA-256, prefix ``RIHS01_``;
* :data:`PUBLISHED` holds hashes as ROS 2 itself generated them (``*__EXPECTED_HASH`` tables in rosidl-generated
  C sources, ``rosidl_generator_c``'s ``idl__description.c``, found in public ROS 2 workspaces; ``std_msgs/String``
  from the example key in rmw_zenoh's ``docs/design.md``);
* CDR comes from ``mcap-ros2-support``'s serialiser, fed the definitions above.
"""

from __future__ import annotations

import hashlib
import json
import re
from functools import lru_cache
from typing import Any

MSG = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/msg/String": "string data",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "nav_msgs/msg/Odometry": ("std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
                              "geometry_msgs/TwistWithCovariance twist"),
    "sensor_msgs/msg/Image": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                              "uint8 is_bigendian\nuint32 step\nuint8[] data"),
    "sensor_msgs/msg/RegionOfInterest": ("uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\n"
                                         "bool do_rectify"),
    "sensor_msgs/msg/CameraInfo": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
                                   "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
                                   "uint32 binning_y\nRegionOfInterest roi"),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "nav_msgs/msg/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses",
    "nav_msgs/msg/MapMetaData": ("builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\n"
                                 "uint32 height\ngeometry_msgs/Pose origin"),
    "nav_msgs/msg/OccupancyGrid": "std_msgs/Header header\nMapMetaData info\nint8[] data",
}

# Hashes ROS 2 generated (Iron and later share them for these types), 32 bytes as rosidl writes them.
PUBLISHED = {
    "builtin_interfaces/msg/Time": "b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
    "std_msgs/msg/String": "df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "std_msgs/msg/Header": "f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "geometry_msgs/msg/Point": "6963084842a9b04494d6b2941d11444708d892da2f4b09843b9c43f42a7f6881",
    "geometry_msgs/msg/Quaternion": "8a765f66778c8ff7c8ab94afcc590a2ed5325a1d9a076ffff38fbce36f458684",
    "geometry_msgs/msg/Pose": "d501954e9476cea2996984e812054b68026ae0bfae789d9a10b23daf35cc90fa",
    "geometry_msgs/msg/PoseStamped": "10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "geometry_msgs/msg/Vector3": "cc12fe83e4c02719f1ce8070bfd14aecd40f75a96696a67a2a1f37f7dbb0765d",
    "sensor_msgs/msg/Image": "d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CameraInfo": "b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "nav_msgs/msg/Odometry": "3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "tf2_msgs/msg/TFMessage": "e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
}

# type_description_interfaces/msg/FieldType ids: the scalar ids; +48 fixed array, +96 bounded sequence,
# +144 unbounded sequence. A .msg ``byte`` is an IDL octet, a .msg ``char`` an IDL uint8.
_SCALAR = {"int8": 2, "uint8": 3, "char": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8,
           "uint64": 9, "float32": 10, "float64": 11, "bool": 15, "byte": 16, "string": 17, "wstring": 18}
_NESTED = 1
_BOUNDED_STRING = 21
_FIELD = re.compile(r"^(?P<type>[A-Za-z0-9_/]+)(?P<bound><=\d+)?(?P<array>\[(?P<n><=)?(?P<size>\d*)\])?\s+"
                    r"(?P<name>[a-z][a-z0-9_]*)$")


def _resolve(pkg: str, t: str) -> str:
    if "/" not in t:
        return f"{pkg}/msg/{t}"
    p, n = t.split("/")[0], t.split("/")[-1]
    return f"{p}/msg/{n}"


def fields(typename: str) -> list[dict[str, Any]]:
    """The individual type description's fields of one type (defaults excluded, as the hash excludes them)."""
    pkg = typename.split("/")[0]
    out = []
    for line in MSG[typename].splitlines():
        m = _FIELD.match(line.strip())
        assert m, (typename, line)
        t = m["type"]
        nested = "" if t in _SCALAR else _resolve(pkg, t)
        base = _NESTED if nested else (_BOUNDED_STRING if t == "string" and m["bound"] else _SCALAR[t])
        capacity = 0
        if m["array"]:
            if m["n"]:
                base += 96
            elif m["size"]:
                base, capacity = base + 48, int(m["size"])
            else:
                base += 144
        out.append({"name": m["name"], "type": {
            "type_id": base, "capacity": capacity,
            "string_capacity": int(m["bound"][2:]) if m["bound"] else 0, "nested_type_name": nested}})
    return out


def _referenced(typename: str) -> list[str]:
    seen: set[str] = set()
    todo = [f["type"]["nested_type_name"] for f in fields(typename) if f["type"]["nested_type_name"]]
    while todo:
        t = todo.pop()
        if t not in seen:
            seen.add(t)
            todo += [f["type"]["nested_type_name"] for f in fields(t) if f["type"]["nested_type_name"]]
    return sorted(seen)


@lru_cache(maxsize=64)
def rihs01(typename: str) -> str:
    """REP 2011 RIHS01 of a type: SHA-256 of its type description's canonical JSON."""
    desc = {"type_description": {"type_name": typename, "fields": fields(typename)},
            "referenced_type_descriptions": [{"type_name": t, "fields": fields(t)} for t in _referenced(typename)]}
    text = json.dumps(desc, ensure_ascii=True, allow_nan=False, separators=(", ", ": "), sort_keys=False)
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def concatenated(typename: str) -> str:
    """The definition with its dependencies, as ``ros2msg`` schemas and ``mcap-ros2-support`` take it."""
    parts = [MSG[typename]]
    for t in _referenced(typename):
        if t != "builtin_interfaces/msg/Time":  # mcap-ros2-support defines Time itself
            pkg, _, name = t.split("/")
            parts.append("=" * 80 + f"\nMSG: {pkg}/{name}\n" + MSG[t])
    return "\n".join(parts) + "\n"


@lru_cache(maxsize=64)
def _encoder(typename: str) -> Any:
    from mcap_ros2._dynamic import serialize_dynamic  # the serialiser behind mcap_ros2.writer.Writer

    return serialize_dynamic(typename, concatenated(typename))[typename]


def cdr(typename: str, msg: dict[str, Any]) -> bytes:
    """Little-endian CDR (with the encapsulation header) of a message given as nested dicts."""
    return bytes(_encoder(typename)(msg))
