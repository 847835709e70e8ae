"""The gateway's own events (queued, started, failed by the watchdog, gateway restart); the summaries of bus
messages are :func:`eqa.event_log.summarize` (the services journal the same summaries)."""

from __future__ import annotations

import time
from typing import Any

from eqa.event_log import MAX_FRONTIERS, MAX_TEXT, summarize

__all__ = ["MAX_FRONTIERS", "MAX_TEXT", "gateway_event", "summarize"]


def gateway_event(kind: str, episode_id: str, **fields: Any) -> dict[str, Any]:
    """An event the gateway itself emits (queued, started, failed by the watchdog, gateway restart)."""
    return {"kind": kind, "episode_id": episode_id, **fields, "t": round(time.time(), 3)}
