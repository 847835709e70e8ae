"""Messages and the wire codec: arrays as raw bytes, versions, clear errors."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from eqa import keys
from eqa.codec import CodecError
from eqa.messages import (
    SCHEMA_VERSION,
    Decision,
    EpisodeStart,
    Frame,
    GridSpec,
    MapUpdate,
    Pose2D,
    Question,
    StopConfig,
    decode,
    encode,
    model_json,
)


def _map() -> MapUpdate:
    occ = np.zeros((300, 200), bool)
    occ[10:20, 30:40] = True
    return MapUpdate(
        episode_id="e", step=2, grid=GridSpec(origin_x=-1, origin_y=-2, resolution=0.1, rows=300, cols=200),
        occupied=occ, free=~occ, explored=np.zeros_like(occ), values={"question": np.full((300, 200), 1.5, np.float32)},
        pose=Pose2D(x=1, y=2, yaw=3),
    )


def test_arrays_roundtrip_exactly_and_maps_are_compressed():
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    depth = np.random.default_rng(1).random((48, 64), dtype=np.float32)
    f = Frame(episode_id="e", step=1, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4), intrinsics=np.eye(3),
              rgb=rgb, depth=depth)
    back = decode(encode(f), Frame)
    assert np.array_equal(back.rgb, rgb) and back.rgb.dtype == np.uint8
    assert np.array_equal(back.depth, depth) and back.depth.dtype == np.float32
    m = _map()
    raw = encode(m)
    assert len(raw) < m.occupied.nbytes  # three bool maps and a float layer, compressed
    back_m = decode(raw, MapUpdate)
    assert np.array_equal(back_m.occupied, m.occupied) and back_m.values["question"].dtype == np.float32


def test_json_form_roundtrips_arrays():
    m = _map()
    again = MapUpdate.model_validate(model_json(m))
    assert np.array_equal(again.occupied, m.occupied)


@pytest.mark.parametrize(
    "payload, match",
    [
        (b"", "msgpack"),
        (msgpack.packb([1, 2]), "expected a message map"),
        (msgpack.packb({"kind": "nope"}), "unknown message kind"),
        (msgpack.packb({"kind": "decision", "schema_version": SCHEMA_VERSION + 1}), "schema version"),
        (msgpack.packb({"kind": "decision", "episode_id": "e"}), "invalid decision"),
        (msgpack.packb({"kind": "frame", "rgb": msgpack.ExtType(1, b"\x05\x00\x00\x00junk")}), "malformed array"),
    ],
)
def test_bad_payloads_give_reasons(payload, match):
    with pytest.raises(CodecError, match=match):
        decode(payload)


def test_object_arrays_are_refused():
    with pytest.raises((CodecError, ValidationError)):
        encode(Frame(episode_id="e", step=0, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4), intrinsics=np.eye(3),
                     rgb=np.array([object()]), depth=np.zeros(1, np.float32)))


def test_question_validation():
    q = Question(text="Is the stove off?", choices=["Yes", "No"], scene="gen-00001")
    assert q.labels == ["A", "B"] and q.formatted().endswith("B) No. Answer:")
    for bad in (["only"], [str(i) for i in range(27)]):
        with pytest.raises(ValidationError, match="between 2 and 26"):
            Question(text="x?", choices=bad, scene="s")
    with pytest.raises(ValidationError, match="empty"):
        Question(text="   ", choices=["a", "b"], scene="s")
    with pytest.raises(ValidationError):
        Question(text="x" * 2001, choices=["a", "b"], scene="s")
    with pytest.raises(ValidationError, match="finite"):
        Pose2D(x=float("nan"), y=0)
    with pytest.raises(ValidationError):
        StopConfig(eps=1.5)


def test_episode_ids_are_key_safe_and_decisions_roundtrip():
    q = Question(text="q?", choices=["a", "b"], scene="s")
    with pytest.raises(ValidationError, match="letters, digits"):
        EpisodeStart(episode_id="ep/**", robot="r0", question=q, max_steps=5)
    d = Decision(episode_id="e", step=0, rule="cp", stop=False, reason="3 answers left",
                 prediction_set=["A", "B", "C"], scores={"A": -0.1})
    assert decode(encode(d), Decision) == d


def test_keys_refuse_wildcards():
    assert keys.stream("robot0", keys.SIM_FRAME) == "eqa/v1/robot0/sim/frame"
    assert keys.robot_of("eqa/v1/robot0/sim/frame") == "robot0"
    for bad in ("*", "a/b", "@x", "", "x" * 65):
        with pytest.raises(ValueError):
            keys.stream(bad, keys.SIM_FRAME)
