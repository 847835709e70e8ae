"""Liveliness checks used by ``eqa health`` and the compose health checks."""

from __future__ import annotations

from eqa import keys
from eqa.bus import Bus
from eqa.settings import Settings


def alive_services(settings: Settings, timeout: float = 2.0) -> dict[str, list[str]]:
    """``service -> [instances]`` of every liveliness token reachable from these settings."""
    out: dict[str, list[str]] = {}
    with Bus(settings.model_copy(update={"instance": "health-check"}), "health") as bus:
        for service, instance in bus.alive(keys.ALIVE_ANY, timeout=timeout):
            out.setdefault(service, []).append(instance)
    return out


def check(settings: Settings, services: list[str], timeout: float = 2.0) -> list[str]:
    """The services of ``services`` with no live instance (empty = healthy)."""
    alive = alive_services(settings, timeout)
    return [s for s in services if not alive.get(s)]
