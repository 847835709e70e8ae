"""The gateway's episode state machine as pure functions (gateway/state.py): no store, no bus, no clock."""

from __future__ import annotations

import numpy as np

from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStatus,
    ErrorReply,
    Frame,
    Pose2D,
    Question,
    StopConfig,
)
from gateway import state as lifecycle


def _status(state: str = "running", steps: int = 0) -> EpisodeStatus:
    q = Question(text="Where is it?", choices=["bedroom", "hallway"], scene="gen-1", answer="B")
    return EpisodeStatus(episode_id="ep-1", robot="r0", state=state, question=q, strategy="semantic",  # type: ignore[arg-type]
                         stop=StopConfig(), max_steps=10, steps=steps, created_at=0.0, updated_at=0.0)


def _frame(step: int) -> Frame:
    return Frame(episode_id="ep-1", step=step, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4), intrinsics=np.eye(3),
                 rgb=np.zeros((2, 2, 3), np.uint8), depth=np.zeros((2, 2), np.float32))


def test_messages_advance_a_running_episode_without_touching_the_input() -> None:
    st = _status()
    t = lifecycle.on_message(st, "r0", _frame(3), now=5.0)
    assert not t.ignore and t.ending is None and t.status is not None
    assert (t.status.step, t.status.steps, t.status.normalized_steps, t.status.updated_at) == (3, 4, 0.4, 5.0)
    assert (st.step, st.steps) == (-1, 0)  # pure: the input is not changed
    d = lifecycle.on_message(t.status, "r0", Decision(episode_id="ep-1", step=3, rule="cp", stop=False, reason="",
                                               prediction_set=["A", "B"], answer="B"), now=6.0)
    assert d.status is not None and d.status.prediction_set == ["A", "B"] and d.status.answer == "B"


def test_ignored_inputs() -> None:
    assert lifecycle.on_message(_status("queued"), "r0", _frame(0), 1.0).ignore
    assert lifecycle.on_message(_status(), "r0", EpisodeCancel(episode_id="ep-1"), 1.0).ignore
    other = lifecycle.on_message(_status(), "r9", _frame(0), 1.0)
    assert other.ignore and "runs on r0" in other.notes[0]


def test_endings() -> None:
    end = EpisodeEnd(episode_id="ep-1", robot="r0", state="stopped", reason="one answer left", answer="B", steps=4,
                     max_steps=10)
    t = lifecycle.on_message(_status(), "r0", end, 1.0)
    assert t.ending == lifecycle.Ending("stopped", "one answer left", end=end)
    refusal = lifecycle.on_message(_status(), "r0", ErrorReply(source="sim", reason="start pose refused", step=0), 1.0)
    assert refusal.ending == lifecycle.Ending("failed", "sim refused the episode: start pose refused",
                                              tell_services=True)
    late = lifecycle.on_message(_status(steps=2), "r0", ErrorReply(source="sim", reason="goal refused", step=2), 1.0)
    assert late.ending is None and late.last_error == "sim at step 2: goal refused"
    final = lifecycle.finished(_status(), "stopped", "one answer left", 9.0, end=end, recording=True)
    assert (final.answer_text, final.correct, final.normalized_steps) == ("hallway", True, 0.4)
    assert final.recording == "/v1/episodes/ep-1/recording" and final.updated_at == 9.0
    assert lifecycle.end_event(final)["source"] == "gateway" and lifecycle.end_event(final)["state"] == "stopped"
    assert lifecycle.timed_out("running", 0.0, 0.0, 11.0, 10.0)
    assert not lifecycle.timed_out("queued", 0.0, 0.0, 11.0, 10.0)
    reason = lifecycle.timeout_reason(_status(), 10.0, ["planner"], "mapper at step 0: x", restarted=True)
    assert reason.startswith("no message for 10 s (last step -1); services not alive: planner; last error: mapper")
    assert "restarted" in reason and lifecycle.cancellable("queued") and not lifecycle.cancellable("stopped")
