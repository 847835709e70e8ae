"""The gateway's Prometheus metrics and its ``/metrics`` route (docs/metrics.md).

* ``eqa_gateway_http_responses_total{method, code}``: every response, counted by a pure ASGI middleware
  outside every other layer, so the refusals of the body limit and the authentication in front of the routes
  are counted too: failed authentications are ``code="401"``, limits ``code="429"`` (and 413, 408, 503).
* ``eqa_gateway_request_seconds``: time to the response's first byte.
* ``eqa_gateway_episodes{state, kind}`` (queued and running, read from the episode manager at scrape time),
  ``eqa_gateway_episodes_ended_total{state, kind}`` (stopped, failed, cancelled), the idle time of the running
  episode that waits longest (``eqa_gateway_running_idle_seconds_max``: a stalled fleet) and the live instances
  of each service as the gateway's liveliness view has them (``eqa_gateway_service_instances``).
* The kernel's metrics (:mod:`eqa.metrics`: store, bus) of the gateway process are in the same exposition.

Who may read ``/metrics``: everyone when ``EQA_API_TOKENS`` is empty (the API is open then too); otherwise a
caller on the loopback interface whose request came through no proxy (no ``Forwarded`` / ``X-Forwarded-For``
header), a bearer ``EQA_METRICS_TOKEN``, or an API token with the ``admin`` scope; anyone else gets 401.
"""

from __future__ import annotations

import hmac
import ipaddress
import time
import weakref
from collections.abc import Iterator
from typing import Any

from fastapi import FastAPI, HTTPException, Request, status
from fastapi.responses import Response
from prometheus_client import Counter, Histogram
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import REGISTRY, Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from eqa import metrics
from eqa.messages import EpisodeStatus
from gateway.auth import bearer_token

METHODS = frozenset({"GET", "POST", "PUT", "PATCH", "DELETE", "HEAD", "OPTIONS"})
ACTIVE_STATES = ("queued", "running")
KINDS = ("question", "task")

HTTP_RESPONSES = Counter(
    "eqa_gateway_http_responses_total", "HTTP responses of the gateway by method and status code (401: failed "
    "authentication, 429: a limit)", ["method", "code"])
REQUEST_SECONDS = Histogram(
    "eqa_gateway_request_seconds", "Time from a request's arrival to its response's first byte",
    buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0))
EPISODES_ENDED = Counter(
    "eqa_gateway_episodes_ended_total", "Episodes that ended, by final state and kind", ["state", "kind"])


def kind_of(st: EpisodeStatus) -> str:
    return "task" if st.task is not None else "question"


def episode_ended(st: EpisodeStatus) -> None:
    """Count an episode's end (the manager calls it once per final status it stores)."""
    EPISODES_ENDED.labels(st.state, kind_of(st)).inc()


class ResponseMetrics:
    """Pure ASGI middleware counting every HTTP response by method and status (outermost layer)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        method = scope.get("method", "")
        method = method if method in METHODS else "other"  # the label set stays bounded whatever is sent
        started = False

        async def counting(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start" and not started:
                started = True
                HTTP_RESPONSES.labels(method, str(int(message["status"]))).inc()
                REQUEST_SECONDS.observe(time.perf_counter() - t0)
            await send(message)

        await self.app(scope, receive, counting)


class EpisodeCollector(Collector):
    """Gauges read from the app's episode manager at scrape time (nothing to keep in step)."""

    def __init__(self) -> None:
        self.apps: weakref.WeakSet[FastAPI] = weakref.WeakSet()  # a test process makes many apps

    def collect(self) -> Iterator[GaugeMetricFamily]:
        episodes = GaugeMetricFamily("eqa_gateway_episodes", "Episodes queued or running on this gateway",
                                     labels=["state", "kind"])
        idle = GaugeMetricFamily("eqa_gateway_running_idle_seconds_max",
                                 "Seconds since the last message of the running episode that waits longest "
                                 "(0: none running); the watchdog fails it at EQA_EPISODE_TIMEOUT_S")
        alive = GaugeMetricFamily("eqa_gateway_service_instances",
                                  "Live instances of each service (liveliness tokens the gateway sees)",
                                  labels=["service"])
        counts = {(s, k): 0 for s in ACTIVE_STATES for k in KINDS}
        longest = 0.0
        services: dict[str, int] = {}
        now = time.time()
        for app in list(self.apps):
            manager = getattr(app.state, "manager", None)
            if manager is None:
                continue
            for episode in _records(manager):
                st = episode.status
                key = (st.state, kind_of(st))
                if key in counts:
                    counts[key] += 1
                if st.state == "running":
                    longest = max(longest, now - episode.last_activity)
            for service, instances in manager.alive_services().items():
                services[service] = services.get(service, 0) + len(instances)
        for (state, kind), n in counts.items():
            episodes.add_metric([state, kind], n)
        idle.add_metric([], longest)
        for service, n in sorted(services.items()):
            alive.add_metric([service], n)
        yield episodes
        yield idle
        yield alive


def _records(manager: Any) -> list[Any]:
    """The manager's active records, copied without its lock (a scrape never waits on a store call)."""
    for _ in range(3):
        try:
            return list(manager._active.values())
        except RuntimeError:  # changed size while copied: copy again
            continue
    return []


COLLECTOR = EpisodeCollector()
REGISTRY.register(COLLECTOR)

_LOOPBACK_PROXY_HEADERS = ("forwarded", "x-forwarded-for", "x-real-ip")


def _is_loopback(host: str | None) -> bool:
    try:
        return host is not None and ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def may_read(request: Request) -> bool:
    """Whether the caller may read ``/metrics`` (see the module docstring)."""
    settings = request.app.state.settings
    if not settings.api_tokens:
        return True
    host = request.client.host if request.client is not None else None
    if _is_loopback(host) and not any(h in request.headers for h in _LOOPBACK_PROXY_HEADERS):
        return True
    presented = bearer_token(request.headers)
    if presented is None:
        return False
    if settings.metrics_token and hmac.compare_digest(settings.metrics_token.encode(), presented.encode()):
        return True
    scopes = request.app.state.auth.lookup(presented)
    return scopes is not None and "admin" in scopes


def install(app: FastAPI) -> None:
    """Count this app's responses and episodes, and serve ``GET /metrics`` (call it last in ``create_app``:
    the middleware added last is the outermost)."""
    metrics.enable()
    COLLECTOR.apps.add(app)
    app.add_middleware(ResponseMetrics)

    @app.get("/metrics", include_in_schema=False)
    async def prometheus(request: Request) -> Response:
        if not may_read(request):
            raise HTTPException(status.HTTP_401_UNAUTHORIZED, detail="metrics need EQA_METRICS_TOKEN or an admin "
                                "token as a bearer token (or a loopback caller)",
                                headers={"WWW-Authenticate": "Bearer"})
        return Response(metrics.exposition(), media_type=metrics.CONTENT_TYPE)
