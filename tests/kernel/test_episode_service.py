"""eqa.episode_service: the one episode-service pattern, on a small probe service over real Zenoh and a real
store (embedded SQLite in the test's data dir): holding until EpisodeStart, the resent-step answer, state in
the store and a restart, bounds and expiry of held messages, ownership, a failing handler, the end."""

from __future__ import annotations

import queue
import time
from collections.abc import Iterator
from typing import Any

import pytest

from eqa import keys
from eqa.bus import Bus
from eqa.codec import unpackb
from eqa.episode_service import EpisodeService
from eqa.messages import Decision, EpisodeEnd, EpisodeStart, ErrorReply, Question, StepScores
from eqa.settings import Settings
from eqa.store import episode_end_key, episode_state_key

ROBOT = "r0"


class Probe(EpisodeService[dict[str, Any]]):
    """Counts the scores of each episode and answers every step with a Decision naming the count."""

    name = "probe"
    error_stream = keys.MAPPER_ERROR
    hold_ttl_s = 1.0
    hold_max_per_episode = 3

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.handled: list[tuple[str, int]] = []

    def setup_episodes(self) -> None:
        self.on_step(keys.MAPPER_SCORES, self.on_scores)

    def owns(self, robot: str) -> bool:
        return robot != "r9"

    def start_episode(self, robot: str, start: EpisodeStart) -> dict[str, Any] | None:
        return None if start.question.text == "refuse" else {"n": 0}

    def dump_state(self, state: dict[str, Any], **extra: Any) -> dict[str, Any]:
        return dict(state)

    def load_state(self, episode_id: str, data: Any) -> dict[str, Any]:
        return {"n": int(data["n"])}

    def unknown_episode(self, robot: str, msg: Any, why: str) -> None:
        self.error(robot, msg.episode_id, msg.step, f"unknown episode: {why}")

    def on_scores(self, robot: str, state: dict[str, Any], msg: StepScores) -> None:
        if msg.relevance < 0:
            raise ValueError("negative relevance")
        state["n"] += 1
        self.handled.append((msg.episode_id, msg.step))
        out = Decision(episode_id=msg.episode_id, step=msg.step, rule="max_steps", stop=False, reason=f"n={state['n']}")
        self.publish_step(msg.episode_id, keys.STOPPER_DECISION, out, msg.step, save=True)


def _start(eid: str, robot: str = ROBOT, text: str = "Is it on?") -> EpisodeStart:
    question = Question(text=text, choices=["yes", "no"], scene="gen-00001")
    return EpisodeStart(episode_id=eid, robot=robot, question=question, max_steps=10, record=False)


def _scores(eid: str, step: int, relevance: float = 0.5) -> StepScores:
    return StepScores(episode_id=eid, step=step, answer_probs=[0.5, 0.5], relevance=relevance)


@pytest.fixture
def rig(hub_settings: Settings, settings: Settings) -> Iterator[tuple[Settings, queue.Queue[Any]]]:
    hub = Bus(hub_settings, "gateway", "hub").open()
    out: queue.Queue[Any] = queue.Queue()
    for pair in (keys.STOPPER_DECISION, keys.MAPPER_ERROR):
        hub.subscribe(keys.any_robot(pair), (Decision, ErrorReply), lambda _k, m: out.put(m))
    try:
        yield settings, out
    finally:
        hub.close()


def _run(svc: Probe, *calls: tuple[Any, ...]) -> None:
    for pair, robot, msg in calls:
        svc.submit(svc.receive, pair, robot, msg)
    assert svc.drain(10)


def _collect(out: queue.Queue[Any], n: int, timeout: float = 10.0) -> list[Any]:
    got = []
    deadline = time.monotonic() + timeout
    while len(got) < n:
        got.append(out.get(timeout=max(0.01, deadline - time.monotonic())))
    time.sleep(0.2)
    assert out.empty(), f"more than {n} messages: {list(out.queue)}"
    return got


def test_held_until_start_resent_step_answered_again_and_restart(rig) -> None:
    settings, out = rig
    svc = Probe(settings)
    svc.start()
    try:
        time.sleep(0.3)
        # step 1 and step 0 overtake their start: held, then handled in step order
        _run(svc, (keys.MAPPER_SCORES, ROBOT, _scores("ep-a", 1)), (keys.MAPPER_SCORES, ROBOT, _scores("ep-a", 0)))
        assert svc.handled == [] and out.empty()
        _run(svc, (keys.EPISODE_START, ROBOT, _start("ep-a")))
        assert svc.handled == [("ep-a", 0), ("ep-a", 1)]
        d = _collect(out, 2)
        assert [(m.step, m.reason) for m in d] == [(0, "n=1"), (1, "n=2")]
        # the resent step is answered with the same message, the handler does not run again; older: ignored
        _run(svc, (keys.MAPPER_SCORES, ROBOT, _scores("ep-a", 1)), (keys.MAPPER_SCORES, ROBOT, _scores("ep-a", 0)))
        again = _collect(out, 1)[0]
        assert (again.step, again.reason, again.sent_at) == (1, "n=2", d[1].sent_at)
        assert svc.handled == [("ep-a", 0), ("ep-a", 1)]
        # a repeated start is ignored
        _run(svc, (keys.EPISODE_START, ROBOT, _start("ep-a")))
        assert svc.episodes["ep-a"] == {"n": 2}
        stored = unpackb(svc.store.get(episode_state_key("probe", "ep-a")))
        assert stored["robot"] == ROBOT and stored["state"] == {"n": 2} and stored["answers"]["step"] == 1
    finally:
        svc.stop()
    # a restarted service: the state and the last answer come from the store
    svc = Probe(settings)
    svc.start()
    try:
        time.sleep(0.3)
        _run(svc, (keys.MAPPER_SCORES, ROBOT, _scores("ep-a", 1)))
        again = _collect(out, 1)[0]
        assert (again.step, again.reason) == (1, "n=2") and svc.handled == []
        _run(svc, (keys.MAPPER_SCORES, ROBOT, _scores("ep-a", 2)))
        assert _collect(out, 1)[0].reason == "n=3"
        # the end drops memory and store
        _run(svc, (keys.EPISODE_END, ROBOT, EpisodeEnd(episode_id="ep-a", robot=ROBOT, state="stopped", reason="done",
                                                        steps=3)))
        assert "ep-a" not in svc.episodes and svc.store.get(episode_state_key("probe", "ep-a")) is None
    finally:
        svc.stop()


def test_bounds_expiry_ownership_errors_and_refused_start(rig) -> None:
    settings, out = rig
    svc = Probe(settings)
    svc.start()
    try:
        time.sleep(0.3)
        # at most 3 held per episode: the 4th is answered at once, the 3 others when they expire (1 s)
        _run(svc, *[(keys.MAPPER_SCORES, ROBOT, _scores("ep-x", k)) for k in range(4)])
        first = _collect(out, 1)[0]
        assert isinstance(first, ErrorReply) and first.step == 3 and "3 of its messages already wait" in first.reason
        expired = _collect(out, 3, timeout=10)
        assert sorted(e.step for e in expired) == [0, 1, 2]
        assert all("no EpisodeStart within 1 s" in e.reason for e in expired)
        # messages of an episode that already ended are dropped quietly
        svc.store.set(episode_end_key("ep-old"), b"{}")
        _run(svc, (keys.MAPPER_SCORES, ROBOT, _scores("ep-old", 0)))
        # a robot this instance does not own: nothing at all
        _run(svc, (keys.EPISODE_START, "r9", _start("ep-9", "r9")), (keys.MAPPER_SCORES, "r9", _scores("ep-9", 0)))
        assert "ep-9" not in svc.episodes and not svc._held
        # a refused start drops what was held for it
        _run(svc, (keys.MAPPER_SCORES, ROBOT, _scores("ep-r", 0)),
             (keys.EPISODE_START, ROBOT, _start("ep-r", text="refuse")))
        assert "ep-r" not in svc.episodes and "ep-r" not in svc._held
        # a handler that raises answers the episode with an error at once
        _run(svc, (keys.EPISODE_START, ROBOT, _start("ep-b")), (keys.MAPPER_SCORES, ROBOT, _scores("ep-b", 0, -1.0)))
        err = _collect(out, 1)[0]
        assert isinstance(err, ErrorReply) and err.episode_id == "ep-b" and err.step == 0
        assert "probe failed on step_scores: ValueError: negative relevance" in err.reason
        assert svc.handled == []
    finally:
        svc.stop()


def test_held_bytes_are_bounded(rig) -> None:
    import numpy as np

    from eqa.messages import Frame, Pose2D

    settings, out = rig

    class Frames(Probe):
        hold_max_bytes = 3 * 1024 * 1024

        def setup_episodes(self) -> None:
            self.on_step(keys.SIM_FRAME, lambda robot, state, msg: None)

    svc = Frames(settings)
    svc.start()
    try:
        time.sleep(0.3)
        rgb = np.zeros((600, 800, 3), np.uint8)  # 1.44 MB a frame
        frames = [Frame(episode_id=f"ep-f{i}", step=0, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4),
                        intrinsics=np.eye(3), rgb=rgb, depth=np.zeros((1, 1), np.float32)) for i in range(4)]
        _run(svc, *[(keys.SIM_FRAME, ROBOT, f) for f in frames])
        assert sorted(svc._held) == ["ep-f0", "ep-f1"]
        errs = _collect(out, 2)
        assert {e.episode_id for e in errs} == {"ep-f2", "ep-f3"} and all("bytes" in e.reason for e in errs)
    finally:
        svc.stop()
