"""In-process services for the tests that drive one over a real bus."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import TypeVar

from eqa.service import Service

S = TypeVar("S", bound=Service)


@contextlib.contextmanager
def serving(service: S, settle_s: float = 0.5) -> Iterator[S]:
    """``service`` started, given ``settle_s`` for its subscriptions to reach the other peers, and stopped on the
    way out (also when the test fails)."""
    service.start()
    try:
        time.sleep(settle_s)
        yield service
    finally:
        service.stop()
