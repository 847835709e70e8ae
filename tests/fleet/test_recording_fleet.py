"""A demo episode on the real fleet (sim, mapper, vlm_scorer, planner, stopper as processes) through the
gateway: the merged .rrd is served over HTTP, verifies with the rerun tool and holds every entity the design
lists; its MCAP, read back with an independent reader (the ``mcap`` reader and ``mcap-ros2-support``'s CDR
decoder; the writer serialises with ``rosbags``), has the channels, message counts, timestamps and content of
what the episode published (its SSE events and the rows of its Rerun recording), keeps rosbag2's rules
(tests/support/ros2_bag.py) and reads back through ``rosbags``' rosbag2 MCAP storage reader, places the camera
with ``/tf`` and ``/tf_static``, and ``eqa export --mcap`` writes the same. One fleet and one episode (160x120
images, 4 steps) for the module.
"""

from __future__ import annotations

import io
import json
import math
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from support.fleet import GatewayThread, fleet_settings, sse_events, wait_for
from support.ros2_bag import ros2_profile_problems, rosbags_read

from eqa import ros
from eqa.launcher import Fleet
from eqa.recording import ENTITIES, REQUIRED_ENTITIES
from eqa.ros import yaw_from_quat
from eqa_app.cli import main
from gateway import mcap_export, recordings

SCENE = "gen-00001"
TASK_SCENE = "gen-115001"  # a tuning-seed task house with potted plants
ROS_TOPICS = {
    "/camera/color/image_raw": "sensor_msgs/msg/Image",
    "/camera/depth/image_raw": "sensor_msgs/msg/Image",
    "/camera/color/camera_info": "sensor_msgs/msg/CameraInfo",
    "/camera/pose": "geometry_msgs/msg/PoseStamped",
    "/robot/pose": "geometry_msgs/msg/PoseStamped",
    "/robot/path": "nav_msgs/msg/Path",
    "/goal_pose": "geometry_msgs/msg/PoseStamped",
    "/plan/path": "nav_msgs/msg/Path",
    "/map/occupancy": "nav_msgs/msg/OccupancyGrid",
    "/map/explored": "nav_msgs/msg/OccupancyGrid",
}


@dataclass
class Episode:
    episode_id: str
    status: dict[str, Any]
    events: list[tuple[str, dict[str, Any]]]
    rrd: httpx.Response
    missing: httpx.Response
    out: Path
    mcap: httpx.Response
    settings: Any
    task: tuple[dict[str, Any], Path] | None = None  # a task episode on the same fleet: final status, merged .rrd


@pytest.fixture(scope="module")
def episode(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[Episode]:
    from services.sim.library import load_or_generate

    s = fleet_settings(tmp_path_factory.mktemp("rec-fleet"), redis_url, record=True, episode_timeout_s=120.0)
    load_or_generate(SCENE, s.scenes_path)
    load_or_generate(TASK_SCENE, s.scenes_path)
    with (
        Fleet(s, scorers=1) as fleet,
        GatewayThread(fleet.client_settings()) as gw,
        httpx.Client(base_url=gw.url, timeout=60) as c,
    ):
        assert wait_for(lambda: c.get("/v1/ready").status_code == 200, 60), c.get("/v1/ready").text
        r = c.post(
            "/v1/questions",
            json={
                "question": "Which room is the sofa in?",
                "choices": ["kitchen", "living room", "bedroom", "bath"],
                "scene": SCENE,
                "max_steps": 4,
                "seed": 1,
                "stop_rule": "max_steps",
            },
        )
        assert r.status_code == 202, r.text
        eid = r.json()["episode_id"]
        events = list(sse_events(c, f"/v1/episodes/{eid}/events", timeout=300))
        st = c.get(f"/v1/episodes/{eid}").json()
        time.sleep(1.0)  # each service closes (flushes) its recorder when it sees the episode end
        rrd = c.get(f"/v1/episodes/{eid}/recording")
        missing = c.get("/v1/episodes/ep-none/recording")
        t = c.post("/v1/tasks", json={"instruction": "Find a potted plant", "scene": TASK_SCENE, "max_steps": 6,
                                      "seed": 1})
        assert t.status_code == 202, t.text
        tid = t.json()["episode_id"]
        list(sse_events(c, f"/v1/episodes/{tid}/events", timeout=300))
        tst = c.get(f"/v1/episodes/{tid}").json()
        time.sleep(1.0)
        trrd = c.get(f"/v1/episodes/{tid}/recording")
        assert trrd.status_code == 200, trrd.text
        mcap = c.get(f"/v1/episodes/{eid}/recording.mcap")
    out = s.data_dir / f"{eid}.rrd"
    out.write_bytes(rrd.content)
    tout = s.data_dir / f"{tid}.rrd"
    tout.write_bytes(trrd.content)
    yield Episode(eid, st, events, rrd, missing, out, mcap, s, (tst, tout))


def test_recording_served_over_http(episode: Episode) -> None:
    st = episode.status
    assert episode.events[-1][1]["kind"] == "episode_end"
    assert st["state"] == "stopped" and st["steps"] == 4, st
    assert st["recording"] == f"/v1/episodes/{episode.episode_id}/recording"
    assert episode.rrd.status_code == 200 and episode.rrd.headers["content-type"] == "application/octet-stream"
    ok, msg = recordings.verify(episode.out)
    assert ok, msg
    assert episode.missing.status_code == 404


def test_demo_episode_recording_has_every_entity(episode: Episode) -> None:
    paths = recordings.entity_paths(episode.out)
    missing = [
        k
        for k in REQUIRED_ENTITIES
        if not any(p == "/" + ENTITIES[k] or p.startswith("/" + ENTITIES[k] + "/") for p in paths)
    ]
    assert not missing, f"missing entities {missing}; recording has {sorted(paths)}"


def test_task_episode_recording_shows_phase_and_outcome(episode: Episode) -> None:
    """A task's recording holds its phase per step and its outcome (eqa.recording ENTITIES task_*)."""
    assert episode.task is not None
    st, path = episode.task
    assert st["state"] in ("stopped", "failed") and st["outcome"] is not None, st
    assert st["outcome"]["success"] == bool(st["metrics"].get("SR")), st
    assert "answering" not in (st["stop_reason"] or "")
    paths = recordings.entity_paths(path)
    for k in ("task_phase", "task_outcome"):
        assert "/" + ENTITIES[k] in paths, f"{ENTITIES[k]} missing; recording has {sorted(paths)}"
    assert any(p.startswith("/" + ENTITIES["task_flags"] + "/") for p in paths), sorted(paths)


def _read(data: bytes) -> tuple[Any, dict[str, list[tuple[Any, Any, Any]]]]:
    reader = make_reader(io.BytesIO(data), decoder_factories=[DecoderFactory()])
    summary = reader.get_summary()
    by_topic: dict[str, list[tuple[Any, Any, Any]]] = defaultdict(list)
    for schema, channel, message in reader.iter_messages(log_time_order=True):
        by_topic[channel.topic].append((schema, channel, message))
    return summary, by_topic


def _decode(schema: Any, channel: Any, message: Any) -> Any:
    msg = DecoderFactory().decoder_for(channel.message_encoding, schema)(message.data)
    return json.loads(msg.data) if channel.topic.startswith("/eqa/") else msg


@pytest.fixture(scope="module")
def mcap_read(episode: Episode) -> tuple[Any, dict[str, list[tuple[Any, Any, Any]]]]:
    assert episode.mcap.status_code == 200, episode.mcap.text
    return _read(episode.mcap.content)


def test_channels_and_counts_match_what_the_episode_published(episode: Episode, mcap_read: Any) -> None:
    summary, by_topic = mcap_read
    events = [e for _, e in episode.events]
    kinds = Counter(e["kind"] for e in events)
    topics = {ch.topic: ch for ch in summary.channels.values()}
    schemas = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
    for topic, name in ROS_TOPICS.items():
        assert topic in topics, f"{topic} missing; channels {sorted(topics)}"
        assert schemas[topic].name == name and schemas[topic].encoding == "ros2msg"
        assert topics[topic].message_encoding == "cdr"
    assert any(t.startswith("/map/value/") for t in topics), sorted(topics)
    for kind, n in kinds.items():
        topic = "/eqa/" + kind
        assert schemas[topic].name == ros.STRING and schemas[topic].encoding == "ros2msg"
        assert topics[topic].message_encoding == "cdr"
        assert len(by_topic[topic]) == n, (topic, len(by_topic[topic]), n)
    counts = summary.statistics.channel_message_counts
    for ch_id, ch in summary.channels.items():
        assert counts[ch_id] == len(by_topic[ch.topic]), ch.topic
    frames = kinds["frame"]
    assert frames == 4, kinds
    for topic in ("/robot/pose", "/robot/path", "/camera/color/image_raw", "/camera/depth/image_raw",
                  "/camera/color/camera_info", "/camera/pose"):
        assert len(by_topic[topic]) == frames, (topic, len(by_topic[topic]))
    maps = kinds["map_update"]
    assert len(by_topic["/map/occupancy"]) == len(by_topic["/map/explored"]) == maps
    goals = [e for e in events if e["kind"] == "goal" and not e["done"] and e["pose"]]
    assert len(by_topic["/goal_pose"]) == len(goals)
    assert summary.statistics.message_count == sum(len(v) for v in by_topic.values())


def test_timestamps_follow_the_event_log(episode: Episode, mcap_read: Any) -> None:
    summary, by_topic = mcap_read
    events = [e for _, e in episode.events]
    for kind in {e["kind"] for e in events}:
        got = [m.log_time for _, _, m in by_topic["/eqa/" + kind]]
        assert got == [round(e["t"] * 1e9) for e in events if e["kind"] == kind], kind
    t0, t1 = round(events[0]["t"] * 1e9), round(events[-1]["t"] * 1e9)
    assert summary.statistics.message_start_time >= t0 - 5_000_000_000
    assert summary.statistics.message_end_time <= t1 + 5_000_000_000  # services log their last rows at the end
    for topic in ROS_TOPICS:
        last = -1
        for s, ch, m in by_topic[topic]:
            msg = _decode(s, ch, m)
            st = msg.header.stamp
            assert st.sec * 1_000_000_000 + st.nanosec == m.log_time == m.publish_time, topic
            assert m.log_time >= last
            last = m.log_time


def test_content_matches_the_episode(episode: Episode, mcap_read: Any) -> None:
    _, by_topic = mcap_read
    events = [e for _, e in episode.events]
    frames = [e for e in events if e["kind"] == "frame"]
    for ev, (s, ch, m) in zip(frames, by_topic["/robot/pose"], strict=True):
        p = _decode(s, ch, m).pose
        assert (p.position.x, p.position.y) == pytest.approx((ev["pose"]["x"], ev["pose"]["y"]), abs=1e-9)
        o = p.orientation
        assert math.cos(yaw_from_quat(o.x, o.y, o.z, o.w) - ev["pose"]["yaw"]) == pytest.approx(1.0, abs=1e-9)
    path = _decode(*by_topic["/robot/path"][-1]).poses
    assert [c for q in path for c in (q.pose.position.x, q.pose.position.y)] == pytest.approx(
        [c for f in frames for c in (f["pose"]["x"], f["pose"]["y"])])
    rows = [r for e, r in mcap_export.recording_rows(episode.out) if e == "camera/rgb"]
    for ev, row, (s, ch, m) in zip(frames, rows, by_topic["/camera/color/image_raw"], strict=True):
        img = _decode(s, ch, m)
        assert [img.height, img.width] == ev["image"] and img.encoding == "rgb8" and img.step == img.width * 3
        assert bytes(img.data) == bytes(row["Image:buffer"][0])  # the very pixels the sim logged
    for s, ch, m in by_topic["/camera/depth/image_raw"]:
        d = _decode(s, ch, m)
        depth = np.frombuffer(bytes(d.data), dtype="<f4").reshape(d.height, d.width)
        assert d.encoding == "32FC1" and np.isfinite(depth).all() and depth.max() > 0.1
    info = _decode(*by_topic["/camera/color/camera_info"][0])
    k = np.array(info.k).reshape(3, 3)
    assert (info.width, info.height) == (160, 120) and k[2, 2] == 1.0 and k[0, 2] == pytest.approx(80, abs=1)
    grids = [e["grid"] for e in events if e["kind"] == "map_update"]
    for g, (s, ch, m) in zip(grids, by_topic["/map/occupancy"], strict=True):
        occ = _decode(s, ch, m)
        assert (occ.info.width, occ.info.height) == (g["cols"], g["rows"])
        assert occ.info.resolution == pytest.approx(g["resolution"])
        assert (occ.info.origin.position.x, occ.info.origin.position.y) == pytest.approx(
            (g["origin_x"], g["origin_y"]))
        cells = np.array(occ.data, dtype=np.int8)
        assert set(np.unique(cells)) <= {-1, 0, 100} and (cells == 0).any() and (cells == -1).any()
    decisions = [e for e in events if e["kind"] == "decision"]
    assert [_decode(*x) for x in by_topic["/eqa/decision"]] == decisions


def test_cli_export_writes_the_same_channels(episode: Episode, mcap_read: Any, tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
                                             ) -> None:
    s = episode.settings
    monkeypatch.setenv("EQA_DATA_DIR", str(s.data_dir))
    monkeypatch.setenv("EQA_REDIS_URL", s.redis_url)
    out = tmp_path / "ep.mcap"
    assert main(["export", episode.episode_id, "--mcap", "-o", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    _, by_topic = _read(out.read_bytes())
    _, served = mcap_read
    assert {t: len(v) for t, v in by_topic.items()} == {t: len(v) for t, v in served.items()}
    assert main(["export", "ep-nope", "--mcap", "-o", str(tmp_path / "x.mcap")]) == 2
    assert "no episode 'ep-nope'" in capsys.readouterr().err


def test_rerun_opens_the_mcap(episode: Episode, tmp_path: Path) -> None:
    import rerun.chunk as rrc

    path = tmp_path / "ep.mcap"
    path.write_bytes(episode.mcap.content)
    entities = {chunk.entity_path for chunk in rrc.McapReader(path).stream()}
    missing = [t for t in ROS_TOPICS if t not in entities]
    assert not missing, f"rerun's MCAP loader did not show {missing}; it has {sorted(entities)}"


def test_the_bag_keeps_rosbag2s_rules_and_rosbags_reads_it(episode: Episode, mcap_read: Any, tmp_path: Path) -> None:
    assert ros2_profile_problems(episode.mcap.content) == []
    path = tmp_path / "ep.mcap"
    path.write_bytes(episode.mcap.content)
    got = rosbags_read(path)
    summary, by_topic = mcap_read
    assert got["count"] == summary.statistics.message_count
    assert {t: len(v) for t, v in got["raw"].items()} == {t: len(v) for t, v in by_topic.items()}
    assert {t: c.msgtype for t, c in got["connections"].items()} == {
        ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}


def test_tf_places_the_camera_where_the_recording_has_it(episode: Episode, mcap_read: Any) -> None:
    """map -> base_link (/tf) composed with base_link -> camera_optical_frame (/tf_static) is the camera pose of
    each frame, and the images and camera_info are in that frame: what Foxglove's 3D panel needs."""
    _, by_topic = mcap_read
    (static,) = [_decode(*x) for x in by_topic["/tf_static"]]
    (mount_tf,) = static.transforms
    assert (mount_tf.header.frame_id, mount_tf.child_frame_id) == ("base_link", "camera_optical_frame")
    t_ns = by_topic["/tf_static"][0][2].log_time
    assert t_ns == min(m.log_time for v in by_topic.values() for _, _, m in v)

    def matrix(tr: Any) -> np.ndarray:
        m = np.eye(4)
        q, v = tr.transform.rotation, tr.transform.translation
        m[:3, :3] = ros.matrix_from_quat(q.x, q.y, q.z, q.w)
        m[:3, 3] = (v.x, v.y, v.z)
        return m

    base_at = {}
    for s, ch, m in by_topic["/tf"]:
        (tr,) = _decode(s, ch, m).transforms
        assert (tr.header.frame_id, tr.child_frame_id) == ("map", "base_link")
        base_at[m.log_time] = matrix(tr)
    cams = [(m.log_time, _decode(s, ch, m).pose) for s, ch, m in by_topic["/camera/pose"]]
    assert cams
    for t, pose in cams:
        want = np.eye(4)
        o, p = pose.orientation, pose.position
        want[:3, :3] = ros.matrix_from_quat(o.x, o.y, o.z, o.w)
        want[:3, 3] = (p.x, p.y, p.z)
        assert np.allclose(base_at[t] @ matrix(mount_tf), want, atol=1e-6), t
    for topic in ("/camera/color/image_raw", "/camera/depth/image_raw", "/camera/color/camera_info"):
        assert {_decode(*x).header.frame_id for x in by_topic[topic]} == {"camera_optical_frame"}, topic
