"""Liveliness checks used by ``eqa health`` and the compose health checks."""

from __future__ import annotations

import time

from eqa import keys
from eqa.bus import Bus
from eqa.settings import Settings

RETRY_S = 0.2


def check(settings: Settings, services: list[str], timeout: float = 5.0) -> list[str]:
    """The services of ``services`` with no live instance (empty = healthy). A session just opened has not
    heard of every peer yet, so the liveliness query is repeated until all are seen or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    with Bus(settings.model_copy(update={"instance": "health-check"}), "health") as bus:
        while True:
            remaining = deadline - time.monotonic()
            alive = {service for service, _ in bus.alive(keys.ALIVE_ANY, timeout=max(0.1, min(1.0, remaining)))}
            missing = [s for s in services if s not in alive]
            if not missing or time.monotonic() >= deadline:
                return missing
            time.sleep(RETRY_S)
