"""Client of the scorer replica pool.

``ScorerClient(bus, settings).score(request)`` sends one :class:`~eqa.messages.ScoreRequest` to one live
scorer replica and returns its :class:`~eqa.messages.ScoreResult`; ``detect`` (a
:class:`~eqa.messages.DetectRequest`, HELIOS detections) and ``values`` (a :class:`~eqa.messages.ValueRequest`,
the per-target value prompt) go through the same pool with the same balancing, failover and errors.

* Discovery: a liveliness subscriber on ``eqa/v1/alive/vlm_scorer/*/*`` keeps the set of live replicas (a
  replica's liveliness instance is its replica id; see ``services/vlm_scorer/service.py``).
* Balancing: each request goes to the live replica with the fewest requests in flight from this client
  (ties broken round-robin).
* Failover: when the chosen replica gives no answer within ``scorer_timeout_s`` (it died, was killed, or is
  overloaded) the request is sent to another live replica, up to ``retries`` more attempts; replicas that
  failed this request are tried last. When no replica is live the client waits for one up to
  ``scorer_timeout_s`` before giving up. Giving up raises :class:`ScorerUnavailable`.
* An :class:`~eqa.messages.ErrorReply` means the request itself was refused (bad input, backend not
  loadable): :class:`ScorerError` is raised at once, without retry.

Thread-safe: several threads may call :meth:`ScorerClient.score` at once.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time

from eqa import keys, metrics
from eqa.bus import Bus
from eqa.messages import (
    DetectRequest,
    DetectResult,
    ErrorReply,
    Message,
    ScoreRequest,
    ScoreResult,
    ValueRequest,
    ValueResult,
)
from eqa.settings import ScorerSettings

log = logging.getLogger(__name__)

SERVICE = "vlm_scorer"


class ScorerUnavailable(RuntimeError):  # noqa: N818 - name fixed by the interface
    """No scorer replica answered within the timeout and retries."""


class ScorerError(RuntimeError):
    """A replica refused the request (the reason is the replica's ErrorReply)."""

    def __init__(self, reply: ErrorReply) -> None:
        super().__init__(reply.reason)
        self.reply = reply


class ScorerClient:
    def __init__(
        self, bus: Bus, settings: ScorerSettings, retries: int = 3, timeout_s: float | None = None
    ) -> None:
        self.bus = bus
        self.timeout_s = float(timeout_s if timeout_s is not None else settings.scorer_timeout_s)
        self.retries = int(retries)
        self._lock = threading.Condition()
        self._live: set[str] = set()
        self._inflight: dict[str, int] = {}
        self._rr = itertools.count()
        self.stats = {"requests": 0, "answers": 0, "failovers": 0, "errors": 0}
        bus.watch_alive(keys.alive_service(SERVICE), self._on_alive)

    # ---- discovery ------------------------------------------------------------------------------------
    def _on_alive(self, service: str, instance: str, alive: bool) -> None:
        if service != SERVICE:
            return
        with self._lock:
            if alive:
                self._live.add(instance)
            else:
                self._live.discard(instance)
            self._lock.notify_all()
        log.info("scorer replica %s %s", instance, "up" if alive else "gone")

    def replicas(self) -> list[str]:
        with self._lock:
            return sorted(self._live)

    def wait_for_replicas(self, n: int = 1, timeout: float = 10.0) -> bool:
        """Block until at least ``n`` replicas are live (tests, launchers)."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while len(self._live) < n:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(left)
            return True

    def _pick(self, tried: set[str], deadline: float) -> str | None:
        with self._lock:
            while not self._live:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._lock.wait(min(left, 0.5))
            live = sorted(self._live)
            fresh = [r for r in live if r not in tried] or live
            turn = next(self._rr)
            best = min(fresh, key=lambda r: (self._inflight.get(r, 0), (live.index(r) - turn) % len(live)))
            self._inflight[best] = self._inflight.get(best, 0) + 1
            return best

    def _done(self, replica: str) -> None:
        with self._lock:
            self._inflight[replica] = max(0, self._inflight.get(replica, 0) - 1)

    # ---- scoring --------------------------------------------------------------------------------------
    def score(self, request: ScoreRequest) -> ScoreResult:
        """One replica's answer to ``request``; see the module docstring for failover and errors."""
        return self._ask(request, ScoreResult)  # type: ignore[return-value]

    def detect(self, request: DetectRequest) -> DetectResult:
        """Open-vocabulary detections of one frame (HELIOS object layer), same pool, failover and errors."""
        return self._ask(request, DetectResult)  # type: ignore[return-value]

    def values(self, request: ValueRequest) -> ValueResult:
        """The per-target value prompt "Seems like there is a (object) ahead" (HELIOS 3.1.2), same pool."""
        return self._ask(request, ValueResult)  # type: ignore[return-value]

    def _ask(self, request: ScoreRequest | DetectRequest | ValueRequest, expected: type[Message]) -> Message:
        if not metrics.enabled():
            return self._ask_pool(request, expected)
        service, kind, outcome = self.bus.service, request.kind, "unavailable"
        metrics.gauge_add(metrics.SCORER_INFLIGHT, service)
        t0 = time.perf_counter()
        try:
            reply = self._ask_pool(request, expected)
            outcome = "ok"
            return reply
        except ScorerError:
            outcome = "refused"
            raise
        finally:
            metrics.gauge_add(metrics.SCORER_INFLIGHT, service, amount=-1)
            metrics.observe(metrics.SCORER_SECONDS, time.perf_counter() - t0, service, kind, outcome)

    def _ask_pool(self, request: ScoreRequest | DetectRequest | ValueRequest, expected: type[Message]) -> Message:
        with self._lock:
            self.stats["requests"] += 1
        tried: set[str] = set()
        reasons: list[str] = []
        for attempt in range(self.retries + 1):
            replica = self._pick(tried, time.monotonic() + self.timeout_s)
            if replica is None:
                reasons.append("no live scorer replica")
                break
            tried.add(replica)
            try:
                replies = self.bus.query(keys.scorer_replica(replica), request, self.timeout_s, expected)
            except Exception as exc:
                replies = []
                reasons.append(f"{replica}: {type(exc).__name__}: {exc}")
            finally:
                self._done(replica)
            for key, reply in replies:
                if isinstance(reply, ErrorReply):
                    with self._lock:
                        self.stats["errors"] += 1
                    raise ScorerError(reply)
                if isinstance(reply, expected) and isinstance(reply, (ScoreResult, DetectResult, ValueResult)):
                    if not reply.replica:
                        reply.replica = keys.replica_of(key)
                    with self._lock:
                        self.stats["answers"] += 1
                    return reply
            if not replies:
                reasons.append(f"{replica}: no answer within {self.timeout_s:g}s")
            with self._lock:
                self.stats["failovers"] += 1
            metrics.inc(metrics.SCORER_FAILOVERS, self.bus.service)
            log.warning(
                "scorer replica %s gave no answer to %s (attempt %d); trying another",
                replica,
                request.request_id,
                attempt + 1,
            )
        raise ScorerUnavailable(
            f"no scorer replica answered request {request.request_id}: " + "; ".join(reasons[-4:])
        )
