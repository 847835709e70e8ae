"""Hostile bus payloads: decompression bombs and lying array headers are refused before any large
allocation, frames held for unknown episodes are capped in bytes, an EpisodeStart that does not validate (or
whose handler fails) is answered with an ErrorReply at once instead of silence for the gateway's watchdog,
and a flood of data messages cannot hold up an EpisodeEnd in the gateway. Real Zenoh sessions on loopback,
the real sim, mapper and gateway."""

from __future__ import annotations

import base64
import resource
import sqlite3
import threading
import time
import zlib

import httpx
import msgpack
import numpy as np
import pytest
from support.fleet import GatewayThread, wait_for
from support.services import serving

from eqa import codec, keys
from eqa.bus import Bus
from eqa.codec import CodecError, packb, unpackb
from eqa.messages import EpisodeEnd, ErrorReply, Frame, Pose2D, decode
from eqa.settings import Settings


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _zext(dtype: str, shape: list[int], body: bytes) -> msgpack.ExtType:
    header = msgpack.packb([dtype, shape])
    return msgpack.ExtType(2, len(header).to_bytes(4, "little") + header + body)


def _zeros_compressed(n: int) -> bytes:
    z = zlib.compressobj(9)
    block = bytes(1 << 20)
    out = [z.compress(block) for _ in range(n >> 20)]
    return b"".join([*out, z.flush()])


def test_decompression_bomb_is_refused_before_inflating() -> None:
    bomb_body = _zeros_compressed(256 << 20)  # 256 MB of zeros in ~250 KB
    assert len(bomb_body) < 1 << 20
    rss0 = _rss_mb()
    payload = msgpack.packb({"a": _zext("|u1", [256 << 20], bomb_body)}, use_bin_type=True)
    with pytest.raises(CodecError, match="over the cap"):
        unpackb(payload)
    # A header that lies (declares 1000 bytes) stops inflating at 1001 bytes.
    payload = msgpack.packb({"a": _zext("|u1", [1000], bomb_body)}, use_bin_type=True)
    with pytest.raises(CodecError, match="does not inflate to the 1000 bytes"):
        unpackb(payload)
    assert _rss_mb() - rss0 < 64


@pytest.mark.parametrize(
    "shape", [[2**40, 2**40], [2**62, 4], [-1, 10], [1.5], [True], [1] * 9], ids=str
)
def test_absurd_shapes_are_refused(shape: list) -> None:
    payload = msgpack.packb({"a": _zext("<f8", shape, zlib.compress(b""))}, use_bin_type=True)
    with pytest.raises(CodecError):
        unpackb(payload)
    with pytest.raises(ValueError):
        codec._validate_array({"dtype": "<f8", "shape": shape, "b64": "AAAA"})


def test_all_arrays_of_one_message_share_one_budget() -> None:
    arrays = {f"a{i}": np.ones((1000, 500), np.uint8) for i in range(3)}  # 0.5 MB each
    payload = packb(arrays)
    assert set(unpackb(payload, max_decoded=2 * 10**6)) == {"a0", "a1", "a2"}
    with pytest.raises(CodecError, match="arrays of one message"):
        unpackb(payload, max_decoded=10**6)
    big = {"dtype": "|u1", "shape": [10], "b64": base64.b64encode(bytes(10_000)).decode()}
    with pytest.raises(ValueError, match="longer than its shape"):
        codec._validate_array(big)


def test_bomb_on_the_bus_is_dropped_and_the_stream_goes_on(hub_settings: Settings, settings: Settings) -> None:
    got: list[Frame] = []
    with Bus(hub_settings, "gateway", "t1") as sub, Bus(settings, "attacker", "t2") as pub:
        sub.subscribe(keys.stream("r0", keys.SIM_FRAME), Frame, lambda _k, m: got.append(m))
        time.sleep(0.5)
        bomb = {"kind": "frame", "schema_version": 1, "sent_at": 0.0, "episode_id": "ep-1", "step": 0,
                "pose": {"x": 0, "y": 0, "yaw": 0}, "camera_pose": np.eye(4), "intrinsics": np.eye(3),
                "rgb": _zext("|u1", [4096, 4096, 30], _zeros_compressed(64 << 20)), "depth": np.zeros((2, 2))}
        rss0 = _rss_mb()
        for _ in range(3):
            pub.publish_raw(keys.stream("r0", keys.SIM_FRAME), packb(bomb))
        ok = Frame(episode_id="ep-1", step=1, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4), intrinsics=np.eye(3),
                   rgb=np.zeros((4, 4, 3), np.uint8), depth=np.zeros((4, 4), np.float32))
        pub.publish(keys.stream("r0", keys.SIM_FRAME), ok)
        assert wait_for(lambda: len(got) == 1, 15)
        assert got[0].step == 1 and _rss_mb() - rss0 < 200


def _raw_start(episode_id: str, robot: str, **question: object) -> bytes:
    q = {"id": "q-1", "text": "Where is the box?", "choices": [], "scene": "gen-00014", **question}
    return packb({"kind": "episode_start", "schema_version": 1, "sent_at": time.time(), "episode_id": episode_id,
                  "robot": robot, "question": q, "max_steps": 5, "seed": 0, "record": False})


def test_sim_answers_a_start_it_cannot_take_at_once(hub_settings: Settings, settings: Settings) -> None:
    """A start pose of 1e308 killed the sim's handler with an OverflowError and nothing came back: the episode
    held its robot until the watchdog (120 s). Now the start does not validate, and the sim says so at once."""
    from services.sim.service import SimService

    errors: list[ErrorReply] = []
    with Bus(hub_settings, "gateway", "t1") as bus:
        bus.subscribe(keys.any_robot(keys.SIM_ERROR), ErrorReply, lambda _k, m: errors.append(m))
        with serving(SimService(settings)):
            t0 = time.monotonic()
            bus.publish_raw(keys.stream("r0", keys.EPISODE_START),
                            _raw_start("ep-huge", "r0", start_pose={"x": 1e308, "y": -1e308, "yaw": 0.0}))
            bus.publish_raw(keys.stream("r1", keys.EPISODE_START), _raw_start("ep-nl", "r1", scene="gen-00014\n"))
            assert wait_for(lambda: {e.episode_id for e in errors} >= {"ep-huge", "ep-nl"}, 15), errors
            assert time.monotonic() - t0 < 10
            by_id = {e.episode_id: e for e in errors}
            assert by_id["ep-huge"].step == 0 and "pose out of range" in by_id["ep-huge"].reason
            assert "not a scene id" in by_id["ep-nl"].reason
            assert not (settings.scenes_path / "gen-00014\n").exists()


def test_mapper_holds_at_most_its_byte_cap_of_early_frames(hub_settings: Settings, settings: Settings) -> None:
    """Frames of episodes the mapper has not seen start are held for a while (they may overtake their start):
    at most 64 MB of them, not 64 frames of any size (16 frames of 24 MB were +312 MB). The rest are answered
    with an ErrorReply at once."""
    from services.mapper.service import MapperService

    errors: list[ErrorReply] = []
    with Bus(hub_settings, "gateway", "t1") as bus:
        bus.subscribe(keys.any_robot(keys.MAPPER_ERROR), ErrorReply, lambda _k, m: errors.append(m))
        with serving(MapperService(settings)):
            rgb = np.zeros((1500, 2000, 3), np.uint8)  # 9 MB + 12 MB of depth: 21 MB a frame
            depth = np.zeros((1500, 2000), np.float32)
            sent = [f"ep-x{i}" for i in range(8)]
            for eid in sent:
                bus.publish(keys.stream("r0", keys.SIM_FRAME),
                            Frame(episode_id=eid, step=0, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4),
                                  intrinsics=np.eye(3), rgb=rgb, depth=depth))
            # 3 frames (63 MB) may wait for their start; the other 5 are refused at once (not after 30 s)
            assert wait_for(lambda: len({e.episode_id for e in errors} & set(sent)) >= 5, 15), errors


def test_a_flood_does_not_hold_up_the_end(hub_settings: Settings, settings: Settings, tmp_path) -> None:
    """A flood of data messages must not queue without bound in the gateway (an EpisodeEnd would wait minutes
    behind it). Messages of episodes it does not run are dropped on arrival; data messages wait at most
    INBOX_MAX_DATA deep; the end comes through."""
    from gateway.app import INBOX_MAX_DATA

    gs = hub_settings.model_copy(update={"data_dir": tmp_path / "gw", "api_tokens": [], "episode_timeout_s": 3600.0})
    with GatewayThread(gs) as gw, httpx.Client(base_url=gw.url, timeout=30) as c, \
            Bus(settings, "attacker", "t2") as pub:
        eid = c.post("/v1/questions", json={"question": "q?", "robot": "robot0", "max_steps": 5}).json()["episode_id"]
        time.sleep(0.5)
        frame = Frame(episode_id=eid, step=0, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4), intrinsics=np.eye(3),
                      rgb=np.zeros((240, 320, 3), np.uint8), depth=np.zeros((240, 320), np.float32))
        other = frame.model_copy(update={"episode_id": "ep-not-running"})
        key = keys.stream("robot0", keys.SIM_FRAME)

        def flood() -> None:
            for _ in range(1500):
                pub.publish(key, other)
                pub.publish(key, frame)

        # Hold the gateway's store (a slow or frozen store) while the flood comes in: its consumer stalls.
        lock = sqlite3.connect(gs.data_dir / "store.sqlite", timeout=30, isolation_level=None)
        lock.execute("BEGIN EXCLUSIVE")
        t = threading.Thread(target=flood)
        t.start()
        t.join()
        time.sleep(0.5)
        lock.execute("COMMIT")
        lock.close()
        t0 = time.monotonic()
        pub.publish(keys.stream("robot0", keys.EPISODE_END),
                    EpisodeEnd(episode_id=eid, robot="robot0", state="stopped", reason="done", steps=1, max_steps=5))
        assert wait_for(lambda: c.get(f"/v1/episodes/{eid}").json()["state"] == "stopped", 60)
        took = time.monotonic() - t0
        events = c.get(f"/v1/episodes/{eid}/events").text
        frames_stored = events.count('"kind":"frame"')
        assert frames_stored <= INBOX_MAX_DATA + 2, frames_stored  # the rest was dropped (and logged)
        assert took < 15, took
        assert INBOX_MAX_DATA <= 1000
    assert decode(packb({"kind": "error", "schema_version": 1, "sent_at": 0.0, "source": "x", "reason": "y"}),
                  ErrorReply).reason == "y"
