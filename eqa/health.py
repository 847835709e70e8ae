"""Liveliness checks used by ``eqa health`` and the compose health checks."""

from __future__ import annotations

import time

from eqa import keys
from eqa.bus import Bus
from eqa.settings import Settings

RETRY_S = 0.2


def check_settings(settings: Settings) -> Settings:
    """The session of a check. With connect endpoints it is a Zenoh *client* of them: the router it reaches
    already holds every service's liveliness token and answers the first query with all of them once the one
    link is up. A *peer* sees a token only after it has linked to the peer holding it (through the router's
    gossip) and received its declarations, one handshake per peer, each needing that peer's process to be
    scheduled; on a loaded machine one slow peer then reads as dead for as long as its handshake takes, and the
    session's close waits for the handshake in flight. Without endpoints (multicast scouting) it stays a peer:
    it has no router to ask."""
    update: dict[str, object] = {"instance": "health-check"}
    if settings.zenoh_connect:
        update.update(zenoh_mode="client", zenoh_listen=[])
    return settings.model_copy(update=update)


def check(settings: Settings, services: list[str], timeout: float = 5.0) -> list[str]:
    """The services of ``services`` with no live instance (empty = healthy). The liveliness query is repeated
    until all are seen or ``timeout`` passes: a service may be starting, and a peer session (no connect
    endpoints) learns of the others one link at a time."""
    deadline = time.monotonic() + timeout
    with Bus(check_settings(settings), "health") as bus:
        while True:
            remaining = deadline - time.monotonic()
            alive = {service for service, _ in bus.alive(keys.ALIVE_ANY, timeout=max(0.1, min(1.0, remaining)))}
            missing = [s for s in services if s not in alive]
            if not missing or time.monotonic() >= deadline:
                return missing
            time.sleep(RETRY_S)
