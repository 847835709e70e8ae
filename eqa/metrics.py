"""Prometheus metrics of the kernel: one definition per metric, for every process (docs/metrics.md lists them).

The metrics live in prometheus-client's default registry and are defined here once, at import, so several
services in one process (the embedded tests run them in threads) share them and nothing is registered twice;
a ``service`` label tells them apart. Counting is off until :func:`enable` (or :func:`serve`) is called: the
hooks in the kernel (:func:`inc`, :func:`observe`, :func:`timer`, :func:`timed_store`) then cost one flag test,
so a process without a metrics port pays nothing measurable (eqa_app/benches/metrics.py).

* :func:`serve` starts the HTTP exposition of a service process on ``EQA_METRICS_PORT`` (0 = off) and
  ``EQA_METRICS_HOST``; :func:`exposition` gives the same text to the gateway's ``/metrics`` route.
* Step latency is a histogram per service and input (``eqa_step_seconds``); its ``_count`` is the number of
  steps the service computed.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

from prometheus_client import REGISTRY, Counter, Gauge, Histogram, generate_latest, start_http_server
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from eqa.settings import MonitoringSettings

log = logging.getLogger(__name__)

CONTENT_TYPE = CONTENT_TYPE_LATEST
# a step is tens of ms (sim, planner) to seconds (a VLM on CPU); a store call is sub-ms to a frozen Redis' timeout
STEP_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
STORE_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1.0, 3.0, 10.0)

STEP_SECONDS = Histogram(
    "eqa_step_seconds", "Time a service took to compute one step from one input (the count: steps computed)",
    ["service", "input"], buckets=STEP_BUCKETS)
RESENDS = Counter(
    "eqa_resends_total", "Steps sent again: the sim's frame after EQA_STEP_RESEND_S (how=frame), or a service "
    "answering a repeated step by re-publishing its stored output (how=answer_again)", ["service", "how"])
EPISODES_RESTORED = Counter(
    "eqa_episodes_restored_total", "Episodes a service took up from the store (after a restart or a robot move)",
    ["service"])
STEP_CLAIMS = Counter(
    "eqa_step_claims_total", "Step claims among the instances of a service: won (this instance computes it), "
    "again (its own claim, a resent step), lost (another live instance holds it)", ["service", "outcome"])
STEP_TAKEOVERS = Counter(
    "eqa_step_takeovers_total", "Steps claimed again because the instance holding the claim is gone", ["service"])
BUS_DROPPED = Counter(
    "eqa_bus_dropped_total", "Bus messages dropped, by reason (malformed, handler_error, unknown_episode, "
    "inbox_full, malformed_query, malformed_reply)", ["service", "reason"])
STORE_SECONDS = Histogram(
    "eqa_store_seconds", "Latency of one store call", ["backend", "op"], buckets=STORE_BUCKETS)
STORE_ERRORS = Counter(
    "eqa_store_errors_total", "Store calls that raised, by exception type", ["backend", "op", "error"])
SCORER_SECONDS = Histogram(
    "eqa_scorer_request_seconds", "A scorer-pool request as its client saw it (failovers included), by request "
    "kind and outcome (ok, refused, unavailable)", ["service", "kind", "outcome"], buckets=STEP_BUCKETS)
SCORER_FAILOVERS = Counter(
    "eqa_scorer_failovers_total", "Scorer requests sent to another replica after no answer in time", ["service"])
SCORER_INFLIGHT = Gauge(
    "eqa_scorer_inflight", "Scorer-pool requests this process is waiting on", ["service"])
REPLICA_SECONDS = Histogram(
    "eqa_scorer_replica_seconds", "Time a scorer replica took to answer one request (its model's time)",
    ["kind", "outcome"], buckets=STEP_BUCKETS)
QUEUE_DEPTH = Gauge(
    "eqa_queryable_queue_depth", "Queries waiting for a serial queryable's worker (a scorer replica's queue)",
    ["service"])
SERVICE_STARTED = Gauge(
    "eqa_service_started_seconds", "Unix time this service process started (changes() counts restarts)",
    ["service"])
CHILD_RESTARTS = Counter(
    "eqa_launcher_restarts_total", "Children the launcher restarted after they exited", ["service"])
STANDBY_PROMOTIONS = Counter(
    "eqa_launcher_standby_promotions_total", "Restarts done by promoting the service's warm standby", ["service"])
STANDBY_READY = Gauge(
    "eqa_launcher_standby_ready", "1 while the service has a warm standby ready to take a dead instance's place",
    ["service"])


class _State:
    on = False
    servers: ClassVar[dict[int, Any]] = {}
    lock = threading.Lock()


def enabled() -> bool:
    return _State.on


def enable(on: bool = True) -> None:
    """Count from now on (``on=False``: stop counting; what was counted stays)."""
    _State.on = on


_CHILDREN: dict[tuple[Any, tuple[str, ...]], Any] = {}


def child(metric: Any, labels: tuple[str, ...]) -> Any:
    """``metric.labels(*labels)``, looked up once (prometheus-client validates labels on every call). The label
    values of the kernel's metrics are names from code (services, kinds, reasons, operations, exception types),
    so the cache stays small."""
    found = _CHILDREN.get((metric, labels))
    if found is None:
        found = _CHILDREN[(metric, labels)] = metric.labels(*labels)
    return found


def inc(metric: Counter, *labels: str, amount: float = 1.0) -> None:
    """``metric.labels(*labels).inc(amount)`` when counting is on."""
    if _State.on:
        child(metric, labels).inc(amount)


def gauge_add(metric: Gauge, *labels: str, amount: float = 1.0) -> None:
    if _State.on:
        child(metric, labels).inc(amount)


def gauge_set(metric: Gauge, value: float, *labels: str) -> None:
    if _State.on:
        child(metric, labels).set(value)


def observe(metric: Histogram, value: float, *labels: str) -> None:
    if _State.on:
        child(metric, labels).observe(value)


class _Timer:
    __slots__ = ("labels", "metric", "t0")

    def __init__(self, metric: Histogram, labels: tuple[str, ...]) -> None:
        self.metric, self.labels, self.t0 = metric, labels, 0.0

    def __enter__(self) -> _Timer:
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        child(self.metric, self.labels).observe(time.perf_counter() - self.t0)

    def relabel(self, *labels: str) -> None:
        """Observe under these labels instead (an outcome known only at the end)."""
        self.labels = labels


class _NoTimer:
    __slots__ = ()

    def __enter__(self) -> _NoTimer:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def relabel(self, *labels: str) -> None:
        return None


_NO_TIMER = _NoTimer()


def timer(metric: Histogram, *labels: str) -> _Timer | _NoTimer:
    """``with timer(STEP_SECONDS, service, input):`` observes the block's wall time (also when it raises)."""
    return _Timer(metric, labels) if _State.on else _NO_TIMER


F = TypeVar("F", bound=Callable[..., Any])


def timed_step(service: str, input_kind: str) -> Callable[[F], F]:
    """Decorator: the call is one step of ``service`` from ``input_kind`` (:data:`STEP_SECONDS`)."""

    def wrap(fn: F) -> F:
        @functools.wraps(fn)
        def run(*args: Any, **kwargs: Any) -> Any:
            if not _State.on:
                return fn(*args, **kwargs)
            with _Timer(STEP_SECONDS, (service, input_kind)):
                return fn(*args, **kwargs)

        return run  # type: ignore[return-value]

    return wrap


STORE_OPS = ("get", "set", "delete", "keys", "set_if_absent", "delete_if_equal", "set_many_if", "append", "read",
             "stream_len", "get_many", "delete_many", "set_many", "index_add", "index_remove", "index_page",
             "index_below", "index_len")
_store_depth = threading.local()


def timed_store(backend: str) -> Callable[[type], type]:
    """Class decorator of a store backend: each call of :data:`STORE_OPS` is timed (:data:`STORE_SECONDS`) and
    its exceptions counted (:data:`STORE_ERRORS`). A call made inside another (SQLite's ``set_if_absent``
    calls ``get``) is part of the outer one, not counted again."""

    def wrap_op(op: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def run(*args: Any, **kwargs: Any) -> Any:
            if not _State.on or getattr(_store_depth, "n", 0):
                return fn(*args, **kwargs)
            _store_depth.n = 1
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            except Exception as exc:
                child(STORE_ERRORS, (backend, op, type(exc).__name__)).inc()
                raise
            finally:
                _store_depth.n = 0
                child(STORE_SECONDS, (backend, op)).observe(time.perf_counter() - t0)

        return run

    def decorate(cls: type) -> type:
        for op in STORE_OPS:
            setattr(cls, op, wrap_op(op, getattr(cls, op)))
        return cls

    return decorate


def exposition() -> bytes:
    """The text exposition of this process' metrics (what ``/metrics`` answers)."""
    return generate_latest(REGISTRY)


def serve(settings: MonitoringSettings, service: str) -> int | None:
    """Serve ``/metrics`` on ``EQA_METRICS_PORT`` (0 = off: nothing is counted) and start counting; once per
    port and process. Returns the port, or None when off."""
    port = settings.metrics_port
    if not port:
        return None
    with _State.lock:
        if port not in _State.servers:
            try:
                _State.servers[port] = start_http_server(port, addr=settings.metrics_host)
            except OSError as exc:
                raise OSError(f"cannot serve metrics on {settings.metrics_host}:{port}: {exc} (set EQA_METRICS_PORT "
                              "to a free port, or 0 for none)") from exc
            log.info("metrics on http://%s:%d/metrics", settings.metrics_host, port)
    enable()
    child(SERVICE_STARTED, (service,)).set(time.time())
    return port


def stop_serving(port: int | None = None) -> None:
    """Shut this process' metrics server on ``port`` (all of them: None) down (the launcher, tests)."""
    with _State.lock:
        ports = list(_State.servers) if port is None else [port] if port in _State.servers else []
        servers = [_State.servers.pop(p) for p in ports]
    for server, thread in servers:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)
