"""The bus over real Zenoh sessions: two peers on loopback, multicast scouting off."""

from __future__ import annotations

import time

import numpy as np
import pytest
from support.fleet import wait_for

from eqa import keys
from eqa.bus import Bus
from eqa.messages import ErrorReply, Frame, Pose2D, Question, ScoreRequest, ScoreResult, StepScores


def _frame(step: int = 0) -> Frame:
    return Frame(
        episode_id="ep1", step=step, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4), intrinsics=np.eye(3),
        rgb=np.zeros((12, 16, 3), np.uint8), depth=np.ones((12, 16), np.float32),
    )




def test_pubsub_between_two_peers_and_garbage_is_dropped(hub_settings, settings):
    got: list[Frame] = []
    key = keys.stream("r0", keys.SIM_FRAME)
    with Bus(hub_settings, "sim", "a") as a, Bus(settings, "mapper", "b") as b:
        b.subscribe(key, Frame, lambda k, m: got.append(m))
        time.sleep(0.3)
        a.publish_raw(key, b"\x00garbage")
        a.publish(key, StepScores(episode_id="ep1", step=0, answer_probs=[1.0], relevance=0.5))  # wrong type
        a.publish(key, _frame(3))
        assert wait_for(lambda: len(got) == 1, timeout=5.0)
        assert got[0].step == 3 and got[0].depth.dtype == np.float32
        a.publish(key, _frame(4))  # the subscriber survived the garbage
        assert wait_for(lambda: len(got) == 2, timeout=5.0)


def test_handler_exception_does_not_kill_subscriber(hub_settings, settings):
    calls: list[int] = []

    def handler(_k, m):
        calls.append(m.step)
        if m.step == 0:
            raise RuntimeError("boom")

    key = keys.stream("r0", keys.SIM_FRAME)
    with Bus(hub_settings, "sim", "a") as a, Bus(settings, "mapper", "b") as b:
        b.subscribe(key, Frame, handler)
        time.sleep(0.3)
        a.publish(key, _frame(0))
        a.publish(key, _frame(1))
        assert wait_for(lambda: calls == [0, 1], timeout=5.0)


def test_queryable_replies_and_reports_errors(hub_settings, settings):
    def score(req: ScoreRequest) -> ScoreResult:
        if not req.question.choices:
            raise ValueError("no choices")
        n = len(req.question.choices)
        return ScoreResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                           answer_probs=[1 / n] * n, relevance=0.5, backend="test")

    with Bus(hub_settings, "vlm_scorer", "s1") as a, Bus(settings, "mapper", "m") as b:
        a.declare_queryable(keys.scorer_replica("s1"), ScoreRequest, score)
        time.sleep(0.3)
        q = Question(text="Where?", choices=["a", "b"], scene="s")
        req = ScoreRequest(episode_id="e", step=0, question=q, rgb=np.zeros((4, 4, 3), np.uint8))
        replies = b.query(keys.SCORER_ANY, req, timeout=2.0)
        assert len(replies) == 1 and isinstance(replies[0][1], ScoreResult)
        assert keys.replica_of(replies[0][0]) == "s1"
        bad = req.model_copy(update={"question": Question(text="x", scene="s")})
        (_, err), = b.query(keys.SCORER_ANY, bad, timeout=2.0)
        assert isinstance(err, ErrorReply) and "no choices" in err.reason
        raw = b.session.get(keys.SCORER_ANY, payload=b"junk", timeout=2.0)
        texts = [r.ok.payload.to_bytes() for r in raw if r.ok is not None]
        assert texts and b"msgpack" in texts[0]


def test_liveliness_tokens_appear_and_disappear(hub_settings, settings):
    seen: list[tuple[str, str, bool]] = []
    with Bus(hub_settings, "gateway", "g") as watcher:
        watcher.watch_alive(keys.ALIVE_ANY, lambda s, i, up: seen.append((s, i, up)))
        b = Bus(settings, "mapper", "m1").open()
        b.declare_alive()
        assert wait_for(lambda: ("mapper", "m1", True) in seen, timeout=5.0)
        assert ("mapper", "m1") in watcher.alive()
        b.close()
        assert wait_for(lambda: ("mapper", "m1", False) in seen, timeout=5.0)


def test_a_process_restarted_under_a_live_name_is_seen_arriving(hub_settings, settings):
    """A second process under a live instance name is reported up again (whatever was in flight to the first
    is lost), and the name is reported gone only with its last process, in either order of exits."""
    seen: list[tuple[str, str, bool]] = []
    with Bus(hub_settings, "gateway", "g") as watcher:
        watcher.watch_alive(keys.ALIVE_ANY, lambda s, i, up: seen.append((s, i, up)))
        old = Bus(settings, "mapper", "m1").open()
        old.declare_alive()
        assert wait_for(lambda: seen == [("mapper", "m1", True)], timeout=5.0)
        new = Bus(settings, "mapper", "m1").open()
        new.declare_alive()
        assert wait_for(lambda: seen == [("mapper", "m1", True)] * 2, timeout=5.0), seen
        assert watcher.alive(keys.alive_service("mapper")) == [("mapper", "m1")]
        old.close()
        time.sleep(0.5)
        assert seen == [("mapper", "m1", True)] * 2  # the new process still holds the name
        assert watcher.alive(keys.alive_service("mapper")) == [("mapper", "m1")]
        new.close()
        assert wait_for(lambda: seen[-1] == ("mapper", "m1", False), timeout=5.0), seen
        assert seen.count(("mapper", "m1", False)) == 1


def test_liveliness_keys_name_the_process():
    key = keys.alive("mapper", "m1", "1f0a")
    assert keys.parse_alive(key) == ("mapper", "m1", "1f0a")
    for bad in ("", "XYZ", "*", "a/b", "0" * 33):
        with pytest.raises(ValueError):
            keys.alive("mapper", "m1", bad)
    for bad in ("eqa/v1/alive/mapper/m1", "eqa/v1/alive/mapper/m1/a/b", "eqa/v1/robots/mapper/m1/a"):
        with pytest.raises(ValueError):
            keys.parse_alive(bad)
