"""Every Zenoh key expression of the system, in one place.

Streams of one robot live under ``eqa/v1/{robot}/{service}/{stream}``; scorer replicas answer queries on
``eqa/v1/scorer/{replica}/score``; each running service process holds a liveliness token
``eqa/v1/alive/{service}/{instance}/{session}`` (``session`` is its Zenoh session id, so that a process
restarted under a live instance name holds a token of its own: Zenoh keeps one token per key expression, and a
shared key would hide the new process from watchers). Identifiers are restricted to ``[A-Za-z0-9_-]`` so that
no caller can smuggle wildcards (``*``, ``**``), separators or ``@`` chunks into a data key.
"""

from __future__ import annotations

import re

ROOT = "eqa/v1"
_ID = re.compile(r"[A-Za-z0-9_-]{1,64}")

SERVICES = ("sim", "mapper", "vlm_scorer", "planner", "stopper", "gateway")

# (service, stream) pairs of one robot. The message type of each is in ``eqa.messages.STREAM_TYPES``.
EPISODE_START = ("episode", "start")
EPISODE_CANCEL = ("episode", "cancel")
EPISODE_END = ("episode", "end")
SIM_FRAME = ("sim", "frame")
SIM_ERROR = ("sim", "error")
MAPPER_MAP = ("mapper", "map")
MAPPER_SCORES = ("mapper", "scores")
MAPPER_ERROR = ("mapper", "error")
STOPPER_DECISION = ("stopper", "decision")
PLANNER_GOAL = ("planner", "goal")


def check_id(value: str, what: str = "id") -> str:
    """Return ``value`` if it is a safe key chunk, else raise ``ValueError`` naming the rule."""
    if not isinstance(value, str) or not _ID.fullmatch(value):  # fullmatch: "$" would pass a trailing newline
        raise ValueError(f"{what} {value!r} must be 1-64 characters of letters, digits, '_' or '-'")
    return value


def stream(robot: str, pair: tuple[str, str]) -> str:
    """Key of one stream of one robot, e.g. ``stream("r0", SIM_FRAME) == "eqa/v1/r0/sim/frame"``."""
    service, name = pair
    return f"{ROOT}/{check_id(robot, 'robot')}/{service}/{name}"


def robot_streams(robot: str) -> str:
    """Selector for every stream of one robot (what the gateway records)."""
    return f"{ROOT}/{check_id(robot, 'robot')}/**"


def any_robot(pair: tuple[str, str]) -> str:
    """Selector for one stream over all robots (a service serves every robot)."""
    service, name = pair
    return f"{ROOT}/*/{service}/{name}"


def robot_of(key: str) -> str:
    """The robot id inside a stream key."""
    parts = str(key).split("/")
    if len(parts) < 5 or f"{parts[0]}/{parts[1]}" != ROOT:
        raise ValueError(f"not a robot stream key: {key!r}")
    return parts[2]


def scorer_replica(replica: str) -> str:
    return f"{ROOT}/scorer/{check_id(replica, 'replica')}/score"


SCORER_ANY = f"{ROOT}/scorer/*/score"


_SESSION = re.compile(r"[0-9a-f]{1,32}")


def alive(service: str, instance: str, session: str) -> str:
    """The liveliness key of one process: ``session`` is its Zenoh session id in hex."""
    if not isinstance(session, str) or not _SESSION.fullmatch(session):
        raise ValueError(f"session must be a Zenoh session id (1-32 lowercase hex digits), got {session!r}")
    return f"{ROOT}/alive/{check_id(service, 'service')}/{check_id(instance, 'instance')}/{session}"


ALIVE_ANY = f"{ROOT}/alive/**"


def alive_service(service: str) -> str:
    return f"{ROOT}/alive/{check_id(service, 'service')}/*/*"


def parse_alive(key: str) -> tuple[str, str, str]:
    """``(service, instance, session)`` of a liveliness key."""
    parts = str(key).split("/")
    if len(parts) != 6 or parts[2] != "alive":
        raise ValueError(f"not a liveliness key: {key!r}")
    return parts[3], parts[4], parts[5]


def replica_of(key: str) -> str:
    parts = str(key).split("/")
    if len(parts) != 5 or parts[2] != "scorer":
        raise ValueError(f"not a scorer key: {key!r}")
    return parts[3]
