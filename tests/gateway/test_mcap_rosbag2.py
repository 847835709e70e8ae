"""The episode MCAP as a ROS 2 bag: an export of an event log checked against rosbag2's rules
(tests/support/ros2_bag.py) and read back by ``rosbags``' rosbag2 MCAP storage reader and by the ``mcap`` reader
with ``mcap-ros2-support``'s CDR decoder, neither of which shares code with the writer's CDR (``rosbags``
serialiser) or its container writer (``mcap``). The recording part (images, maps, the camera mount on
``/tf_static``) is checked on a real fleet episode in tests/fleet/test_recording_fleet.py."""

from __future__ import annotations

import io
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from support import ros2_defs
from support.ros2_bag import qos_problems, ros2_profile_problems, rosbags_read

from eqa import ros
from gateway import mcap_export

T0 = time.time()
EVENTS = [
    {"kind": "episode_start", "episode_id": "ep-1", "t": T0},
    {"kind": "frame", "episode_id": "ep-1", "step": 0, "pose": {"x": 1.0, "y": 2.0, "yaw": 0.3}, "t": T0 + 1},
    {"kind": "decision", "episode_id": "ep-1", "step": 0, "prediction_set": ["A", "B"], "t": T0 + 2},
    {"kind": "goal", "episode_id": "ep-1", "step": 0, "pose": {"x": 2.0, "y": 2.5, "yaw": -1.0}, "done": False,
     "t": T0 + 3},
    {"kind": "frame", "episode_id": "ep-1", "step": 1, "pose": {"x": 2.0, "y": 2.5, "yaw": -1.0}, "t": T0 + 4},
    {"kind": "episode_end", "episode_id": "ep-1", "t": T0 + 5},
]


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "ep.mcap"
    mcap_export.write_mcap(out, EVENTS)
    return out


def test_the_export_keeps_rosbag2s_rules(bag: Path) -> None:
    assert ros2_profile_problems(bag.read_bytes()) == []


def test_the_rule_check_finds_what_rosbag2_refuses() -> None:
    """The check is not vacuous: a JSON channel beside CDR ones, a channel without QoS, a missing distro
    record, and QoS in a form Humble's reader cannot take are each reported."""
    from mcap.writer import Writer

    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="ros2", library="test")
    js = w.register_schema(name="eqa.frame", encoding="jsonschema", data=b"{}")
    w.register_channel(topic="/eqa/frame", message_encoding="json", schema_id=js)
    ps = w.register_schema(name=ros.POSE_STAMPED, encoding="ros2msg", data=ros.msgdef(ros.POSE_STAMPED).encode())
    w.register_channel(topic="/robot/pose", message_encoding="cdr", schema_id=ps)
    w.finish()
    problems = "\n".join(ros2_profile_problems(buf.getvalue()))
    for part in ("different serialization formats", "/eqa/frame: message encoding 'json'",
                 "/eqa/frame: schema 'eqa.frame' ('jsonschema')", "/robot/pose: no offered_qos_profiles",
                 "no 'rosbag2' metadata record"):
        assert part in problems, (part, problems)
    assert qos_problems("- {history: keep_last}") and qos_problems("[")
    jazzy_strings = mcap_export.Qos().yaml().replace("history: 1", "history: keep_last")
    assert any("history" in p for p in qos_problems(jazzy_strings))


def test_channels_qos_and_distro_as_rosbag2_reads_them(bag: Path) -> None:
    reader = make_reader(io.BytesIO(bag.read_bytes()), decoder_factories=[DecoderFactory()])
    summary = reader.get_summary()
    assert summary is not None
    chans = {c.topic: c for c in summary.channels.values()}
    types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert types == {"/eqa/episode_start": ros.STRING, "/eqa/frame": ros.STRING, "/eqa/decision": ros.STRING,
                     "/eqa/goal": ros.STRING, "/eqa/episode_end": ros.STRING, "/robot/pose": ros.POSE_STAMPED,
                     "/robot/path": ros.PATH, "/goal_pose": ros.POSE_STAMPED, "/tf": ros.TF_MESSAGE}
    tf_qos = yaml.safe_load(chans["/tf"].metadata["offered_qos_profiles"])
    assert tf_qos[0]["depth"] == 100 and tf_qos[0]["reliability"] == 1 and tf_qos[0]["durability"] == 2
    for c in chans.values():  # Jazzy's writer puts the type hash beside the QoS (an independent RIHS01 here)
        assert c.metadata["topic_type_hash"] == ros2_defs.rihs01(types[c.topic])
    distro = [m.metadata for m in reader.iter_metadata() if m.name == "rosbag2"]
    assert distro == [{"ROS_DISTRO": "jazzy"}]
    assert summary.statistics is not None and summary.statistics.message_count == 13


def test_rosbags_reads_it_as_a_rosbag2_mcap_and_events_are_strings(bag: Path) -> None:
    got = rosbags_read(bag)
    assert got["count"] == 13
    conns = got["connections"]
    assert {c.ext.serialization_format for c in conns.values()} == {"cdr"}
    assert conns["/tf"].ext.offered_qos_profiles[0].depth == 100
    dec = DecoderFactory()
    reader = make_reader(io.BytesIO(bag.read_bytes()))
    summary = reader.get_summary()
    assert summary is not None
    schema = next(s for s in summary.schemas.values() if s.name == ros.STRING)
    string = dec.decoder_for("cdr", schema)
    assert string is not None
    events = [json.loads(string(data).data) for kind in ("episode_start", "frame", "decision", "goal", "episode_end")
              for _, data in got["raw"]["/eqa/" + kind]]
    assert sorted(events, key=lambda e: e["t"]) == EVENTS  # every event, as stored
    assert [t for t, _ in got["raw"]["/eqa/decision"]] == [round(EVENTS[2]["t"] * 1e9)]


def test_tf_places_the_base_at_each_frame(bag: Path) -> None:
    reader = make_reader(io.BytesIO(bag.read_bytes()), decoder_factories=[DecoderFactory()])
    tfs = [(m.log_time, d) for _, c, m, d in reader.iter_decoded_messages(topics=["/tf"])]
    frames = [e for e in EVENTS if e["kind"] == "frame"]
    assert len(tfs) == len(frames)
    for (t_ns, msg), ev in zip(tfs, frames, strict=True):
        (tr,) = msg.transforms
        assert (tr.header.frame_id, tr.child_frame_id) == ("map", "base_link")
        assert tr.header.stamp.sec * 1_000_000_000 + tr.header.stamp.nanosec == t_ns == round(ev["t"] * 1e9)
        v, q = tr.transform.translation, tr.transform.rotation
        assert (v.x, v.y, v.z) == pytest.approx((ev["pose"]["x"], ev["pose"]["y"], 0.0))
        assert math.cos(ros.yaw_from_quat(q.x, q.y, q.z, q.w) - ev["pose"]["yaw"]) == pytest.approx(1.0)


def test_a_rigid_camera_mount_is_one_static_transform_and_a_moving_one_is_not() -> None:
    from services.ros2_bridge.core import base_to_camera

    mount = base_to_camera(1.5, -30.0)
    assert np.array_equal(mcap_export.camera_mount([mount, mount + 1e-4]), mount)  # rounded event poses
    tilted = base_to_camera(1.5, -20.0)
    assert mcap_export.camera_mount([mount, tilted]) is None
    assert mcap_export.camera_mount([]) is None
