"""Compact JSON summaries of bus messages: what the gateway stores in an episode's event stream and sends
as Server-Sent Events. No image or map arrays, only the fields a client follows an episode by."""

from __future__ import annotations

import math
import time
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


def summarize(msg: Message) -> dict[str, Any]:
    """A JSON-safe dict with ``kind``, ``episode_id``, ``step`` (when the message has one) and key fields."""
    out: dict[str, Any] = {"kind": msg.kind, "episode_id": getattr(msg, "episode_id", None)}
    if isinstance(msg, Frame):
        out.update(
            step=msg.step,
            pose=_pose(msg.pose),
            scene=msg.scene,
            image=list(msg.rgb.shape[:2]),
            visible=sorted({lab.category for lab in msg.labels})[:32],
        )
        if msg.skill is not None:  # a task skill's outcome (issue 17)
            out["skill"] = msg.skill.model_dump(mode="json")
    elif isinstance(msg, MapUpdate):
        best = sorted(msg.frontiers, key=lambda f: -f.weight)[:MAX_FRONTIERS]
        out.update(
            step=msg.step,
            pose=_pose(msg.pose),
            grid=msg.grid.model_dump(),
            explored_area_m2=_r(msg.explored_area_m2, 2),
            frontiers=len(msg.frontiers),
            top_frontiers=[{"x": _r(f.x, 2), "y": _r(f.y, 2), "weight": _r(f.weight)} for f in best],
            prompt_points=[p.label for p in msg.prompt_points],
            layers=sorted(msg.values),
            timing_ms={k: _r(v, 1) for k, v in msg.timing_ms.items()},
        )
    elif isinstance(msg, StepScores):
        out.update(
            step=msg.step,
            answer_probs=[_r(p) for p in msg.answer_probs],
            relevance=_r(msg.relevance),
            gsv=_r(msg.gsv),
            backend=msg.backend,
        )
    elif isinstance(msg, Decision):
        out.update(
            step=msg.step,
            rule=msg.rule,
            stop=msg.stop,
            reason=msg.reason,
            prediction_set=msg.prediction_set,
            step_set=msg.step_set,
            scores={k: _r(v) for k, v in msg.scores.items()},
            answer=msg.answer,
            q_hat=None if msg.q_hat is None else _r(msg.q_hat),
        )
    elif isinstance(msg, Goal):
        out.update(
            step=msg.step,
            pose=_pose(msg.pose),
            done=msg.done,
            reason=msg.reason,
            path_len=len(msg.path),
            skill=msg.skill,
            target=msg.target,
            phase=msg.phase,
            numbers={k: _r(v) for k, v in msg.numbers.items()},
            frontier=None
            if msg.frontier is None
            else {"x": _r(msg.frontier.x, 2), "y": _r(msg.frontier.y, 2), "weight": _r(msg.frontier.weight)},
        )
    elif isinstance(msg, ErrorReply):
        out.update(step=msg.step, source=msg.source, reason=msg.reason)
    elif isinstance(msg, EpisodeEnd):
        out.update(
            robot=msg.robot,
            state=msg.state,
            reason=msg.reason,
            answer=msg.answer,
            answer_text=msg.answer_text,
            prediction_set=msg.prediction_set,
            steps=msg.steps,
            max_steps=msg.max_steps,
            normalized_steps=_r(msg.normalized_steps),
            correct=msg.correct,
        )
        if msg.metrics:  # a task episode's phase metrics (issue 17) and what they mean
            out["metrics"] = {k: _r(v) for k, v in msg.metrics.items()}
            out["outcome"] = task_outcome(kind_of_metrics(msg.metrics), msg.metrics, msg.state, msg.reason,
                                          msg.steps, msg.max_steps)
    elif isinstance(msg, EpisodeStart):
        out.update(
            robot=msg.robot,
            question=msg.question.text,
            choices=msg.question.choices,
            scene=msg.question.scene,
            strategy=msg.strategy,
            stop=msg.stop.model_dump(),
            max_steps=msg.max_steps,
            seed=msg.seed,
        )
    elif isinstance(msg, EpisodeCancel):
        out.update(reason=msg.reason)
    for name in ("reason", "question"):  # texts a bus peer controls: bounded in the stored event
        if isinstance(out.get(name), str) and len(out[name]) > MAX_TEXT:
            out[name] = out[name][:MAX_TEXT] + "..."
    out["t"] = round(time.time(), 3)
    return out


def gateway_event(kind: str, episode_id: str, **fields: Any) -> dict[str, Any]:
    """An event the gateway itself emits (queued, started, failed by the watchdog, gateway restart)."""
    return {"kind": kind, "episode_id": episode_id, **fields, "t": round(time.time(), 3)}
