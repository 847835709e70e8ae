"""The web console (``/``) and the API routes it needs beyond the episode routes: the latest camera view and
map of an episode as PNG images, and a fleet overview. Same token, scopes, tenant rules and rate limit as the
rest of the API (:mod:`gateway.auth`): the images of another tenant's episode are "not found" like its status.

The console itself is static HTML, JS and CSS in ``gateway/console/`` (no CDN, no build step). It reads the
token once into ``sessionStorage`` and sends it as a bearer header with every call; it follows an episode's
events with ``fetch`` (``EventSource`` cannot send a header), resuming with ``Last-Event-ID`` after a lost
connection or a page reload.

The images come from the bus: this router's lifespan (nested in the gateway's, so the manager and its bus
exist) subscribes to each robot's frame, map and goal streams and keeps the latest of each per episode in a
:class:`gateway.views.ViewCache`.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, FastAPI, HTTPException, Request, Response, status
from fastapi import Path as PathParam
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from eqa import keys
from eqa.messages import Frame, Goal, MapUpdate, Message
from gateway.deps import ManagerDep, ReaderDep
from gateway.routers.episodes import READ_ERRORS, errors
from gateway.views import ViewCache

STATIC_DIR = Path(__file__).resolve().parents[1] / "console"
STATIC_URL = "/console"
FAILURES_SHOWN = 10
RATE_WINDOW_S = 300.0  # episodes per minute over the last five minutes
RECENT_SCANNED = 500  # newest episodes read to count them
CONSOLE_CSP = (  # the console loads nothing from other hosts and runs no inline script
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
    "frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    views = ViewCache()
    app.state.views = views
    manager = app.state.manager

    def on_message(_key: str, msg: Message) -> None:  # Zenoh thread: keep references only
        if manager.is_active(getattr(msg, "episode_id", None)):
            views.offer(msg)

    for robot in app.state.settings.robots:
        manager.bus.subscribe(keys.stream(robot, keys.SIM_FRAME), Frame, on_message)
        manager.bus.subscribe(keys.stream(robot, keys.MAPPER_MAP), MapUpdate, on_message)
        manager.bus.subscribe(keys.stream(robot, keys.PLANNER_GOAL), Goal, on_message)
    yield


router = APIRouter(prefix="/v1", tags=["console"], lifespan=_lifespan)

EpisodeId = Annotated[
    str, PathParam(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$", description="an episode id, ep-...")
]
PNG: dict[int | str, dict[str, Any]] = {
    **errors(404, *READ_ERRORS),
    200: {"content": {"image/png": {}}, "description": "PNG image; header X-EQA-Step says of which step",
          "headers": {"X-EQA-Step": {"description": "the step of the image", "schema": {"type": "integer"}}}},
}
PNG[404] = {**PNG[404], "description": "no such episode (or another tenant's), or no image of it yet"}


async def _image(request: Request, manager: Any, caller: Any, episode_id: str, kind: str) -> Response:
    await run_in_threadpool(manager.get, episode_id, caller)  # 404 for an unknown or another tenant's episode
    got = await run_in_threadpool(request.app.state.views.png, episode_id, kind)
    if got is None:
        what = "camera view" if kind == "frame" else "map"
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"no {what} of episode {episode_id} yet "
                            "(kept while the episode runs on this gateway and for a while after)")
    step, png = got
    return Response(png, media_type="image/png", headers={"X-EQA-Step": str(step), "Cache-Control": "no-store"})


@router.get(
    "/episodes/{episode_id}/frame.png",
    response_class=Response,
    summary="The latest camera view of an episode with its prompt points (PNG)",
    description="The most recent simulator or robot frame of the episode, with the prompt points the scorer "
    "rated on it (Explore-EQA Eq. 1) as numbered yellow circles. Kept in memory for the gateway's newest "
    "episodes; 404 before the first frame.",
    responses=PNG,
)
async def frame_png(episode_id: EpisodeId, request: Request, manager: ManagerDep, caller: ReaderDep) -> Response:
    return await _image(request, manager, caller, episode_id, "frame")


@router.get(
    "/episodes/{episode_id}/map.png",
    response_class=Response,
    summary="The latest top-down map of an episode: explored area, frontiers, path (PNG)",
    description="+y up. Grey unknown, white free, light blue explored, dark occupied; orange dots are frontiers "
    "sized by their weight (Eq. A6), the blue line the planned path, the green line the trail, red the robot.",
    responses=PNG,
)
async def map_png(episode_id: EpisodeId, request: Request, manager: ManagerDep, caller: ReaderDep) -> Response:
    return await _image(request, manager, caller, episode_id, "map")


class RobotView(BaseModel):
    robot: str
    episode_id: str | None = Field(None, description='running episode; "busy" when it is another tenant\'s')
    step: int | None = None
    max_steps: int | None = None
    question: str | None = None
    queue: list[str] = Field(default_factory=list, description="queued episodes of this caller, next first")


class Failure(BaseModel):
    episode_id: str
    robot: str
    reason: str
    at: float


class FleetView(BaseModel):
    """What the console's fleet view shows."""

    robots: list[RobotView]
    services: dict[str, list[str]] = Field(description="alive instances per service kind (liveliness tokens)")
    missing: list[str] = Field(description="service kinds an episode needs and none is alive")
    episodes_per_minute: float = Field(description="episodes that ended over the last 5 minutes, per minute")
    finished_recently: int
    recent_failures: list[Failure]
    at: float


def _fleet(manager: Any, caller: Any) -> FleetView:
    now = time.time()
    running = {s.episode_id: s for s in manager.list(caller, limit=1000, state="running")}
    queued = sorted(manager.list(caller, limit=1000, state="queued"), key=lambda s: s.created_at)
    robots = []
    for robot, eid in manager.robots(caller).items():
        st = running.get(eid) if eid else None
        robots.append(RobotView(
            robot=robot,
            episode_id=eid,
            step=None if st is None else max(0, st.step + 1),
            max_steps=None if st is None else st.max_steps,
            question=None if st is None else st.question.text,
            queue=[s.episode_id for s in queued if s.robot == robot],
        ))
    recent = manager.list(caller, limit=RECENT_SCANNED)
    done = [s for s in recent if s.state not in ("queued", "running") and now - s.updated_at <= RATE_WINDOW_S]
    failures = [s for s in recent if s.state == "failed"][:FAILURES_SHOWN]
    return FleetView(
        robots=robots,
        services=manager.alive_services(),
        missing=manager.missing_services(),
        episodes_per_minute=round(len(done) / (RATE_WINDOW_S / 60.0), 2),
        finished_recently=len(done),
        recent_failures=[Failure(episode_id=s.episode_id, robot=s.robot, reason=s.stop_reason or "failed",
                                 at=s.updated_at) for s in failures],
        at=now,
    )


@router.get(
    "/fleet",
    response_model=FleetView,
    responses=errors(*READ_ERRORS),
    summary="The fleet at a glance: robots, their episode and queue, services alive, throughput, failures",
    description="Episodes are the caller's own (all with the admin scope); another tenant's running episode "
    "shows as `busy`.",
)
async def fleet(manager: ManagerDep, caller: ReaderDep) -> FleetView:
    return await run_in_threadpool(_fleet, manager, caller)


def install(app: FastAPI) -> None:
    """Register the console on the gateway: the routes above, ``/`` (the page) and its static files."""
    app.include_router(router)
    app.mount(STATIC_URL, StaticFiles(directory=str(STATIC_DIR)), name="console")

    @app.get("/", include_in_schema=False)
    async def console_page() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", headers={"Content-Security-Policy": CONSOLE_CSP,
                                                                "Cache-Control": "no-cache"})

    base_openapi = app.openapi

    def openapi_with_console_security() -> dict[str, Any]:
        first = app.openapi_schema is None
        spec = base_openapi()
        if first and app.state.settings.api_tokens:
            for path in ("/v1/fleet", "/v1/episodes/{episode_id}/frame.png", "/v1/episodes/{episode_id}/map.png"):
                for op in spec.get("paths", {}).get(path, {}).values():
                    op["security"] = [{"bearerAuth": []}]
        return spec

    app.openapi = openapi_with_console_security  # type: ignore[method-assign]
