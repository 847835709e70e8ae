"""The data flow of the system, declared once: every stream of a robot with its message type, the one process
that publishes it and the processes that consume it; the scorer query; the process lists.

Derived from this: the launcher's process lists (:mod:`eqa.launcher`), the gateway's list of services an
episode needs, the stream table of docs/architecture.md (:func:`stream_table`). Checked against this
(``tests/kernel/test_dataflow.py``): :data:`eqa.messages.STREAM_TYPES`, :data:`eqa.keys.SERVICES`, the ACL's stream
owners (:mod:`eqa.security`), the compose file, and the code itself (which stream each service subscribes to
and publishes on, read from its source).

A stream is ``eqa/v1/{robot}/{service}/{stream}`` (:func:`eqa.keys.stream`); the gateway also observes every
stream of its robots for the episode event log (:func:`eqa.keys.robot_streams`).
"""

from __future__ import annotations

from dataclasses import dataclass

from eqa import keys
from eqa.messages import (
    Decision,
    DetectRequest,
    DetectResult,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    ErrorReply,
    Frame,
    Goal,
    MapUpdate,
    Message,
    ScoreRequest,
    ScoreResult,
    StepScores,
    ValueRequest,
    ValueResult,
)

GATEWAY = "gateway"
PIPELINE = ("sim", "mapper", "vlm_scorer", "planner", "stopper")
"""The services an episode needs (``eqa up --no-gateway``, the benchmark runner, the gateway's watchdog)."""
SERVICES = (*PIPELINE, GATEWAY)
"""Every process kind of the fleet (one liveliness service name each)."""
STATEFUL = ("sim", "mapper", "planner", "stopper")
"""Services with per-episode state (sharded by robot when several instances run)."""
_EPISODE = ("sim", "mapper", "planner", "stopper")
STANDS_IN: dict[str, str] = {"ros2_bridge": "sim"}
"""Processes that take a service's place for some robots and keep its contract: they consume and publish exactly
the streams of the one they stand in for (``ros2_bridge``: a ROS 2 robot in the sim's place for the robots of
``EQA_ROS2_ROBOTS``; docs/robots.md). The gateway counts one alive as the service."""


@dataclass(frozen=True)
class Stream:
    pair: tuple[str, str]
    types: tuple[type[Message], ...]
    producer: str
    consumers: tuple[str, ...]
    what: str

    @property
    def key(self) -> str:
        return "eqa/v1/{robot}/" + "/".join(self.pair)


@dataclass(frozen=True)
class Query:
    selector: str
    request: type[Message]
    reply: type[Message]
    server: str
    clients: tuple[str, ...]
    what: str


STREAMS: tuple[Stream, ...] = (
    Stream(keys.EPISODE_START, (EpisodeStart,), GATEWAY, _EPISODE, "a question starts on a robot"),
    Stream(keys.EPISODE_CANCEL, (EpisodeCancel,), GATEWAY, _EPISODE, "a user cancels an episode"),
    Stream(keys.EPISODE_END, (EpisodeEnd,), "stopper", _EPISODE, "the answer, or why there is none"),
    Stream(keys.SIM_FRAME, (Frame,), "sim", ("mapper",), "RGB-D view and pose of step t"),
    Stream(keys.SIM_ERROR, (ErrorReply,), "sim", ("planner",), "a start or goal the simulator refuses"),
    Stream(keys.MAPPER_MAP, (MapUpdate,), "mapper", ("planner",), "2D maps, frontiers with Eq. A6 weights"),
    Stream(keys.MAPPER_SCORES, (StepScores,), "mapper", ("stopper",), "answer distribution and relevance"),
    Stream(keys.MAPPER_ERROR, (ErrorReply,), "mapper", (), "a frame or score the mapper could not use"),
    Stream(keys.STOPPER_DECISION, (Decision,), "stopper", ("planner",), "stop or go on (Eq. 7-10)"),
    Stream(keys.PLANNER_GOAL, (Goal,), "planner", ("sim", "stopper"), "next pose of step t+1, or done"),
)

QUERIES: tuple[Query, ...] = (
    Query(keys.SCORER_ANY, ScoreRequest, ScoreResult, "vlm_scorer", ("mapper",),
          "the four VLM queries of a step (Eq. 1, 2, 5), to any replica"),
    Query(keys.SCORER_ANY, DetectRequest, DetectResult, "vlm_scorer", ("mapper",),
          "HELIOS: open-vocabulary detections of a task episode's frame (same replicas)"),
    Query(keys.SCORER_ANY, ValueRequest, ValueResult, "vlm_scorer", ("mapper",),
          'HELIOS 3.1.2: "Seems like there is a (object) ahead" per task class (same replicas)'),
)

STREAM_TYPES: dict[tuple[str, str], tuple[type[Message], ...]] = {s.pair: s.types for s in STREAMS}
PRODUCERS: dict[tuple[str, str], str] = {s.pair: s.producer for s in STREAMS}


def produced_by(service: str) -> set[tuple[str, str]]:
    return {s.pair for s in STREAMS if s.producer == service}


def consumed_by(service: str) -> set[tuple[str, str]]:
    return {s.pair for s in STREAMS if service in s.consumers}


def stream_table() -> str:
    """The table of streams (``tests/kernel/test_dataflow.py`` checks that docs/architecture.md holds it verbatim)."""
    rows = ["| stream (`eqa/v1/{robot}/...`) | message | published by | consumed by | what |", "|---|---|---|---|---|"]
    for s in STREAMS:
        types = ", ".join(t.__name__ for t in s.types)
        consumers = ", ".join(s.consumers) or "(gateway event log only)"
        rows.append(f"| `{'/'.join(s.pair)}` | `{types}` | {s.producer} | {consumers} | {s.what} |")
    for q in QUERIES:
        rows.append(f"| `{q.selector}` (query) | `{q.request.__name__}` -> `{q.reply.__name__}` | "
                    f"{', '.join(q.clients)} asks | {q.server} answers | {q.what} |")
    return "\n".join(rows)
