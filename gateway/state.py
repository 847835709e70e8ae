"""The episode state machine of the gateway as pure functions: a status and an input in, the next status and
what the shell must do out. No store, no bus, no clock (``now`` is an argument), no lock.

States (``EpisodeState``)::

    queued --start--> running --EpisodeEnd (stopper)--> stopped | failed | cancelled
       |                 |--sim refuses step 0 (ErrorReply)--> failed   (services told to drop it)
       |                 |--no message for the timeout---------> failed   (services told to drop it)
       +--cancel---------+--cancel-----------------------------> cancelled

:class:`gateway.manager.EpisodeManager` is the I/O shell: it persists what these functions return, appends
the events to the episode's stream, publishes on the bus and moves the robot's queue on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from eqa import dataflow
from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    EpisodeStatus,
    ErrorReply,
    Frame,
    Message,
)
from eqa.task_traces import TraceError, task_outcome
from gateway.events import gateway_event

TERMINAL = frozenset({"stopped", "failed", "cancelled"})
ACTIVE = frozenset({"queued", "running"})


@dataclass(frozen=True)
class Ending:
    """An episode ends: its final ``state`` and ``reason``; ``end`` is the stopper's message when it came from
    the stopper; ``tell_services``: publish ``EpisodeCancel`` (an end decided by the gateway while running)."""

    state: str
    reason: str
    end: EpisodeEnd | None = None
    tell_services: bool = False


@dataclass
class Transition:
    """What one bus message does to an episode. ``ignore``: not this episode's business (nothing changes)."""

    ignore: bool = False
    status: EpisodeStatus | None = None  # the next status (to save) when the episode goes on
    ending: Ending | None = None
    last_error: str | None = None
    notes: list[str] = field(default_factory=list)


def on_message(st: EpisodeStatus, robot: str, msg: Message, now: float) -> Transition:
    """The next state of episode ``st`` after a message of ``robot``'s streams.

    The stopper's ``EpisodeEnd`` ends it; a sim ``ErrorReply`` before any frame ends it as failed (the sim
    refused the episode: a robot is never held by a bad request); any other message advances ``step``,
    ``steps`` (frames seen), the running prediction set and answer."""
    if isinstance(msg, EpisodeStart | EpisodeCancel) or st.state != "running":
        return Transition(ignore=True)
    if st.robot != robot:
        return Transition(ignore=True, notes=[f"episode {st.episode_id} runs on {st.robot}, not {robot}"])
    if isinstance(msg, EpisodeEnd):
        state = msg.state if msg.state in TERMINAL else "stopped"
        return Transition(ending=Ending(state, msg.reason, end=msg))
    nxt = st.model_copy(deep=True)
    nxt.updated_at = now
    out = Transition(status=nxt)
    if isinstance(msg, ErrorReply):
        out.last_error = f"{msg.source} at step {msg.step}: {msg.reason}"
        robot_side = "sim" if msg.source.startswith("sim") else msg.source
        if dataflow.STANDS_IN.get(robot_side, robot_side) == "sim" and st.steps == 0:
            out.ending = Ending("failed", f"{robot_side} refused the episode: {msg.reason}", tell_services=True)
            return out
    step = getattr(msg, "step", None)
    if isinstance(step, int):
        nxt.step = max(nxt.step, step)
    if isinstance(msg, Frame):
        nxt.steps = max(nxt.steps, msg.step + 1)
    elif isinstance(msg, Decision):
        nxt.prediction_set = list(msg.prediction_set)
        nxt.answer = msg.answer or nxt.answer
    nxt.normalized_steps = nxt.steps / max(nxt.max_steps, 1)
    return out


def started(st: EpisodeStatus, now: float) -> EpisodeStatus:
    """``queued`` -> ``running``."""
    return st.model_copy(update={"state": "running", "updated_at": now})


def finished(
    st: EpisodeStatus, state: str, reason: str, now: float, end: EpisodeEnd | None = None, recording: bool = False,
    trace: dict[str, Any] | None = None,
) -> EpisodeStatus:
    """The final status: the stopper's answer, set and steps when ``end`` is given; the answer's text from the
    choices; ``correct`` against a known ground truth; the recording link when there is a recording; a task's
    outcome (:func:`eqa.task_traces.task_outcome`, with the phase and step of its first failure when the sim's
    ``trace`` is given)."""
    nxt = st.model_copy(deep=True)
    nxt.state = state  # type: ignore[assignment]
    nxt.updated_at = now
    nxt.stop_reason = reason
    if end is not None:
        nxt.answer = end.answer
        nxt.answer_text = end.answer_text
        nxt.prediction_set = list(end.prediction_set)
        nxt.steps = end.steps
        nxt.correct = end.correct
        nxt.metrics = dict(end.metrics)
    nxt.normalized_steps = nxt.steps / max(nxt.max_steps, 1)
    choices = nxt.question.choices
    if nxt.answer and nxt.answer_text is None and choices and "A" <= nxt.answer <= "Z":
        idx = ord(nxt.answer) - ord("A")
        nxt.answer_text = choices[idx] if idx < len(choices) else None
    if nxt.correct is None and nxt.answer and nxt.question.answer:
        nxt.correct = nxt.answer == nxt.question.answer
    if recording:
        nxt.recording = f"/v1/episodes/{nxt.episode_id}/recording"
    if nxt.task is not None:
        try:
            nxt.outcome = task_outcome(nxt.task.kind, nxt.metrics, nxt.state, reason, nxt.steps, nxt.max_steps, trace)
        except TraceError:
            nxt.outcome = task_outcome(nxt.task.kind, nxt.metrics, nxt.state, reason, nxt.steps, nxt.max_steps)
    return nxt


def end_event(st: EpisodeStatus) -> dict[str, Any]:
    """The ``episode_end`` event the gateway writes when it ends an episode itself (no stopper's end)."""
    return gateway_event(
        "episode_end",
        st.episode_id,
        robot=st.robot,
        state=st.state,
        reason=st.stop_reason,
        answer=st.answer,
        prediction_set=st.prediction_set,
        steps=st.steps,
        max_steps=st.max_steps,
        normalized_steps=round(st.normalized_steps, 4),
        correct=st.correct,
        source="gateway",
        **({"outcome": st.outcome} if st.outcome is not None else {}),
    )


def timeout_reason(
    st: EpisodeStatus, timeout_s: float, missing: list[str], last_error: str | None, restarted: bool
) -> str:
    """Why the watchdog failed a running episode: how long nothing came, which services are not alive, the
    episode's last error, and whether the gateway restarted meanwhile."""
    reason = (
        f"no message for {timeout_s:g} s (last step {st.step}); services not alive: "
        f"{', '.join(missing) if missing else 'none, all alive'}"
    )
    if last_error:
        reason += f"; last error: {last_error}"
    if restarted:
        reason += "; the gateway restarted meanwhile, so the end may have been published while it was down"
    return reason


def timed_out(state: str, last_activity: float, started_at: float, now: float, timeout_s: float) -> bool:
    return state == "running" and now - max(last_activity, started_at) > timeout_s


def cancellable(state: str) -> bool:
    return state in ACTIVE
