"""The rules an MCAP file must keep for rosbag2 (``ros2 bag info/play``) to read it, checked with readers that
share no code with the export (``mcap``'s reader, ``mcap-ros2-support``'s CDR decoder, PyYAML, and ``rosbags``'
rosbag2 MCAP storage reader).

Where each rule comes from (ros2/rosbag2, ``rosbag2_storage_mcap/src/mcap_storage.cpp`` and
``rosbag2_cpp/src/rosbag2_cpp/readers/sequential_reader.cpp``, branches humble and jazzy; the MCAP ``ros2``
profile in foxglove/mcap ``docs/specification/profiles/ros2.md``):

* profile ``ros2``; every channel ``cdr`` (the reader throws "All topics must have the same serialization format"
  otherwise; the profile says MUST) with a ``ros2msg`` schema named ``pkg/msg/Type`` (the topic's type);
* every channel's metadata has ``offered_qos_profiles``, a YAML list of QoS profiles; Humble's reader decodes the
  policies as integers (``node["history"].as<int>()``), so the integer form is the one every distribution reads;
* a ``topic_type_hash``, when present, is ``RIHS01_`` and 64 hex digits;
* a statistics record (``mcap_reader_->statistics().value()`` gives the counts and the time range);
* a metadata record ``rosbag2`` (found through the metadata index) with ``ROS_DISTRO`` or ``serialized_metadata``;
* every message decodes as its schema says.
"""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

QOS_KEYS = {"history", "depth", "reliability", "durability", "deadline", "lifespan", "liveliness",
            "liveliness_lease_duration", "avoid_ros_namespace_conventions"}
# rmw/types.h enums through Humble (best_available, 4, came in Iron and Humble's reader does not know it)
QOS_RANGES = {"history": range(0, 4), "reliability": range(0, 4), "durability": range(0, 4),
              "liveliness": range(0, 5)}
TYPE_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*/msg/[A-Z][A-Za-z0-9]*")
RIHS01 = re.compile(r"RIHS01_[0-9a-f]{64}")


def qos_problems(text: str) -> list[str]:
    try:
        profiles = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        return [f"offered_qos_profiles is not YAML: {exc}"]
    if not isinstance(profiles, list) or not profiles:
        return [f"offered_qos_profiles is not a non-empty list: {profiles!r}"]
    out = []
    for p in profiles:
        if not isinstance(p, dict) or set(p) != QOS_KEYS:
            out.append(f"a QoS profile has keys {sorted(p) if isinstance(p, dict) else p!r}, not {sorted(QOS_KEYS)}")
            continue
        for key, allowed in QOS_RANGES.items():
            if not isinstance(p[key], int) or p[key] not in allowed:
                out.append(f"QoS {key}={p[key]!r} is not an rmw enum value Humble's reader takes")
        if not isinstance(p["depth"], int) or p["depth"] < 0:
            out.append(f"QoS depth={p['depth']!r}")
        for key in ("deadline", "lifespan", "liveliness_lease_duration"):
            d = p[key]
            if not isinstance(d, dict) or set(d) != {"sec", "nsec"} or not all(isinstance(v, int) for v in d.values()):
                out.append(f"QoS {key}={d!r} is not {{sec, nsec}}")
        if not isinstance(p["avoid_ros_namespace_conventions"], bool):
            out.append("QoS avoid_ros_namespace_conventions is not a bool")
    return out


def ros2_profile_problems(data: bytes) -> list[str]:
    """Every way the file breaks a rule above (empty: rosbag2 can read it)."""
    reader = make_reader(io.BytesIO(data), decoder_factories=[DecoderFactory()])
    out: list[str] = []
    if reader.get_header().profile != "ros2":
        out.append(f"profile {reader.get_header().profile!r}, not 'ros2'")
    summary = reader.get_summary()
    if summary is None:
        return [*out, "no summary section"]
    if summary.statistics is None:
        out.append("no statistics record")
    formats = {ch.message_encoding for ch in summary.channels.values()}
    if len(formats) > 1:
        out.append(f"topics with different serialization formats {sorted(formats)}")
    for ch in summary.channels.values():
        schema = summary.schemas.get(ch.schema_id)
        if ch.message_encoding != "cdr":
            out.append(f"{ch.topic}: message encoding {ch.message_encoding!r}, not 'cdr'")
        if schema is None or schema.encoding != "ros2msg" or not TYPE_NAME.fullmatch(schema.name):
            what = "none" if schema is None else f"{schema.name!r} ({schema.encoding!r})"
            out.append(f"{ch.topic}: schema {what}, not a ros2msg pkg/msg/Type")
        if "offered_qos_profiles" not in ch.metadata:
            out.append(f"{ch.topic}: no offered_qos_profiles")
        else:
            out += [f"{ch.topic}: {p}" for p in qos_problems(ch.metadata["offered_qos_profiles"])]
        h = ch.metadata.get("topic_type_hash")
        if h is not None and not RIHS01.fullmatch(h):
            out.append(f"{ch.topic}: topic_type_hash {h!r}")
    if not any(m.name == "rosbag2" for m in summary.metadata_indexes):
        out.append("no 'rosbag2' metadata record in the metadata index")
    records = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
    if records and not any({"ROS_DISTRO", "serialized_metadata"} & set(m.metadata) for m in records):
        out.append("the 'rosbag2' metadata record has neither ROS_DISTRO nor serialized_metadata")
    if not out:
        for schema, channel, message, _decoded in reader.iter_decoded_messages():
            assert schema is not None and channel is not None and message is not None
    return out


def rosbags_read(path: Path) -> dict[str, Any]:
    """Topics, message counts, QoS and the raw messages as ``rosbags``' rosbag2 MCAP storage reads them (the
    plugin ``rosbags.rosbag2.Reader`` opens each file of a bag with)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    reader = McapReader(path)
    reader.open()
    try:
        conns = {c.id: c for c in reader.connections}
        raw: dict[str, list[tuple[int, bytes]]] = {}
        for conn, t_ns, data in reader.messages(reader.connections):
            raw.setdefault(conn.topic, []).append((t_ns, bytes(data)))
        return {"connections": {c.topic: c for c in conns.values()}, "raw": raw, "count": reader.metadata.message_count}
    finally:
        reader.close()
