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
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import fastapi_offline
from fastapi import FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from eqa import keys
from eqa.bus import Bus
from eqa.messages import MESSAGE_TYPES, Message
from eqa.settings import Settings
from eqa.store import open_store
from gateway.auth import RateLimiter
from gateway.deps import DocsCallerDep
from gateway.manager import EpisodeManager, SceneArea
from gateway.routers import episodes, health

log = logging.getLogger(__name__)

MAX_BODY_BYTES = 2 * 1024 * 1024
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


def _watchdog_period(settings: Settings) -> float:
    return max(0.05, min(1.0, settings.episode_timeout_s / 4))


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    loop = asyncio.get_running_loop()
    hub = Hub()
    app.state.hub = hub
    store = await asyncio.to_thread(open_store, settings)
    bus = Bus(settings, "gateway").open()
    inbox: asyncio.Queue[tuple[str, Message]] = asyncio.Queue()

    def notify() -> None:
        loop.call_soon_threadsafe(hub.bump)

    manager = EpisodeManager(settings, store, bus, notify=notify, scene_area=app.state.scene_area)

    def on_message(key: str, msg: Message) -> None:  # Zenoh thread
        loop.call_soon_threadsafe(inbox.put_nowait, (keys.robot_of(key), msg))

    all_types = tuple(MESSAGE_TYPES.values())
    for robot in settings.robots:
        bus.subscribe(keys.robot_streams(robot), all_types, on_message)
    await asyncio.to_thread(manager.start)
    app.state.manager = manager

    async def consume() -> None:
        while True:
            robot, msg = await inbox.get()
            try:
                await asyncio.to_thread(manager.handle, robot, msg)
            except Exception:
                log.exception("handling %s of %s failed; going on", msg.kind, robot)

    async def watchdog() -> None:
        period = _watchdog_period(settings)
        while True:
            await asyncio.sleep(period)
            try:
                await asyncio.to_thread(manager.check_timeouts)
            except Exception:
                log.exception("watchdog pass failed; going on")

    tasks = [
        asyncio.create_task(consume(), name="gateway-consume"),
        asyncio.create_task(watchdog(), name="gateway-watchdog"),
    ]
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


async def _validation_error(_request: Request, exc: Exception) -> JSONResponse:
    """422 with one ``{loc, msg, type}`` per field (never echoing the input back: it may be 1 MB)."""
    assert isinstance(exc, RequestValidationError)
    detail: list[dict[str, Any]] = [
        {"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
        for e in exc.errors()
    ]
    return JSONResponse(status_code=status.HTTP_422_UNPROCESSABLE_CONTENT, content={"detail": detail})


def create_app(settings: Settings, scene_area: SceneArea | None = None) -> FastAPI:
    """The gateway app. ``scene_area`` gives a scene's floor area for the default step budget and the check
    that a requested scene exists (the process entry passes the simulator's scene library)."""
    app = FastAPI(
        title="EQA gateway",
        version="1.0.0",
        description=(
            "Submit embodied questions, follow episodes live (Server-Sent Events), fetch results and Rerun "
            "recordings. When `EQA_API_TOKENS` is set, routes under `/v1/episodes` and `/v1/questions` need "
            "`Authorization: Bearer <token>`, and this documentation (`/docs`, `/redoc`, `/openapi.json`) needs "
            "the token too, as a bearer token or as the password of HTTP Basic authentication (what a browser "
            "asks for); `/v1/health` and `/v1/ready` are open."
        ),
        lifespan=lifespan,
        # Served below behind the token check instead of FastAPI's open defaults.
        docs_url=None,
        redoc_url=None,
        openapi_url=None,
    )
    app.state.settings = settings
    app.state.scene_area = scene_area
    app.state.limiter = RateLimiter(settings.rate_limit_per_s)
    app.state.manager = None
    app.add_exception_handler(RequestValidationError, _validation_error)

    @app.middleware("http")
    async def limit_body(request: Request, call_next: Any) -> Any:
        length = request.headers.get("content-length")
        if length is not None and length.isdigit() and int(length) > MAX_BODY_BYTES:
            return JSONResponse(status_code=413, content={"detail": f"body over {MAX_BODY_BYTES} bytes"})
        return await call_next(request)

    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(settings.cors_origins),
            allow_methods=["*"],
            allow_headers=["Authorization", "Content-Type", "Last-Event-ID"],
        )
    app.include_router(health.router)
    app.include_router(episodes.router)
    _add_docs(app)
    return app


def _add_docs(app: FastAPI) -> None:
    """``/openapi.json``, ``/docs`` (Swagger UI) and ``/redoc``, behind :func:`gateway.auth.authenticate_docs`
    (open when no tokens are configured). With tokens the spec declares the bearer scheme on the API routes,
    so Swagger UI's "Authorize" button sends the token with its "Try it out" requests."""
    base_openapi = app.openapi

    def openapi_with_security() -> dict[str, Any]:
        first = app.openapi_schema is None
        spec = base_openapi()  # cached by FastAPI in app.openapi_schema after the first call
        if first and app.state.settings.api_tokens:
            schemes = spec.setdefault("components", {}).setdefault("securitySchemes", {})
            schemes["bearerAuth"] = {"type": "http", "scheme": "bearer", "description": "a token of EQA_API_TOKENS"}
            for path, operations in spec.get("paths", {}).items():
                if path.startswith(("/v1/episodes", "/v1/questions")):
                    for op in operations.values():
                        op["security"] = [{"bearerAuth": []}]
        return spec

    app.openapi = openapi_with_security  # type: ignore[method-assign]

    @app.get("/openapi.json", include_in_schema=False)
    async def openapi(_caller: DocsCallerDep) -> JSONResponse:
        return JSONResponse(app.openapi())

    # Swagger UI (5.x, reads OpenAPI 3.1) and ReDoc come with the fastapi-offline package: /docs and /redoc work
    # without internet access (FastAPI's defaults load them, and Google fonts, from CDNs). They are a public
    # library, served without a token.
    app.mount(SWAGGER_ASSETS, StaticFiles(directory=str(DOCS_ASSETS_DIR)), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def swagger(_caller: DocsCallerDep) -> HTMLResponse:
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
    async def redoc(_caller: DocsCallerDep) -> HTMLResponse:
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
