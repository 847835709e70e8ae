"""The FastAPI application of the gateway: :func:`create_app` builds it from :class:`Settings`.

The lifespan opens the store and one Zenoh session, subscribes to every stream of each configured robot,
holds the liveliness token ``eqa/v1/alive/gateway/{instance}``, reconciles stored episodes and runs the
watchdog. Zenoh callbacks run on Zenoh threads and hand each message to asyncio with
``loop.call_soon_threadsafe``; one consumer task applies them in arrival order (the blocking store calls
run in a worker thread).
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any

import fastapi_offline
from fastapi import Depends, FastAPI, HTTPException, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.datastructures import Headers

from eqa import keys, logs, metrics
from eqa.bus import Bus
from eqa.messages import MESSAGE_TYPES, EpisodeEnd, ErrorReply, Message
from eqa.service import SHELL_GROUPS
from eqa.settings import (
    FleetSettings,
    GatewaySettings,
    Groups,
    HeliosSettings,
    HomeSettings,
    SettingsGroup,
    SettingsView,
    SimulatorSettings,
    view,
)
from eqa.store import StoreUnavailable, open_store, unavailable_errors
from gateway import metrics as gateway_metrics
from gateway.auth import Authenticator, authenticate_docs, retry_after
from gateway.errors import GatewayError
from gateway.limits import BODY_METHODS, BodyLimit
from gateway.manager import PRUNE_BATCH, EpisodeManager, SceneArea
from gateway.routers import console, episodes, health, homes, labels, tasks
from gateway.schemas import Problem

log = logging.getLogger(__name__)

# the settings groups the gateway reads: the shell's (process, bus, store, metrics), its own, the robots and the
# episode watchdog, homes, the scenes (a request's step budget from the scene's area) and the task's pick limit
SETTINGS_GROUPS: Groups = (*SHELL_GROUPS, FleetSettings, GatewaySettings, HomeSettings, SimulatorSettings,
                           HeliosSettings)

INBOX_MAX_DATA = 256  # data messages waiting for the episode logic; more are dropped (logged)
CONTROL_TYPES = (EpisodeEnd, ErrorReply)  # never dropped for a running episode
PRUNE_EVERY_S = 30.0  # retention pass period
STORE_RETRY_AFTER_S = 5
STORE_TIMEOUT_S = 3.0  # one Redis call; a frozen Redis gives 503 after this, not after 10 s
SWAGGER_ASSETS = "/docs/assets"  # Swagger UI and ReDoc files from the fastapi-offline package
DOCS_ASSETS_DIR = Path(fastapi_offline.__file__).parent / "static"
DOCS_CSP = (  # the docs pages load nothing from other hosts (their inline set-up scripts and styles stay allowed)
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'"
)


class Hub:
    """Wakes Server-Sent-Event streams when an event was stored (lives on the event loop)."""

    def __init__(self) -> None:
        self._event = asyncio.Event()

    def waiter(self) -> asyncio.Event:
        return self._event

    def bump(self) -> None:
        event, self._event = self._event, asyncio.Event()
        event.set()


def _watchdog_period(settings: SettingsGroup) -> float:
    return max(0.05, min(1.0, settings.episode_timeout_s / 4))


class Inbox:
    """The bus messages of the episodes this gateway runs, from Zenoh's threads to the event loop, handled in
    arrival order on a worker thread. Messages of other episodes are dropped on arrival, before any work; data
    messages (frames, maps, scores, goals, decisions) wait at most INBOX_MAX_DATA deep, so a flood cannot delay an
    EpisodeEnd or an ErrorReply behind it for more than that (the drops are counted and logged)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, manager: EpisodeManager) -> None:
        self.loop, self.manager = loop, manager
        self.queue: asyncio.Queue[tuple[str, Message]] = asyncio.Queue()
        self.data = 0  # data messages waiting
        self.dropped = 0  # data messages dropped

    def on_message(self, key: str, msg: Message) -> None:  # Zenoh thread
        self.loop.call_soon_threadsafe(self._enqueue, keys.robot_of(key), msg)

    def _enqueue(self, robot: str, msg: Message) -> None:  # event loop
        if not self.manager.is_active(getattr(msg, "episode_id", None)):
            return
        if not isinstance(msg, CONTROL_TYPES):
            if self.data >= INBOX_MAX_DATA:
                self.dropped += 1
                metrics.inc(metrics.BUS_DROPPED, "gateway", "inbox_full")
                if self.dropped in (1, 10, 100) or self.dropped % 1000 == 0:
                    log.warning("inbox full: %d data messages dropped so far (a flood on %s?)", self.dropped, robot)
                return
            self.data += 1
        self.queue.put_nowait((robot, msg))

    async def consume(self) -> None:
        while True:
            robot, msg = await self.queue.get()
            if not isinstance(msg, CONTROL_TYPES):
                self.data -= 1
            with logs.bind(robot=robot, episode=getattr(msg, "episode_id", None), step=getattr(msg, "step", None)):
                try:
                    await asyncio.to_thread(self.manager.handle, robot, msg)
                except Exception:
                    log.exception("handling %s of %s failed; going on", msg.kind, robot)


async def watchdog(manager: EpisodeManager, settings: SettingsGroup) -> None:
    """Time out silent episodes every :func:`_watchdog_period`; every PRUNE_EVERY_S, apply the retention of
    episodes and homes (a large backlog in batches, letting requests through between them)."""
    loop = asyncio.get_running_loop()
    period = _watchdog_period(settings)
    last_prune = 0.0
    while True:
        await asyncio.sleep(period)
        try:
            await asyncio.to_thread(manager.check_timeouts)
            if loop.time() - last_prune >= PRUNE_EVERY_S:
                last_prune = loop.time()
                while await asyncio.to_thread(manager.prune) >= PRUNE_BATCH:
                    await asyncio.sleep(0)
                while await asyncio.to_thread(manager.prune_homes) >= PRUNE_BATCH:
                    await asyncio.sleep(0)
        except Exception:
            log.exception("watchdog pass failed; going on")


async def exit_with_launcher(parent_pid: int) -> None:
    """Started by a launcher (``EQA_PARENT_PID``): shut down like on SIGTERM once it is gone (no orphans)."""
    while os.getppid() == parent_pid:
        await asyncio.sleep(0.5)
    log.warning("gateway: launcher (pid %d) is gone; stopping", parent_pid)
    os.kill(os.getpid(), signal.SIGTERM)


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """The gateway's store, bus and episode manager for the app's life, with its three tasks: the inbox, the
    watchdog and, under a launcher, the exit when the launcher is gone."""
    settings: SettingsView = app.state.settings
    loop = asyncio.get_running_loop()
    hub = Hub()
    app.state.hub = hub
    store = await asyncio.to_thread(open_store, settings, STORE_TIMEOUT_S)
    bus = Bus(settings, "gateway").open()

    def notify() -> None:
        loop.call_soon_threadsafe(hub.bump)

    manager = EpisodeManager(settings, store, bus, notify=notify, scene_area=app.state.scene_area)
    inbox = Inbox(loop, manager)
    all_types = tuple(MESSAGE_TYPES.values())
    for robot in settings.robots:
        bus.subscribe(keys.robot_streams(robot), all_types, inbox.on_message)
    await asyncio.to_thread(manager.start)
    app.state.manager = manager
    tasks = [
        asyncio.create_task(inbox.consume(), name="gateway-consume"),
        asyncio.create_task(watchdog(manager, settings), name="gateway-watchdog"),
    ]
    if settings.parent_pid:
        tasks.append(asyncio.create_task(exit_with_launcher(settings.parent_pid), name="gateway-exit-with-launcher"))
    log.info(
        "gateway %s up: robots %s, store %s",
        settings.instance,
        ",".join(settings.robots),
        "redis" if settings.redis_url else "embedded",
    )
    try:
        yield
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        app.state.manager = None
        bus.close()
        store.close()
        log.info("gateway stopped")


async def _gateway_error(_request: Request, exc: Exception) -> JSONResponse:
    """One handler for every :class:`GatewayError` of the episode logic: its status, its detail, and
    ``Retry-After`` when it says when to come back (429)."""
    assert isinstance(exc, GatewayError)
    headers = {"Retry-After": retry_after(exc.retry_after_s)} if exc.retry_after_s is not None else None
    return JSONResponse(status_code=exc.status_code, content={"detail": exc.detail()}, headers=headers)


async def _store_unavailable(_request: Request, exc: Exception) -> JSONResponse:
    """503 with ``Retry-After`` while the store cannot be reached (it was a 500)."""
    log.warning("store unavailable: %s: %s", type(exc).__name__, exc)
    why = str(exc) if isinstance(exc, StoreUnavailable) else type(exc).__name__  # its own words say what happened
    return JSONResponse(
        status_code=status.HTTP_503_SERVICE_UNAVAILABLE,
        content={"detail": f"the episode store is unavailable ({why}); retry in {STORE_RETRY_AFTER_S} s"},
        headers={"Retry-After": str(STORE_RETRY_AFTER_S)},
    )


async def _validation_error(_request: Request, exc: Exception) -> JSONResponse:
    """422 with one ``{loc, msg, type}`` per field (never echoing the input back: it may be 1 MB)."""
    assert isinstance(exc, RequestValidationError)
    detail: list[dict[str, Any]] = [
        {"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
        for e in exc.errors()
    ]
    return JSONResponse(status_code=status.HTTP_422_UNPROCESSABLE_CONTENT, content={"detail": detail})


def create_app(settings: SettingsGroup, scene_area: SceneArea | None = None) -> FastAPI:
    """The gateway app, reading the settings of :data:`SETTINGS_GROUPS` only. ``scene_area`` gives a scene's
    floor area for the default step budget and the check that a requested scene exists (the process entry passes
    the simulator's scene library)."""
    settings = view(settings, SETTINGS_GROUPS)
    app = FastAPI(
        title="EQA gateway",
        version="1.0.0",
        description=(
            "Submit embodied questions, follow episodes live (Server-Sent Events), fetch results and Rerun "
            "recordings. When `EQA_API_TOKENS` is set, routes under `/v1/episodes` and `/v1/questions` need "
            "`Authorization: Bearer <token>`, and this documentation (`/docs`, `/redoc`, `/openapi.json`) needs "
            "the token too, as a bearer token or as the password of HTTP Basic authentication (what a browser "
            "asks for); `/v1/health` and `/v1/ready` are open (without a token readiness says only ready or "
            "not). Tokens carry scopes (`submit`, `read`, `admin`); each token sees only the episodes it "
            "submitted (404 for the others') unless it has `admin`. Limits answer 413 (body over "
            "`EQA_MAX_BODY_BYTES`), 429 with `Retry-After` (rate, failed authentications, full queues) and 503 "
            "with `Retry-After` while the store is unavailable."
        ),
        lifespan=lifespan,
        # Served below behind the token check instead of FastAPI's open defaults.
        docs_url=None,
        redoc_url=None,
        openapi_url=None,
    )
    app.state.settings = settings
    app.state.scene_area = scene_area
    app.state.auth = Authenticator(settings)  # ValueError naming a bad EQA_API_TOKENS entry
    app.state.limiter = app.state.auth.limiter
    app.state.manager = None
    app.state.sse_open = {}  # open event streams per caller key (gateway/routers/episodes.py)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(GatewayError, _gateway_error)
    for exc_type in unavailable_errors():
        app.add_exception_handler(exc_type, _store_unavailable)
    # Body cap and authentication before a body is read (pure ASGI: chunked bodies are counted as they come).
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes, timeout_s=settings.body_timeout_s,
                       max_uploads=settings.max_concurrent_uploads)

    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.cors_origins),
            allow_methods=["*"],
            allow_headers=["Authorization", "Content-Type", "Last-Event-ID"],
        )
    app.include_router(health.router)
    app.include_router(episodes.router)
    app.include_router(labels.router)
    app.include_router(tasks.router)
    app.include_router(homes.router)
    console.install(app)  # the web console at / and the routes it needs
    _add_docs(app)
    gateway_metrics.install(app)
    return app


_EDGE_ANSWERS = {  # what the authentication, limits and store handlers may answer on any protected route
    "401": "missing or invalid bearer token (EQA_API_TOKENS)",
    "403": "the token lacks the scope this route needs",
    "422": "invalid input: one entry per field saying what to change",
    "429": "too many requests (rate, failed authentications, full queue); see Retry-After",
    "503": "the episode store is unavailable, or (a body) EQA_MAX_CONCURRENT_UPLOADS are being received; see "
           "Retry-After",
}
_BODY_ANSWERS = {"400": "malformed request (a Content-Length that is not a number)",
                 "408": "the body did not arrive whole within EQA_BODY_TIMEOUT_S (the connection is closed)",
                 "413": "body over EQA_MAX_BODY_BYTES (checked while it streams in, chunked too)"}


def _protected(path: str) -> bool:
    """Every API route but health and readiness needs the token (when tokens are configured)."""
    return path.startswith("/v1/") and not path.startswith(("/v1/health", "/v1/ready"))


def _document_edge_answers(spec: dict[str, Any]) -> None:
    """Every protected operation lists the answers of the layers in front of it (authentication, scopes,
    rate and queue limits, body cap, store outage), whichever router declared it: the document lists every
    status a route can answer (the fuzz test checks it)."""
    problem = {"$ref": "#/components/schemas/Problem"}
    schemas = spec.setdefault("components", {}).setdefault("schemas", {})
    problem_schema = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    for name, schema in {**problem_schema.pop("$defs", {}), "Problem": problem_schema}.items():
        schemas.setdefault(name, schema)
    for path, operations in spec.get("paths", {}).items():
        if not _protected(path):
            continue
        for method, op in operations.items():
            answers = dict(_EDGE_ANSWERS)
            if method.upper() in BODY_METHODS:
                answers.update(_BODY_ANSWERS)
            for code, description in answers.items():
                entry = op.setdefault("responses", {}).setdefault(
                    code, {"description": description, "content": {"application/json": {"schema": problem}}}
                )
                if code in ("429", "503"):
                    entry.setdefault("headers", {"Retry-After": {"description": "seconds to wait",
                                                                 "schema": {"type": "integer"}}})


DOCS_CHALLENGES = (b"Bearer", b'Basic realm="EQA gateway API docs", charset="UTF-8"')


async def docs_caller(request: Request) -> Any:
    """:func:`gateway.auth.authenticate_docs` (the same check), with its 401 challenge as one
    ``WWW-Authenticate`` line per scheme: browsers read one scheme per line, and Chromium shows no password
    prompt for ``Bearer, Basic realm=...`` in one line (so a person could not open /docs with tokens set)."""
    try:
        return await authenticate_docs(request)
    except HTTPException as exc:
        if exc.status_code != status.HTTP_401_UNAUTHORIZED:
            raise
        lines = Headers(raw=[(b"www-authenticate", c) for c in DOCS_CHALLENGES])
        raise HTTPException(exc.status_code, detail=exc.detail, headers=lines) from None  # type: ignore[arg-type]


DocsAuth = Annotated[Any, Depends(docs_caller)]


def _add_docs(app: FastAPI) -> None:
    """``/openapi.json``, ``/docs`` (Swagger UI) and ``/redoc``, behind :func:`gateway.auth.authenticate_docs`
    (open when no tokens are configured). With tokens the spec declares the bearer scheme on the API routes,
    so Swagger UI's "Authorize" button sends the token with its "Try it out" requests."""
    base_openapi = app.openapi

    def openapi_with_security() -> dict[str, Any]:
        first = app.openapi_schema is None
        spec = base_openapi()  # cached by FastAPI in app.openapi_schema after the first call
        if first:
            _document_edge_answers(spec)
        if first and app.state.settings.api_tokens:
            schemes = spec.setdefault("components", {}).setdefault("securitySchemes", {})
            schemes["bearerAuth"] = {"type": "http", "scheme": "bearer", "description": "a token of EQA_API_TOKENS"}
            for path, operations in spec.get("paths", {}).items():
                if _protected(path):
                    for op in operations.values():
                        op["security"] = [{"bearerAuth": []}]
        return spec

    app.openapi = openapi_with_security  # type: ignore[method-assign]

    @app.get("/openapi.json", include_in_schema=False)
    async def openapi(_caller: DocsAuth) -> JSONResponse:
        return JSONResponse(app.openapi())

    # Swagger UI (5.x, reads OpenAPI 3.1) and ReDoc come with the fastapi-offline package: /docs and /redoc work
    # without internet access (FastAPI's defaults load them, and Google fonts, from CDNs). They are a public
    # library, served without a token.
    app.mount(SWAGGER_ASSETS, StaticFiles(directory=str(DOCS_ASSETS_DIR)), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def swagger(_caller: DocsAuth) -> HTMLResponse:
        page = get_swagger_ui_html(
            openapi_url="/openapi.json",
            title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{SWAGGER_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{SWAGGER_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{SWAGGER_ASSETS}/favicon.png",
        )
        page.headers["Content-Security-Policy"] = DOCS_CSP
        return page

    @app.get("/redoc", include_in_schema=False)
    async def redoc(_caller: DocsAuth) -> HTMLResponse:
        page = get_redoc_html(
            openapi_url="/openapi.json",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{SWAGGER_ASSETS}/redoc.standalone.js",
            redoc_favicon_url=f"{SWAGGER_ASSETS}/favicon.png",
            with_google_fonts=False,
        )
        # ReDoc's sidebar shows a logo from cdn.redoc.ly (and hides it when that fails): the page's policy
        # keeps the browser from asking any host but the gateway.
        page.headers["Content-Security-Policy"] = DOCS_CSP
        return page
