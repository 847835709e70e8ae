"""Episodes: submit a question, status and result, list, cancel, live events (SSE), merged recording."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any

from fastapi import APIRouter, Header, HTTPException, Query, Request, status
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, StreamingResponse
from starlette.concurrency import run_in_threadpool

from eqa import keys
from eqa.messages import EpisodeState, EpisodeStatus
from eqa.store import parse_stream_id
from gateway import mcap_export, recordings
from gateway.deps import ManagerDep, ReaderDep, SettingsDep, SubmitterDep
from gateway.manager import TERMINAL
from gateway.schemas import EpisodeList, Problem, QuestionRequest, Submitted

log = logging.getLogger(__name__)
router = APIRouter(prefix="/v1", tags=["episodes"])

KEEPALIVE_S = 15.0
END_EVENT_PREFIX = b'{"kind":"episode_end"'  # how every stored episode_end event starts (compact JSON)
END_EVENT_WAIT_S = 2.0  # after the final status, how long a stream waits for the episode_end event

_ERRORS: dict[int, tuple[str, object]] = {
    400: ("malformed request (a Content-Length that is not a number)", "Content-Length is not a number"),
    401: ("missing or invalid bearer token (EQA_API_TOKENS)", "missing bearer token"),
    403: ("the token lacks the scope this route needs", "this token lacks the 'submit' scope (it has read); "
          "give it in EQA_API_TOKENS as token:read+submit"),
    404: ("no such episode, or one of another token's (tenants see only their own)", "no episode 'ep-0'"),
    409: ("conflict: the episode already ended, or the robot is busy and EQA_BUSY_POLICY=refuse",
          "episode ep-0 already ended (stopped)"),
    413: ("body over EQA_MAX_BODY_BYTES (checked while it streams in, chunked too)",
          "body over the cap of 2097152 bytes (EQA_MAX_BODY_BYTES)"),
    422: ("invalid input: one entry per field saying what to change",
          [{"loc": ["body", "eps"], "msg": "Input should be less than 1", "type": "less_than"}]),
    429: ("too many requests (rate limit, failed authentications, a full queue, too many open event streams, a "
          "new home past EQA_HOMES_MAX_PER_TENANT); "
          "see Retry-After",
          "rate limit of 50 requests/s exceeded"),
    500: ("the recording could not be merged", "rerun rrd merge failed: ..."),
    503: ("the episode store is unavailable; see Retry-After", "the episode store is unavailable "
          "(ConnectionError); retry in 5 s"),
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI entries (model, description, a working example) of the error answers of a route."""
    out: dict[int | str, dict[str, Any]] = {}
    for code in codes:
        description, example = _ERRORS[code]
        entry: dict[str, Any] = {
            "model": Problem,
            "description": description,
            "content": {"application/json": {"example": {"detail": example}}},
        }
        if code in (429, 503):
            entry["headers"] = {"Retry-After": {"description": "seconds to wait", "schema": {"type": "integer"}}}
        out[code] = entry
    return out


READ_ERRORS = (401, 403, 422, 429, 503)
EpisodeId = Annotated[
    str, PathParam(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$", description="an episode id, ep-...")
]


class CountedStream(StreamingResponse):
    """A streaming response that calls ``release`` once when it is over, however it ends (finished, client
    gone, server stopping, or never started): the per-token count of open event streams."""

    def __init__(self, content: AsyncIterator[bytes], release: Callable[[], None], **kwargs: Any) -> None:
        super().__init__(content, **kwargs)
        self._release: Callable[[], None] | None = release

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            release, self._release = self._release, None
            if release is not None:
                release()


def path_id(value: str, param: str, what: str) -> str:
    """A path parameter that must be a safe id (:func:`eqa.keys.check_id`): the value, or 422 naming the rule."""
    try:
        return keys.check_id(value, what)
    except ValueError as exc:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            detail=[{"loc": ["path", param], "msg": str(exc), "type": "value_error"}],
        ) from exc


def _episode_id(episode_id: str) -> str:
    return path_id(episode_id, "episode_id", "episode id")


def _event_id(value: str, where: list[str]) -> str:
    try:
        parse_stream_id(value)
    except ValueError as exc:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, detail=[{"loc": where, "msg": str(exc), "type": "value_error"}]
        ) from exc
    return value


@router.post(
    "/questions",
    response_model=Submitted,
    status_code=status.HTTP_202_ACCEPTED,
    summary="Submit a question; returns the episode id (running or queued)",
    responses=errors(400, 401, 403, 409, 413, 422, 429, 503),
)
async def submit(body: QuestionRequest, manager: ManagerDep, caller: SubmitterDep) -> Submitted:
    manager.refuse_if_full(caller, body.robot)  # a full queue is refused on the event loop, at once
    return await run_in_threadpool(manager.submit, body, caller)


@router.get(
    "/episodes",
    response_model=EpisodeList,
    summary="Recent episodes of this token (all with admin), newest first",
    responses=errors(*READ_ERRORS),
)
def list_episodes(
    manager: ManagerDep,
    caller: ReaderDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    state: Annotated[EpisodeState | None, Query()] = None,
) -> EpisodeList:
    return EpisodeList(episodes=manager.list(caller, limit=limit, state=state))


@router.get(
    "/episodes/{episode_id}",
    response_model=EpisodeStatus,
    summary="Status and result: answer, prediction set, steps, normalised steps, stop reason",
    responses=errors(404, *READ_ERRORS),
)
async def get_episode(episode_id: EpisodeId, manager: ManagerDep, caller: ReaderDep) -> EpisodeStatus:
    eid = _episode_id(episode_id)
    known = manager.peek(eid, caller) or manager.peek_ended(eid, caller)  # from memory, on the event loop
    if known is not None:
        return known
    return await run_in_threadpool(manager.get, eid, caller)


@router.delete(
    "/episodes/{episode_id}",
    response_model=EpisodeStatus,
    summary="Cancel a queued or running episode (publishes EpisodeCancel)",
    responses=errors(400, 404, 409, 413, *READ_ERRORS),
)
def cancel_episode(episode_id: EpisodeId, manager: ManagerDep, caller: SubmitterDep) -> EpisodeStatus:
    return manager.cancel(_episode_id(episode_id), caller)


@router.get(
    "/episodes/{episode_id}/events",
    summary="Server-Sent Events of an episode, resumable with Last-Event-ID",
    description=(
        "Each event is `id: <stream id>` and `data: <compact JSON summary of a bus message>` (fields `kind`, "
        "`episode_id`, `step`, ...). Reconnect with the `Last-Event-ID` header (or `?after=`) to get every "
        "later event exactly once; an event id is `<ms>-<seq>`, two integers of at most 19 digits. The stream "
        "closes after the `episode_end` event."
    ),
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {
                "text/event-stream": {
                    "example": 'id: 1763777000000-0\ndata: {"kind":"frame","episode_id":"ep-1","step":0}\n\n'
                }
            }
        },
        **errors(404, *READ_ERRORS),
    },
)
async def events(
    episode_id: EpisodeId,
    request: Request,
    manager: ManagerDep,
    caller: ReaderDep,
    last_event_id: Annotated[
        str | None, Header(alias="Last-Event-ID", max_length=64, description="resume after this event id")
    ] = None,
    after: Annotated[
        str | None, Query(max_length=64, description="resume after this event id (same as Last-Event-ID)")
    ] = None,
) -> StreamingResponse:
    eid = _episode_id(episode_id)
    if last_event_id is not None:
        start = _event_id(last_event_id, ["header", "Last-Event-ID"])
    else:
        start = _event_id(after, ["query", "after"]) if after is not None else "0-0"
    await run_in_threadpool(manager.get, eid, caller)
    hub = request.app.state.hub
    streams: dict[str, int] = request.app.state.sse_open
    cap = request.app.state.settings.sse_max_per_token
    if streams.get(caller.key, 0) >= cap:
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            detail=f"this token has {streams[caller.key]} event streams open, the most one token may "
            f"(EQA_SSE_MAX_PER_TOKEN={cap}); close one (or follow several episodes with fewer streams)",
            headers={"Retry-After": "5"},
        )
    streams[caller.key] = streams.get(caller.key, 0) + 1  # event loop only: counted and released there

    def release() -> None:
        left = streams.get(caller.key, 1) - 1
        if left > 0:
            streams[caller.key] = left
        else:
            streams.pop(caller.key, None)

    async def gen() -> AsyncIterator[bytes]:
        cursor = start
        ended = False  # the episode_end event was sent
        terminal_since: float | None = None
        yield b"retry: 1000\n\n"
        while True:
            changed = hub.waiter()
            rows = await run_in_threadpool(manager.events, eid, cursor, 500)
            for entry_id, data in rows:
                cursor = entry_id
                ended = ended or data.startswith(END_EVENT_PREFIX)
                yield b"id: " + entry_id.encode() + b"\ndata: " + data + b"\n\n"
            if rows:
                continue
            st = await run_in_threadpool(manager.get, eid)
            if st.state in TERMINAL:
                # The manager stores the final status just before the episode_end event: wait for the event
                # (briefly: a stream resumed after its end, or an old episode, may have no more to come).
                terminal_since = terminal_since or time.monotonic()
                if ended or time.monotonic() - terminal_since > END_EVENT_WAIT_S:
                    return
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(changed.wait(), timeout=0.1)
                continue
            if await request.is_disconnected():
                return
            try:
                await asyncio.wait_for(changed.wait(), timeout=KEEPALIVE_S)
            except TimeoutError:
                yield b": keepalive\n\n"

    return CountedStream(
        gen(),
        release=release,
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


@router.get(
    "/episodes/{episode_id}/recording",
    response_class=FileResponse,
    summary="The merged Rerun recording (.rrd) of an episode (all services)",
    responses={200: {"content": {"application/octet-stream": {}}}, **errors(404, 500, *READ_ERRORS)},
)
async def recording(episode_id: EpisodeId, manager: ManagerDep, settings: SettingsDep, caller: ReaderDep
                    ) -> FileResponse:
    eid = _episode_id(episode_id)
    await run_in_threadpool(manager.get, eid, caller)
    try:
        path = await run_in_threadpool(recordings.merge, settings, eid)
    except FileNotFoundError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc)) from exc
    except recordings.RecordingError as exc:
        log.error("merge of %s failed: %s", eid, exc)
        raise HTTPException(status.HTTP_500_INTERNAL_SERVER_ERROR, detail=str(exc)) from exc
    return FileResponse(path, media_type="application/octet-stream", filename=f"{eid}.rrd")


@router.get(
    "/episodes/{episode_id}/recording.mcap",
    response_class=FileResponse,
    summary="The episode as a ROS 2 bag in MCAP for ros2 bag, Foxglove or Rerun",
    description="Frames (sensor_msgs/Image), camera info and pose, base poses, goals and paths (PoseStamped, "
    "Path), /tf and /tf_static, 2D maps (OccupancyGrid) and every stored event as std_msgs/String JSON on "
    "/eqa/<kind>, all CDR; images, maps and the camera mount only when the episode was recorded (EQA_RECORD). "
    "Channels: docs/mcap.md.",
    responses={200: {"content": {"application/octet-stream": {}}}, **errors(404, 500, *READ_ERRORS)},
)
async def recording_mcap(episode_id: EpisodeId, manager: ManagerDep, settings: SettingsDep, caller: ReaderDep
                         ) -> FileResponse:
    eid = _episode_id(episode_id)
    await run_in_threadpool(manager.get, eid, caller)

    def build() -> mcap_export.ExportSummary:
        return mcap_export.export_episode(settings, eid, mcap_export.read_events(manager.events, eid))

    try:
        summary = await run_in_threadpool(build)
    except FileNotFoundError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc)) from exc
    except recordings.RecordingError as exc:
        log.error("MCAP export of %s failed: %s", eid, exc)
        raise HTTPException(status.HTTP_500_INTERNAL_SERVER_ERROR, detail=str(exc)) from exc
    return FileResponse(summary.path, media_type="application/octet-stream", filename=f"{eid}.mcap")
