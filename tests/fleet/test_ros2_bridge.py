"""The ROS 2 bridge (services/ros2_bridge): its pure core on ROS messages, its wire format against fixtures made
without its libraries, and the fleet (mapper, vlm_scorer, planner, stopper and the bridge as real processes, the
gateway in a thread) answering questions with four test robots on rmw_zenoh in the sim's place
(tests/support/ros2_robot.py, independent of the bridge's code and libraries): a Jazzy and a Humble robot that
drive to their goals, a Humble one that never arrives and a Jazzy one that sends garbage.

What of the wire format this covers (ROS 2 itself cannot be installed here): type hashes against a separate RIHS01
implementation and against hashes ROS 2 generated (tests/support/ros2_defs.py); CDR of every type the bridge
reads or writes against ``mcap-ros2-support``'s serialiser; topic keys in each distribution's hash form
(``pamoja-ros2`` for RIHS01 keys, ``TypeHashNotSupported`` on Humble); the publication attachment decoded by
``zenoh.ext``; per-robot sequence numbers from 1 and GIDs as rmw_zenoh derives them from the liveliness token;
the bridge's liveliness tokens. Not covered: QoS semantics and transient-local durability, services/actions,
interoperation with rmw_zenoh_cpp itself, TF input in the fleet (unit-tested).
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest
import xxhash
from support import ros2_defs
from support.fleet import GatewayThread, fleet_settings, sse_events, wait_for
from support.ros2_robot import TestRobot, decode_attachment, decode_pose_stamped
from support.ros2_robot import key as robot_key

from eqa import ros
from eqa.bus import Bus
from eqa.launcher import Fleet
from eqa.messages import Pose2D
from services.ros2_bridge import core

SCENE = "gen-00001"
NOW = time.time_ns()


def _image(enc: str, h: int, w: int, data: bytes, step: int) -> Any:
    return ros.T[ros.IMAGE](header=ros.header(NOW, "cam"), height=h, width=w, encoding=enc, is_bigendian=0,
                            step=step, data=np.frombuffer(data, np.uint8))


def _roundtrip(msg: Any, typename: str) -> Any:
    return ros.deserialize(ros.serialize(msg, typename), typename)


# ---- the pure core --------------------------------------------------------------------------------------------
def test_images_convert_and_bad_ones_are_refused_with_a_reason() -> None:
    rgb = np.random.default_rng(0).integers(0, 255, (4, 6, 3), dtype=np.uint8)
    got = core.image_array(_roundtrip(ros.image(NOW, "c", rgb, "rgb8"), ros.IMAGE), "rgb", 100, 0.001)
    assert np.array_equal(got, rgb)
    bgr = _image("bgr8", 4, 6, rgb[..., ::-1].tobytes(), 18)
    assert np.array_equal(core.image_array(bgr, "rgb", 100, 0.001), rgb)
    mm = np.array([[0, 1500], [65535, 250]], dtype="<u2")
    d = core.image_array(_image("16UC1", 2, 2, mm.tobytes(), 4), "depth", 100, 0.001)
    assert d.dtype == np.float32 and np.allclose(d, [[0.0, 1.5], [65.535, 0.25]])
    f = np.array([[1.0, np.nan], [np.inf, -2.0]], dtype="<f4")
    assert core.image_array(_image("32FC1", 2, 2, f.tobytes(), 8), "depth", 100, 1.0).tolist() == [[1, 0], [0, 0]]
    padded = _image("rgb8", 1, 2, bytes([1, 2, 3, 4, 5, 6, 0, 0]), 8)  # row padding is dropped
    assert core.image_array(padded, "rgb", 100, 1.0).tolist() == [[[1, 2, 3], [4, 5, 6]]]
    cases = [
        (_image("yuv422", 4, 6, bytes(48), 12), "rgb", "encoding"),
        (_image("rgb8", 4, 6, bytes(10), 18), "rgb", "size"),
        (_image("rgb8", 0, 6, b"", 18), "rgb", "size"),
        (_image("16UC1", 2, 2, bytes(8), 4), "rgb", "encoding"),
        (_image("rgb8", 20, 20, bytes(1200), 60), "rgb", "huge"),
    ]
    for msg, kind, code in cases:
        with pytest.raises(core.RosInputError) as e:
            core.image_array(msg, kind, 100, 0.001)
        assert e.value.code == code, (msg.encoding, str(e.value))
    with pytest.raises(core.RosInputError, match="register depth") as e:
        core.check_frame(np.zeros((4, 6, 3), np.uint8), np.zeros((2, 6), np.float32), (np.eye(3), 6, 4))
    assert e.value.code == "mismatch"


def test_poses_stamps_and_camera_info() -> None:
    odom = ros.T[ros.ODOMETRY](
        header=ros.header(NOW, "map"), child_frame_id="base_link",
        pose=ros.T["geometry_msgs/msg/PoseWithCovariance"](pose=ros.pose(1.0, 2.0, 0.0, ros.quat_from_yaw(0.7)),
                                                           covariance=np.zeros(36)),
        twist=ros.T["geometry_msgs/msg/TwistWithCovariance"](twist=ros.T["geometry_msgs/msg/Twist"](
            linear=ros.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=ros.T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36)))
    p, st = core.odometry_pose(_roundtrip(odom, ros.ODOMETRY))
    assert (p.x, p.y, st) == (1.0, 2.0, NOW) and p.yaw == pytest.approx(0.7)
    odom.pose.pose.position.x = float("nan")
    with pytest.raises(core.RosInputError) as e:
        core.odometry_pose(odom)
    assert e.value.code == "nan_pose"
    tfm = ros.T["geometry_msgs/msg/TransformStamped"](
        header=ros.header(NOW, "map"), child_frame_id="base_link",
        transform=ros.T["geometry_msgs/msg/Transform"](
            translation=ros.T["geometry_msgs/msg/Vector3"](x=3.0, y=4.0, z=0.0),
            rotation=ros.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
    tf = _roundtrip(ros.T[ros.TF_MESSAGE](transforms=[tfm]), ros.TF_MESSAGE)
    assert core.tf_pose(tf, "map", "base_link")[0] == Pose2D(x=3.0, y=4.0, yaw=0.0)  # type: ignore[index]
    assert core.tf_pose(tf, "map", "other") is None
    for stamp in (NOW - 10**10, 0, NOW + 10**11):
        with pytest.raises(core.RosInputError) as e:
            core.check_stamp(stamp, NOW, 2.0, "rgb")
        assert e.value.code == "stale"
    k = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    K, w, h = core.intrinsics(_roundtrip(ros.camera_info(NOW, "c", k, 160, 120), ros.CAMERA_INFO))
    assert np.array_equal(K, k) and (w, h) == (160, 120)
    bad = ros.camera_info(NOW, "c", k * 0, 160, 120)
    with pytest.raises(core.RosInputError):
        core.intrinsics(bad)


def test_arrival_needs_tolerance_and_settling_and_times_out() -> None:
    goal = Pose2D(x=1.0, y=0.0, yaw=0.0)
    a = core.Arrival(goal, sent_at=0.0, tol_m=0.2, tol_yaw=0.3, settle_s=0.5, timeout_s=3.0)
    assert a.update(Pose2D(x=0.0, y=0.0), 0.5) == "moving"
    assert a.update(Pose2D(x=0.9, y=0.0), 1.0) == "moving"  # inside, not settled yet
    assert a.update(Pose2D(x=0.95, y=0.0, yaw=1.0), 1.4) == "moving"  # heading off: out again
    assert a.update(Pose2D(x=0.95, y=0.0), 1.5) == "moving"
    assert a.update(Pose2D(x=0.96, y=0.0), 2.1) == "arrived"
    b = core.Arrival(goal, sent_at=0.0, tol_m=0.2, tol_yaw=0.3, settle_s=0.5, timeout_s=3.0)
    assert b.update(Pose2D(x=0.0, y=0.0), 3.1) == "timeout"


def test_names_keys_tokens_and_goal_bytes() -> None:
    fqn = core.fully_qualified("/robot0", "camera/color/image_raw")
    assert fqn == "/robot0/camera/color/image_raw" and core.fully_qualified("/r", "/abs/t") == "/abs/t"
    h = ros.type_hash(ros.IMAGE)
    assert core.topic_key(0, fqn, ros.IMAGE, h) == f"0/robot0/camera/color/image_raw/sensor_msgs::msg::dds_::Image_/{h}"
    import pamoja.ros2 as pr

    assert pr.entity_key(0, fqn, ros.IMAGE, h) == core.topic_key(0, fqn, ros.IMAGE, h)  # the third-party assembler
    tok = core.endpoint_token(3, "abc", 0, 2, "MP", "/robot0", "eqa_bridge_robot0", "/robot0/goal_pose",
                              ros.POSE_STAMPED)
    parts = tok.split("/")
    assert parts[:9] == ["@ros2_lv", "3", "abc", "0", "2", "MP", "%", "%robot0", "eqa_bridge_robot0"]
    assert parts[9:12] == ["%robot0%goal_pose", "geometry_msgs::msg::dds_::PoseStamped_",
                           ros.type_hash(ros.POSE_STAMPED)]
    assert core.node_token(0, "abc", 1, "", "n").endswith("/1/1/NN/%/%/n")
    att = core.attachment(7, 123, bytes(range(16)))
    assert decode_attachment(att) == (7, 123, bytes(range(16)))  # zenoh.ext's deserialiser
    data = core.goal_pose_stamped(Pose2D(x=1.5, y=-2.0, yaw=math.pi / 2), NOW, "map")
    stamp, frame, (x, y, z, _qx, _qy, qz, qw) = decode_pose_stamped(data)  # the robot's own decoder
    assert (stamp, frame, x, y, z) == (NOW, "map", 1.5, -2.0, 0.0)
    assert (qz, qw) == pytest.approx((math.sin(math.pi / 4), math.cos(math.pi / 4)))
    with pytest.raises(ValueError):
        core.goal_pose_stamped(Pose2D(x=float("nan"), y=0.0), NOW, "map")


# ---- the wire format against fixtures made without the bridge's libraries -----------------------------------------
def test_type_hashes_match_an_independent_rihs01_and_the_ones_ros2_generated() -> None:
    for typename in ros2_defs.MSG:
        assert ros.type_hash(typename) == ros2_defs.rihs01(typename), typename
        for distro in ("kilted", "rolling"):
            assert core.key_hash(distro, typename) == ros2_defs.rihs01(typename), (distro, typename)
    for typename, digest in ros2_defs.PUBLISHED.items():
        assert ros2_defs.rihs01(typename) == "RIHS01_" + digest, typename
    assert core.key_hash("humble", ros.POSE_STAMPED) == "TypeHashNotSupported"


def _msgs() -> dict[str, tuple[Any, dict[str, Any]]]:
    """One message of each type the bridge or the MCAP export speaks: the bridge's object, the same as dicts."""
    hdr = {"stamp": {"sec": NOW // 10**9, "nanosec": NOW % 10**9}, "frame_id": "map"}
    pose = {"position": {"x": 1.5, "y": -2.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.6, "w": 0.8}}
    k = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
    tf = ros.tf_message([ros.transform_stamped(NOW, "map", "base_link", ros.planar(1.0, 2.0, 0.3))])
    q = ros.quat_from_yaw(0.3)
    pixels = bytes(range(24))
    cells = np.array([[-1, 0], [100, 50]], dtype=np.int8)
    return {
        ros.POSE_STAMPED: (ros.T[ros.POSE_STAMPED](header=ros.header(NOW, "map"), pose=ros.pose(
            1.5, -2.0, 0.0, (0.0, 0.0, 0.6, 0.8))), {"header": hdr, "pose": pose}),
        ros.IMAGE: (_image("bgr8", 2, 4, pixels, 12), {
            "header": {**hdr, "frame_id": "cam"}, "height": 2, "width": 4, "encoding": "bgr8", "is_bigendian": 0,
            "step": 12, "data": pixels}),
        ros.CAMERA_INFO: (ros.camera_info(NOW, "cam", k, 160, 120), {
            "header": {**hdr, "frame_id": "cam"}, "height": 120, "width": 160, "distortion_model": "plumb_bob",
            "d": [0.0] * 5, "k": k.reshape(-1).tolist(), "r": np.eye(3).reshape(-1).tolist(),
            "p": np.hstack([k, np.zeros((3, 1))]).reshape(-1).tolist(), "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}),
        ros.TF_MESSAGE: (tf, {"transforms": [{
            "header": hdr, "child_frame_id": "base_link", "transform": {
                "translation": {"x": 1.0, "y": 2.0, "z": 0.0},
                "rotation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]}}}]}),
        ros.STRING: (ros.string('{"kind":"frame"}'), {"data": '{"kind":"frame"}'}),
        ros.PATH: (ros.path(NOW, "map", [ros.pose_stamped(NOW, "map", 1.5, -2.0)]), {
            "header": hdr, "poses": [{"header": hdr, "pose": {
                "position": {"x": 1.5, "y": -2.0, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}]}),
        ros.OCCUPANCY_GRID: (ros.occupancy_grid(NOW, "map", cells, 0.1, -1.0, -2.0), {
            "header": hdr, "info": {"map_load_time": hdr["stamp"], "resolution": 0.1, "width": 2, "height": 2,
                                    "origin": {"position": {"x": -1.0, "y": -2.0, "z": 0.0},
                                               "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}},
            "data": cells.reshape(-1).tolist()}),
    }


def test_cdr_bytes_match_an_independent_serialiser() -> None:
    """The bridge's CDR (rosbags) byte for byte against mcap-ros2-support's serialiser of the same message, and
    the bridge decodes what the other one wrote (what the test robot sends)."""
    for typename, (msg, as_dict) in _msgs().items():
        theirs = ros2_defs.cdr(typename, as_dict)
        assert ros.serialize(msg, typename) == theirs, typename
        assert ros.serialize(ros.deserialize(theirs, typename), typename) == theirs, typename
    goal = core.goal_pose_stamped(Pose2D(x=1.5, y=-2.0, yaw=2 * math.atan2(0.6, 0.8)), NOW, "map")
    _, as_dict = _msgs()[ros.POSE_STAMPED]
    want = ros2_defs.cdr(ros.POSE_STAMPED, as_dict)
    assert goal[:-56] == want[:-56]  # header and position exact; the quaternion from yaw to rounding
    assert struct.unpack("<7d", goal[-56:]) == pytest.approx(struct.unpack("<7d", want[-56:]), abs=1e-12)


def test_keys_carry_each_distributions_hash_form(tmp_path: Any) -> None:
    fqn = "/robot3/goal_pose"
    humble = core.topic_key(0, fqn, ros.POSE_STAMPED, core.key_hash("humble", ros.POSE_STAMPED))
    assert humble == "0/robot3/goal_pose/geometry_msgs::msg::dds_::PoseStamped_/TypeHashNotSupported"
    assert humble == robot_key(0, fqn, ros.POSE_STAMPED, "humble")
    for distro in ("jazzy", "kilted", "rolling"):
        k = core.topic_key(0, fqn, ros.POSE_STAMPED, core.key_hash(distro, ros.POSE_STAMPED))
        assert k == robot_key(0, fqn, ros.POSE_STAMPED, distro) != humble  # pamoja with the independent hash
    tok = core.endpoint_token(0, "abc", 1, 5, "MP", "/robot3", "eqa_bridge_robot3", fqn, ros.POSE_STAMPED, "humble")
    assert tok.split("/")[11] == "TypeHashNotSupported"
    s = fleet_settings(tmp_path, None, robots=["a", "b"], ros2_robots=["a", "b"], ros2_distros=["b=humble"])
    assert (s.ros2_distro_of("a"), s.ros2_distro_of("b")) == ("jazzy", "humble")
    with pytest.raises(ValueError, match="robot=distro"):
        fleet_settings(tmp_path, None, ros2_distros=["b=iron"])


def _xxh3_gid(token: str) -> bytes:
    """rmw_zenoh's GID of an entity (liveliness_utils.cpp): XXH3-128 of the token, low64 then high64, each
    little-endian; here from the canonical (big-endian high64, low64) digest."""
    d = xxhash.xxh3_128(token.encode()).digest()
    return d[8:][::-1] + d[:8][::-1]


def test_each_publisher_has_its_own_gid_and_sequence_from_one() -> None:
    toks = [core.endpoint_token(0, "abc", n, 5, "MP", f"/r{n}", f"eqa_bridge_r{n}", f"/r{n}/goal_pose",
                                ros.POSE_STAMPED) for n in (0, 1)]
    pubs = [core.Publisher(f"0/r{n}/goal_pose/x/y", t) for n, t in enumerate(toks)]
    got = [decode_attachment(pubs[0].next_attachment(10)), decode_attachment(pubs[1].next_attachment(11)),
           decode_attachment(pubs[0].next_attachment(12))]
    assert [(g[0], g[1]) for g in got] == [(1, 10), (1, 11), (2, 12)]
    assert got[0][2] == got[2][2] == _xxh3_gid(toks[0]) != got[1][2] == _xxh3_gid(toks[1])


def test_camera_pose_of_the_base_is_the_sims_camera() -> None:
    from services.sim.camera import camera_pose

    base = Pose2D(x=2.0, y=3.0, yaw=0.4)
    assert np.allclose(core.camera_to_world(base, core.base_to_camera(1.5, -30.0)), camera_pose(base))


# ---- the fleet with three ROS 2 robots ---------------------------------------------------------------------------
@dataclass
class Run:
    status: dict[str, dict[str, Any]]
    events: dict[str, list[dict[str, Any]]]
    robots: dict[str, TestRobot]
    tokens: list[str]
    bridge_log: str
    elapsed: dict[str, float]


ROBOTS = {"robot0": ("good", "jazzy"), "robot1": ("stuck", "humble"), "robot2": ("garbage", "jazzy"),
          "robot3": ("good", "humble")}


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[Run]:
    from services.sim.library import load_or_generate
    from services.sim.motion import START_CLEARANCE, sample_start_pose

    data = tmp_path_factory.mktemp("ros2-fleet")
    s = fleet_settings(data, redis_url, robots=list(ROBOTS), ros2_robots=list(ROBOTS), episode_timeout_s=120.0,
                       ros2_goal_timeout_s=1.5, ros2_frame_timeout_s=3.0, ros2_settle_s=0.2,
                       ros2_distros=[f"{r}={d}" for r, (_, d) in ROBOTS.items() if d != "jazzy"])
    scene = load_or_generate(SCENE, s.scenes_path)
    services = ("mapper", "vlm_scorer", "planner", "stopper", "ros2_bridge")
    with (
        Fleet(s, services=services, scorers=1) as fleet,
        Bus(fleet.client_settings(), "ros2_test_robots") as bus,
        GatewayThread(fleet.client_settings()) as gw,
        httpx.Client(base_url=gw.url, timeout=60) as c,
    ):
        rng = np.random.default_rng(5)
        robots = {}
        for name, (behaviour, distro) in ROBOTS.items():
            p = sample_start_pose(scene, rng, START_CLEARANCE)
            robots[name] = TestRobot(bus.session, scene, (p.x, p.y, p.yaw), namespace=f"/{name}",
                                     behaviour=behaviour, distro=distro).start()
        assert wait_for(lambda: c.get("/v1/ready").status_code == 200, 60), c.get("/v1/ready").text
        tokens: list[str] = []

        def bridge_tokens() -> bool:  # the bridge's rmw_zenoh tokens (a loaded machine answers late)
            replies = bus.session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
            tokens[:] = [str(r.ok.key_expr) for r in replies if r.ok is not None]
            return all(any(f"eqa_bridge_{name}" in t and "goal_pose" in t for t in tokens) for name in ROBOTS)

        assert wait_for(bridge_tokens, 60), tokens
        eids = {}
        for name in ROBOTS:
            r = c.post("/v1/questions", json={
                "question": "Which room is the sofa in?", "choices": ["kitchen", "living room", "bedroom", "bath"],
                "scene": SCENE, "max_steps": 4, "seed": 1, "stop_rule": "max_steps", "robot": name})
            assert r.status_code == 202, r.text
            eids[name] = r.json()["episode_id"]
        events, status, elapsed = {}, {}, {}
        for name, eid in eids.items():
            events[name] = [e for _, e in sse_events(c, f"/v1/episodes/{eid}/events", timeout=120)]
            elapsed[name] = events[name][-1]["t"] - events[name][0]["t"]  # queued/started to episode_end
            status[name] = c.get(f"/v1/episodes/{eid}").json()
        for r in robots.values():
            r.stop()
        log_text = (data / "logs" / "ros2_bridge-0.log").read_text()
        yield Run(status, events, robots, tokens, log_text, elapsed)


@pytest.mark.parametrize("name", ["robot0", "robot3"])  # Jazzy, Humble
def test_a_question_is_answered_end_to_end_by_a_ros2_robot(run: Run, name: str) -> None:
    st, ev, robot = run.status[name], run.events[name], run.robots[name]
    assert st["state"] == "stopped" and st["steps"] == 4 and st["answer"] in "ABCD", st
    frames = [e for e in ev if e["kind"] == "frame"]
    assert [f["step"] for f in frames] == [0, 1, 2, 3] and all(f["image"] == [120, 160] for f in frames)
    goals = [e for e in ev if e["kind"] == "goal" and not e["done"]]
    assert len(robot.goals) == len(goals) >= 3  # every goal reached the robot's own key, as PoseStamped
    for g, (_stamp, frame_id, vals) in zip(goals, robot.goals, strict=True):
        assert frame_id == "map" and (vals[0], vals[1]) == pytest.approx((g["pose"]["x"], g["pose"]["y"]), abs=1e-3)
    for f, g in zip(frames[1:], goals, strict=False):  # each next frame was taken at the goal it followed
        assert math.hypot(f["pose"]["x"] - g["pose"]["x"], f["pose"]["y"] - g["pose"]["y"]) < 0.01
    assert not [e for e in ev if e["kind"] == "error"], "a robot that arrives gets no refusal"


def test_each_robots_goals_come_from_its_own_publisher(run: Run) -> None:
    """Per robot: sequence numbers 1, 2, 3, ... with no jump (rmw_zenoh reports MESSAGE_LOST on one), and the GID
    rmw_zenoh derives from the bridge's publisher token for that robot, different for every robot."""
    gids = {}
    for name, robot in run.robots.items():
        if not robot.attachments:
            continue
        atts = [decode_attachment(a) for a in robot.attachments]
        assert [a[0] for a in atts] == list(range(1, len(atts) + 1)), name
        (token,) = [t for t in run.tokens if f"eqa_bridge_{name}" in t and t.split("/")[5] == "MP"]
        assert {a[2] for a in atts} == {_xxh3_gid(token)}, name
        assert all(abs(a[1] - time.time_ns()) < 600 * 10**9 for a in atts)  # a wall-clock source timestamp
        gids[name] = atts[0][2]
    assert {"robot0", "robot1", "robot3"} <= set(gids) and len(set(gids.values())) == len(gids)


def test_the_bridge_is_a_ros2_node_with_its_endpoints(run: Run) -> None:
    mine = [t.split("/") for t in run.tokens if "eqa_bridge_robot0" in t]
    kinds = {(p[5], p[9] if len(p) > 9 else None) for p in mine}
    assert ("NN", None) in kinds and ("MP", "%robot0%goal_pose") in kinds, kinds
    assert {("MS", "%robot0%odom"), ("MS", "%robot0%camera%color%image_raw"),
            ("MS", "%robot0%camera%depth%image_raw"), ("MS", "%robot0%camera%color%camera_info")} <= kinds
    pub = next(p for p in mine if p[5] == "MP")
    assert pub[10:12] == ["geometry_msgs::msg::dds_::PoseStamped_", ros2_defs.rihs01(ros.POSE_STAMPED)]
    humble = [t.split("/") for t in run.tokens if "eqa_bridge_robot3" in t and t.split("/")[5] in ("MP", "MS")]
    assert humble and {p[11] for p in humble} == {"TypeHashNotSupported"}


def test_a_robot_that_never_arrives_gets_refused_goals_and_the_episode_ends(run: Run) -> None:
    st, ev = run.status["robot1"], run.events["robot1"]
    errors = [e for e in ev if e["kind"] == "error"]
    assert errors and all("not reached within 1.5 s" in e["reason"] for e in errors), errors
    assert st["state"] in ("stopped", "failed") and ev[-1]["kind"] == "episode_end", st
    assert len(run.robots["robot1"].goals) == len(errors)  # each goal reached the Humble robot and was refused
    assert run.elapsed["robot1"] < 90


def test_a_robot_that_sends_garbage_is_refused_with_reasons_and_no_hang(run: Run) -> None:
    st, ev = run.status["robot2"], run.events["robot2"]
    assert st["state"] == "failed" and "ros2_bridge refused the episode" in st["stop_reason"], st
    err = next(e for e in ev if e["kind"] == "error")
    assert err["step"] == 0 and "no fresh, consistent RGB-D frame" in err["reason"], err
    assert "the last ROS input refused" in err["reason"], err
    assert run.elapsed["robot2"] < 30
    assert not [e for e in ev if e["kind"] == "frame"]
    for code in ("encoding", "stale"):  # counted and logged by reason
        assert f"ROS input refused ({code}," in run.bridge_log, code
    assert "nan_pose" in run.bridge_log or "stale" in run.bridge_log


def test_the_bridge_counts_each_refusal_by_reason(tmp_path: Any) -> None:
    from services.ros2_bridge.service import Ros2BridgeService

    s = fleet_settings(tmp_path, None, robots=["r1"], ros2_robots=["r1"], ros2_max_image_pixels=100)
    bridge = Ros2BridgeService(s)  # not started: its handlers are called directly
    rb = bridge.robots["r1"]
    assert rb.namespace == "/r1"
    bridge._take("r1", "rgb", ros.IMAGE, b"\x00\x01\x00\x00garbage", time.monotonic())
    big = ros.serialize(ros.image(time.time_ns(), "c", np.zeros((20, 20, 3), np.uint8), "rgb8"), ros.IMAGE)
    bridge._take("r1", "rgb", ros.IMAGE, big, time.monotonic())
    old = ros.serialize(ros.image(time.time_ns() - 10**11, "c", np.zeros((2, 2, 3), np.uint8), "rgb8"), ros.IMAGE)
    bridge._take("r1", "rgb", ros.IMAGE, old, time.monotonic())
    assert bridge.refused == {"cdr": 1, "huge": 1, "stale": 1} and rb.rgb is None
    assert "100.0 s old" in rb.last_refusal
    ok = ros.serialize(ros.image(time.time_ns(), "c", np.full((2, 2, 3), 7, np.uint8), "rgb8"), ros.IMAGE)
    bridge._take("r1", "rgb", ros.IMAGE, ok, time.monotonic())
    assert rb.rgb is not None and rb.rgb.value.tolist() == [[[7, 7, 7]] * 2] * 2
