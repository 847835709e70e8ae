"""An episode as a ROS 2 bag in MCAP (``ros2 bag info/play``, Foxglove, Rerun and the ``mcap`` CLI read it).

Built from what the episode left behind, nothing else:

* the **event log** (the store's stream of compact JSON summaries, :mod:`gateway.events`): every event as
  ``std_msgs/String`` (its JSON text) on ``/eqa/<kind>``; the base pose of each frame as
  ``geometry_msgs/PoseStamped`` on ``/robot/pose``, the trajectory so far as ``nav_msgs/Path`` on ``/robot/path``
  and ``map`` -> ``base_link`` on ``/tf``; each goal as ``geometry_msgs/PoseStamped`` on ``/goal_pose`` (Nav2's);
* the merged **Rerun recording** when the episode was recorded: colour and depth frames as
  ``sensor_msgs/Image`` (``rgb8``, ``32FC1`` metres), the pinhole as ``sensor_msgs/CameraInfo``, the camera pose
  as ``geometry_msgs/PoseStamped`` and as the ``base_link`` -> ``camera_optical_frame`` transform (``/tf_static``
  when the camera is rigidly mounted, as on every robot here, else ``/tf``), the planned path as
  ``nav_msgs/Path``, and the 2D maps (occupancy, explored, one per semantic value layer) as
  ``nav_msgs/OccupancyGrid`` placed with the grid of the step's map event.

The file keeps the rules rosbag2's MCAP storage plugin (``rosbag2_storage_mcap``) reads by: profile ``ros2``;
every channel ``cdr`` with a ``ros2msg`` schema (``rosbag2_cpp``'s reader refuses a bag whose topics differ in
serialization format); channel metadata ``offered_qos_profiles`` (a YAML list of QoS profiles in the integer
form rosbag2 wrote through Iron, which Humble's reader requires and Jazzy's still detects) and
``topic_type_hash`` (RIHS01, read from Iron on); a ``rosbag2`` metadata record with ``ROS_DISTRO`` (as Humble and
Iron write it; Jazzy reads it when the record has no ``serialized_metadata``); a statistics record (the reader
takes the counts and time range from it). Messages are CDR of ``rosbags``' ROS 2 Jazzy definitions;
``log_time``, ``publish_time`` and header stamps are the times the data was logged (an event's ``t``, a recording
row's ``log_time``). Frames follow :mod:`eqa.ros`: ``map`` (world, z up), ``base_link``,
``camera_optical_frame``.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from eqa import ros

log = logging.getLogger(__name__)

PROFILE = "ros2"
LIBRARY = "eqa-mcap-export"
ROS_DISTRO = "jazzy"  # the distribution of the message definitions (eqa.ros: rosbags' Jazzy type store)

RGB_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
CAMERA_INFO_TOPIC = "/camera/color/camera_info"
CAMERA_POSE_TOPIC = "/camera/pose"
POSE_TOPIC = "/robot/pose"
TRAJECTORY_TOPIC = "/robot/path"
GOAL_TOPIC = "/goal_pose"
PLAN_TOPIC = "/plan/path"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
MAP_TOPICS = {"map/occupancy": "/map/occupancy", "map/explored": "/map/explored"}
VALUE_PREFIX = "map/value/"
EVENT_PREFIX = "/eqa/"
# Camera mounts this close (metres, rotation-matrix entries) are one rigid mount: the base poses of the events
# carry 4 decimals (eqa.event_log), so mounts derived from them differ by about 1e-4 on a rigid robot.
MOUNT_TOLERANCE = 1e-3


@dataclass(frozen=True)
class Qos:
    """The QoS a topic is offered with (what ``ros2 bag play`` publishes it with)."""

    depth: int = 10
    reliable: bool = True
    transient_local: bool = False

    def yaml(self) -> str:
        """One profile in rosbag2's integer form (rmw enums: history 1 keep_last; reliability 1 reliable, 2 best
        effort; durability 1 transient_local, 2 volatile; liveliness 1 automatic; durations 0 = the default)."""
        zero = "\n    sec: 0\n    nsec: 0"
        return (f"- history: 1\n  depth: {self.depth}\n  reliability: {1 if self.reliable else 2}\n"
                f"  durability: {1 if self.transient_local else 2}\n  deadline:{zero}\n  lifespan:{zero}\n"
                f"  liveliness: 1\n  liveliness_lease_duration:{zero}\n  avoid_ros_namespace_conventions: false")


# What the ROS 2 nodes that publish such topics offer: tf2's broadcasters (depth 100; static: transient local,
# depth 1) and Nav2's map_server (latched maps); everything else the rclcpp default (reliable, volatile, 10).
_LATCHED = Qos(depth=1, transient_local=True)
TOPIC_QOS = {TF_TOPIC: Qos(depth=100), TF_STATIC_TOPIC: _LATCHED, "/map/occupancy": _LATCHED,
             "/map/explored": _LATCHED}


def topic_qos(topic: str) -> Qos:
    return TOPIC_QOS.get(topic) or (_LATCHED if topic.startswith("/map/value/") else Qos())


# Rerun's ChannelDatatype codes and the numpy type of each.
_RR_DTYPES = {6: np.uint8, 7: np.int8, 10: np.uint16, 11: np.int16, 14: np.uint32, 15: np.int32, 33: np.float16,
              34: np.float32, 35: np.float64}
_RR_CHANNELS = {1: 1, 2: 3, 3: 4}  # ColorModel L, RGB, RGBA


class ExportError(RuntimeError):
    pass


@dataclass
class ExportSummary:
    """What was written: messages per topic (the test reads the file back and compares)."""

    path: Path
    messages: Counter[str] = field(default_factory=Counter)
    schemas: dict[str, str] = field(default_factory=dict)  # topic -> schema name

    @property
    def total(self) -> int:
        return sum(self.messages.values())


@dataclass(order=True)
class _Rec:
    log_time: int
    seq: int
    topic: str = field(compare=False)
    data: bytes = field(compare=False)


def _ns(seconds: object) -> int | None:
    return round(float(seconds) * 1e9) if isinstance(seconds, int | float) and math.isfinite(seconds) else None


def _finite(p: object) -> tuple[float, float, float] | None:
    if not isinstance(p, dict):
        return None
    vals = (p.get("x"), p.get("y"), p.get("yaw"))
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in vals):
        return None
    return float(vals[0]), float(vals[1]), float(vals[2])  # type: ignore[arg-type]


def _image_array(row: dict[str, Any], prefix: str) -> np.ndarray | None:
    buf, fmt = row.get(f"{prefix}:buffer"), row.get(f"{prefix}:format")
    if not buf or not fmt:
        return None
    f = fmt[0]
    dtype = _RR_DTYPES.get(f.get("channel_datatype"))
    if dtype is None:
        return None
    ch = _RR_CHANNELS.get(f.get("color_model") or 1, 1)
    arr = np.frombuffer(bytes(buf[0]), dtype=dtype)
    h, w = int(f["height"]), int(f["width"])
    if arr.size != h * w * ch:
        return None
    return arr.reshape((h, w, ch) if ch > 1 else (h, w))


def recording_rows(rrd: Path) -> Iterable[tuple[str, dict[str, Any]]]:
    """(entity path, row) of every non-static row of a Rerun recording; ``log_time`` as int nanoseconds."""
    import pyarrow as pa
    import rerun.chunk as rrc

    for chunk in rrc.RrdReader(rrd).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        if "log_time" not in batch.schema.names:
            continue
        i = batch.schema.get_field_index("log_time")
        batch = batch.set_column(i, "log_time", batch.column(i).cast(pa.int64()))
        for row in batch.to_pylist():
            yield chunk.entity_path.lstrip("/"), row


def _cells_occupancy(img: np.ndarray) -> np.ndarray:
    """The mapper's occupancy image (0 unknown, 128 free, 255 occupied) as OccupancyGrid cells."""
    out = np.full(img.shape, -1, dtype=np.int8)
    out[img >= 64] = 0
    out[img >= 192] = 100
    return out


def _cells_scaled(img: np.ndarray) -> np.ndarray:
    """0..1 (float) or 0..255 (uint8) as 0..100; non-finite as unknown."""
    a = img.astype(np.float64)
    if img.dtype == np.uint8:
        a = a / 255.0
    out = np.full(img.shape, -1, dtype=np.int8)
    ok = np.isfinite(a)
    out[ok] = np.clip(np.round(a[ok] * 100.0), 0, 100).astype(np.int8)
    return out


def camera_mount(mounts: list[np.ndarray]) -> np.ndarray | None:
    """The one ``base_link`` -> camera transform of a rigidly mounted camera, or None when the mount moved
    (then each transform goes on ``/tf`` at its time)."""
    if not mounts:
        return None
    first = mounts[0]
    return first if all(np.allclose(m, first, atol=MOUNT_TOLERANCE, rtol=0.0) for m in mounts) else None


class _Builder:
    def __init__(self) -> None:
        self.recs: list[_Rec] = []
        self.topics: dict[str, str] = {}  # topic -> ROS type

    def ros(self, topic: str, typename: str, msg: object, t_ns: int) -> None:
        self.topics.setdefault(topic, typename)
        self.recs.append(_Rec(t_ns, len(self.recs), topic, ros.serialize(msg, typename)))

    def tf(self, t_ns: int, parent: str, child: str, m: np.ndarray, static: bool = False) -> None:
        msg = ros.tf_message([ros.transform_stamped(t_ns, parent, child, m)])
        self.ros(TF_STATIC_TOPIC if static else TF_TOPIC, ros.TF_MESSAGE, msg, t_ns)


@dataclass
class _Bases:
    """The base pose (x, y, yaw) of each step, from the frame events."""

    by_step: dict[int, tuple[float, float, float]] = field(default_factory=dict)


def _add_events(b: _Builder, events: list[dict[str, Any]]) -> tuple[dict[int, dict[str, Any]], _Bases]:
    """Events onto their channels, poses, transforms and goals as ROS messages; returns the map grid and the base
    pose of each step."""
    grids: dict[int, dict[str, Any]] = {}
    bases = _Bases()
    trail: list[Any] = []
    last_t = 0
    for ev in events:
        kind = ev.get("kind")
        if not isinstance(kind, str) or not kind.replace("_", "").isalnum():
            continue
        t_ns = _ns(ev.get("t")) or last_t
        last_t = t_ns
        b.ros(EVENT_PREFIX + kind, ros.STRING, ros.string(json.dumps(ev, separators=(",", ":"))), t_ns)
        p = _finite(ev.get("pose"))
        if kind == "frame" and p is not None:
            msg = ros.pose_stamped(t_ns, ros.MAP_FRAME, *p[:2], 0.0, p[2])
            b.ros(POSE_TOPIC, ros.POSE_STAMPED, msg, t_ns)
            trail.append(msg)
            b.ros(TRAJECTORY_TOPIC, ros.PATH, ros.path(t_ns, ros.MAP_FRAME, list(trail)), t_ns)
            b.tf(t_ns, ros.MAP_FRAME, ros.BASE_FRAME, ros.planar(*p))
            if isinstance(ev.get("step"), int):
                bases.by_step[ev["step"]] = p
        elif kind == "goal" and p is not None and not ev.get("done"):
            b.ros(GOAL_TOPIC, ros.POSE_STAMPED, ros.pose_stamped(t_ns, ros.MAP_FRAME, *p[:2], 0.0, p[2]), t_ns)
        elif kind == "map_update" and isinstance(ev.get("grid"), dict) and isinstance(ev.get("step"), int):
            grids[ev["step"]] = ev["grid"]
    return grids, bases


def _grid_for(grids: dict[int, dict[str, Any]], step: int, shape: tuple[int, ...]) -> dict[str, Any] | None:
    g = grids.get(step)
    if g is None:  # the closest earlier step's grid when its event was not stored
        earlier = [s for s in grids if s <= step]
        g = grids[max(earlier)] if earlier else None
    if g is None or (int(g.get("rows", -1)), int(g.get("cols", -1))) != tuple(shape[:2]):
        return None
    return g


def _add_recording(b: _Builder, rrd: Path, grids: dict[int, dict[str, Any]], bases: _Bases) -> int:
    """Rows of the recording onto ROS channels, the camera mount onto ``/tf_static`` (or ``/tf``); returns the
    number of maps left out for want of a grid."""
    no_grid = 0
    mounts: list[tuple[int, np.ndarray, np.ndarray]] = []  # (time, camera-to-world, base-to-camera mount)
    for entity, row in recording_rows(rrd):
        t_ns = int(row["log_time"])
        step = int(row.get("step") or 0)
        if entity == "camera/rgb":
            img = _image_array(row, "Image")
            if img is not None and img.ndim == 3 and img.dtype == np.uint8:
                b.ros(RGB_TOPIC, ros.IMAGE, ros.image(t_ns, ros.CAMERA_FRAME, img[..., :3], "rgb8"), t_ns)
        elif entity == "camera/depth":
            img = _image_array(row, "DepthImage")
            if img is not None and img.ndim == 2:
                meter = float((row.get("DepthImage:meter") or [1.0])[0] or 1.0)
                depth = img.astype(np.float32) / np.float32(meter)
                b.ros(DEPTH_TOPIC, ros.IMAGE, ros.image(t_ns, ros.CAMERA_FRAME, depth, "32FC1"), t_ns)
        elif entity == "world/camera":
            if row.get("Pinhole:image_from_camera"):
                k = np.array(row["Pinhole:image_from_camera"][0], dtype=np.float64).reshape(3, 3).T  # column-major
                w, h = row["Pinhole:resolution"][0] if row.get("Pinhole:resolution") else (2 * k[0, 2], 2 * k[1, 2])
                info = ros.camera_info(t_ns, ros.CAMERA_FRAME, k, round(w), round(h))
                b.ros(CAMERA_INFO_TOPIC, ros.CAMERA_INFO, info, t_ns)
            if row.get("Transform3D:translation") and row.get("Transform3D:mat3x3"):
                m = np.eye(4)
                m[:3, :3] = np.array(row["Transform3D:mat3x3"][0], dtype=np.float64).reshape(3, 3).T
                m[:3, 3] = row["Transform3D:translation"][0]
                b.ros(CAMERA_POSE_TOPIC, ros.POSE_STAMPED, ros.pose_stamped_matrix(t_ns, ros.MAP_FRAME, m), t_ns)
                base = bases.by_step.get(step)
                if base is not None:
                    mounts.append((t_ns, m, np.linalg.inv(ros.planar(*base)) @ m))
        elif entity == "world/plan/path" and row.get("LineStrips3D:strips"):
            pts = row["LineStrips3D:strips"][0]
            poses = [ros.pose_stamped(t_ns, ros.MAP_FRAME, float(x), float(y), 0.0) for x, y, _z in pts]
            b.ros(PLAN_TOPIC, ros.PATH, ros.path(t_ns, ros.MAP_FRAME, poses), t_ns)
        elif entity in MAP_TOPICS or entity.startswith(VALUE_PREFIX):
            img = _image_array(row, "Image")
            if img is None or img.ndim != 2:
                continue
            img = np.flipud(img)  # the recording shows y up; grid rows grow with y
            g = _grid_for(grids, step, img.shape)
            if g is None:
                no_grid += 1
                continue
            cells = _cells_occupancy(img) if entity == "map/occupancy" else _cells_scaled(img)
            topic = MAP_TOPICS.get(entity) or "/map/value/" + entity[len(VALUE_PREFIX):]
            grid = ros.occupancy_grid(t_ns, ros.MAP_FRAME, cells, g["resolution"], g["origin_x"], g["origin_y"])
            b.ros(topic, ros.OCCUPANCY_GRID, grid, t_ns)
    rigid = camera_mount([mount for _, _, mount in mounts])
    if rigid is not None:
        # The base at each camera stamp is the camera pose less the mount, so map -> base_link -> camera at the
        # image's time is the recorded camera pose exactly; the static mount is stamped with the first message
        # so a player has it before any image.
        for t_ns, world_T_cam, _ in mounts:
            b.tf(t_ns, ros.MAP_FRAME, ros.BASE_FRAME, world_T_cam @ np.linalg.inv(rigid))
        b.tf(min(r.log_time for r in b.recs), ros.BASE_FRAME, ros.CAMERA_FRAME, rigid, static=True)
    else:
        for t_ns, world_T_cam, mount in mounts:
            b.tf(t_ns, ros.MAP_FRAME, ros.BASE_FRAME, world_T_cam @ np.linalg.inv(mount))
            b.tf(t_ns, ros.BASE_FRAME, ros.CAMERA_FRAME, mount)
    return no_grid


def write_mcap(out: Path, events: list[dict[str, Any]], rrd: Path | None = None) -> ExportSummary:
    """Write the MCAP of one episode from its events (oldest first) and, when given, its merged recording."""
    b = _Builder()
    grids, bases = _add_events(b, events)
    if rrd is not None:
        missing = _add_recording(b, rrd, grids, bases)
        if missing:
            log.warning("%s: %d map image(s) without a grid in the event log were left out", out.name, missing)
    b.recs.sort()
    summary = ExportSummary(out)
    tmp = out.with_name(out.name + ".tmp")
    with tmp.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile=PROFILE, library=LIBRARY)
        schema_ids: dict[str, int] = {}
        channel_ids: dict[str, int] = {}
        for topic, name in b.topics.items():
            if name not in schema_ids:
                schema_ids[name] = w.register_schema(name=name, encoding="ros2msg", data=ros.msgdef(name).encode())
            meta = {"offered_qos_profiles": topic_qos(topic).yaml(), "topic_type_hash": ros.type_hash(name)}
            channel_ids[topic] = w.register_channel(topic=topic, message_encoding="cdr",
                                                    schema_id=schema_ids[name], metadata=meta)
            summary.schemas[topic] = name
        seq: Counter[str] = Counter()
        for r in b.recs:
            w.add_message(channel_ids[r.topic], log_time=r.log_time, data=r.data, publish_time=r.log_time,
                          sequence=seq[r.topic])
            seq[r.topic] += 1
        w.add_metadata("rosbag2", {"ROS_DISTRO": ROS_DISTRO})
        w.finish()
    tmp.replace(out)
    summary.messages = seq
    return summary


def parse_events(rows: Iterable[tuple[str, bytes]]) -> list[dict[str, Any]]:
    """Stored event rows (id, compact JSON) as dicts; an unreadable row is skipped with a warning."""
    out = []
    for entry_id, raw in rows:
        try:
            ev = json.loads(raw)
        except ValueError:
            log.warning("event %s is not JSON; left out of the export", entry_id)
            continue
        if isinstance(ev, dict):
            out.append(ev)
    return out


MCAP_NAME = "episode.mcap"
_export_lock = threading.Lock()  # one export at a time: they share the output file and two cores
MAX_EVENTS = 200_000  # rows read from an episode's event stream at most (the gateway caps what it stores)


def read_events(read: Any, episode_id: str) -> list[dict[str, Any]]:
    """Every stored event of an episode, paging with ``read(episode_id, after, count)``."""
    rows: list[tuple[str, bytes]] = []
    cursor = "0-0"
    while len(rows) < MAX_EVENTS:
        page = read(episode_id, cursor, 1000)
        if not page:
            break
        rows += page
        cursor = page[-1][0]
    return parse_events(rows)


def export_episode(settings: Any, episode_id: str, events: list[dict[str, Any]], out: Path | None = None
                   ) -> ExportSummary:
    """The MCAP of an episode: its events plus its merged recording when one was made. Written to ``out``, by
    default ``{recordings}/{episode_id}/episode.mcap`` (or ``{data_dir}/exports/`` when not recorded)."""
    from eqa.recording import recording_dir
    from gateway import recordings

    rrd: Path | None = None
    if recordings.parts(settings, episode_id):
        rrd = recordings.merge(settings, episode_id)
    if out is None:
        d = recording_dir(settings, episode_id) if rrd is not None else settings.data_dir / "exports" / episode_id
        d.mkdir(parents=True, exist_ok=True)
        out = d / MCAP_NAME
    if not events and rrd is None:
        raise FileNotFoundError(f"episode {episode_id} has neither stored events nor a recording")
    with _export_lock:
        return write_mcap(out, events, rrd)
