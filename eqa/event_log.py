"""The event log of an episode: compact JSON summaries of bus messages, and each service's journal of what it
published.

:func:`summarize` is what the gateway stores in an episode's event stream (``gw:ev:{episode_id}``) and sends as
Server-Sent Events: no image or map arrays, only the fields a client follows an episode by.

**Journals** (no event depends on the gateway being up). Every service appends the summary of each message it
publishes for an episode to its own journal, :func:`eqa.store.episode_journal_key` (``eqa:journal:{service}:
{episode_id}``, a stream), *before* it publishes the message (:meth:`eqa.service.Service.publish`). So each key
has one writer: a service writes its journal, the gateway alone writes the episode's event stream. A gateway
that was down (killed, restarted) backfills the events it did not see from the journals when it comes back
(:func:`missing_events`): an event whose identity (:func:`event_identity`: kind, step, source) is not in the
stored stream yet is appended, marked ``backfilled``; one that then also arrives live is not stored twice.
Journals expire with the services' episode state (:data:`eqa.store.EPISODE_STATE_TTL_S`, on Redis) and are
deleted with the episode by the gateway's retention.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterable
from typing import Any

from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    ErrorReply,
    Frame,
    Goal,
    MapUpdate,
    Message,
    Pose2D,
    StepScores,
)
from eqa.task_traces import kind_of_metrics, task_outcome

MAX_FRONTIERS = 8  # frontiers listed in a map_update summary (the highest weights)
MAX_TEXT = 2000  # characters of a reason kept in an event


def _r(value: float, nd: int = 4) -> float | None:
    v = float(value)
    return round(v, nd) if math.isfinite(v) else None


def _pose(p: Pose2D | None) -> dict[str, float | None] | None:
    return None if p is None else {"x": _r(p.x, 3), "y": _r(p.y, 3), "yaw": _r(p.yaw, 3)}


def _frame(msg: Frame) -> dict[str, Any]:
    out = {"step": msg.step, "pose": _pose(msg.pose), "scene": msg.scene, "image": list(msg.rgb.shape[:2]),
           "visible": sorted({lab.category for lab in msg.labels})[:32]}
    if msg.skill is not None:  # a task skill's outcome
        out["skill"] = msg.skill.model_dump(mode="json")
    return out


def _map_update(msg: MapUpdate) -> dict[str, Any]:
    best = sorted(msg.frontiers, key=lambda f: -f.weight)[:MAX_FRONTIERS]
    return {
        "step": msg.step,
        "pose": _pose(msg.pose),
        "grid": msg.grid.model_dump(),
        "explored_area_m2": _r(msg.explored_area_m2, 2),
        "frontiers": len(msg.frontiers),
        "top_frontiers": [{"x": _r(f.x, 2), "y": _r(f.y, 2), "weight": _r(f.weight)} for f in best],
        "prompt_points": [p.label for p in msg.prompt_points],
        "layers": sorted(msg.values),
        "timing_ms": {k: _r(v, 1) for k, v in msg.timing_ms.items()},
    }


def _step_scores(msg: StepScores) -> dict[str, Any]:
    return {"step": msg.step, "answer_probs": [_r(p) for p in msg.answer_probs], "relevance": _r(msg.relevance),
            "gsv": _r(msg.gsv), "backend": msg.backend}


def _decision(msg: Decision) -> dict[str, Any]:
    # a warm start's calibration (Decision.warm_calibrated) only where there is one: cold episodes' events unchanged
    warm = {} if msg.warm_calibrated is None else {"warm_calibrated": msg.warm_calibrated}
    return {
        **warm,
        "step": msg.step,
        "rule": msg.rule,
        "stop": msg.stop,
        "reason": msg.reason,
        "prediction_set": msg.prediction_set,
        "step_set": msg.step_set,
        "scores": {k: _r(v) for k, v in msg.scores.items()},
        "answer": msg.answer,
        "q_hat": None if msg.q_hat is None else _r(msg.q_hat),
    }


def _goal(msg: Goal) -> dict[str, Any]:
    f = msg.frontier
    return {
        "step": msg.step,
        "pose": _pose(msg.pose),
        "done": msg.done,
        "reason": msg.reason,
        "path_len": len(msg.path),
        "skill": msg.skill,
        "target": msg.target,
        "phase": msg.phase,
        "numbers": {k: _r(v) for k, v in msg.numbers.items()},
        "frontier": None if f is None else {"x": _r(f.x, 2), "y": _r(f.y, 2), "weight": _r(f.weight)},
    }


def _error(msg: ErrorReply) -> dict[str, Any]:
    return {"step": msg.step, "source": msg.source, "reason": msg.reason}


def _episode_end(msg: EpisodeEnd) -> dict[str, Any]:
    out = {
        "robot": msg.robot,
        "state": msg.state,
        "reason": msg.reason,
        "answer": msg.answer,
        "answer_text": msg.answer_text,
        "prediction_set": msg.prediction_set,
        "steps": msg.steps,
        "max_steps": msg.max_steps,
        "normalized_steps": _r(msg.normalized_steps),
        "correct": msg.correct,
    }
    if msg.metrics:  # a task episode's phase metrics and what they mean
        out["metrics"] = {k: _r(v) for k, v in msg.metrics.items()}
        out["outcome"] = task_outcome(kind_of_metrics(msg.metrics), msg.metrics, msg.state, msg.reason, msg.steps,
                                      msg.max_steps)
    return out


def _episode_start(msg: EpisodeStart) -> dict[str, Any]:
    q = msg.question
    return {"robot": msg.robot, "question": q.text, "choices": q.choices, "scene": q.scene, "strategy": msg.strategy,
            "stop": msg.stop.model_dump(), "max_steps": msg.max_steps, "seed": msg.seed}


def _episode_cancel(msg: EpisodeCancel) -> dict[str, Any]:
    return {"reason": msg.reason}


# The key fields of each message kind an event shows (in this order after ``kind`` and ``episode_id``).
SUMMARIES: dict[type[Message], Callable[[Any], dict[str, Any]]] = {
    Frame: _frame,
    MapUpdate: _map_update,
    StepScores: _step_scores,
    Decision: _decision,
    Goal: _goal,
    ErrorReply: _error,
    EpisodeEnd: _episode_end,
    EpisodeStart: _episode_start,
    EpisodeCancel: _episode_cancel,
}


def summarize(msg: Message) -> dict[str, Any]:
    """A JSON-safe dict with ``kind``, ``episode_id``, ``step`` (when the message has one) and key fields."""
    out: dict[str, Any] = {"kind": msg.kind, "episode_id": getattr(msg, "episode_id", None)}
    fields = next((f for cls, f in SUMMARIES.items() if isinstance(msg, cls)), None)
    if fields is not None:
        out.update(fields(msg))
    for name in ("reason", "question"):  # texts a bus peer controls: bounded in the stored event
        if isinstance(out.get(name), str) and len(out[name]) > MAX_TEXT:
            out[name] = out[name][:MAX_TEXT] + "..."
    out["t"] = round(time.time(), 3)
    return out


JOURNAL_SERVICES = ("sim", "mapper", "planner", "stopper")  # the services that publish on robot streams
NOT_BACKFILLED = frozenset({"episode_end"})  # the gateway recovers the end from the stopper's stored copy
Identity = tuple[str, int | None, str | None]


def encode_event(event: dict[str, Any]) -> bytes:
    return json.dumps(event, separators=(",", ":")).encode()


def event_identity(event: dict[str, Any]) -> Identity:
    """What makes two events the same: kind, step, and the source of an error (a resent step's outputs are
    the same events again)."""
    step = event.get("step")
    return (str(event.get("kind")), step if isinstance(step, int) else None,
            str(event["source"]) if event.get("kind") == "error" and "source" in event else None)


def missing_events(stored: Iterable[dict[str, Any]], journals: Iterable[Iterable[dict[str, Any]]]
                   ) -> list[dict[str, Any]]:
    """The journal events whose identity is not among ``stored`` (each once), oldest first by their time
    ``t``, marked ``backfilled``; episode ends excepted (:data:`NOT_BACKFILLED`). Pure."""
    have = {event_identity(e) for e in stored}
    out: list[dict[str, Any]] = []
    for journal in journals:
        for event in journal:
            ident = event_identity(event)
            if ident in have or ident[0] in NOT_BACKFILLED:
                continue
            have.add(ident)
            out.append({**event, "backfilled": True})
    out.sort(key=lambda e: float(e.get("t", 0.0)) if isinstance(e.get("t"), int | float) else 0.0)
    return out
