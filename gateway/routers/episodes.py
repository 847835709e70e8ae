"""Episodes: submit a question, status and result, list, cancel, live events (SSE), merged recording."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import time
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Header, HTTPException, Query, Request, status
from fastapi.responses import FileResponse, StreamingResponse
from starlette.concurrency import run_in_threadpool

from eqa import keys
from eqa.messages import EpisodeState, EpisodeStatus
from gateway import recordings
from gateway.deps import CallerDep, ManagerDep, SettingsDep
from gateway.manager import TERMINAL, GatewayError, InvalidError
from gateway.schemas import EpisodeList, QuestionRequest, Submitted

log = logging.getLogger(__name__)
router = APIRouter(prefix="/v1", tags=["episodes"])

_EVENT_ID = re.compile(r"^\d{1,20}-\d{1,20}$")
KEEPALIVE_S = 15.0
END_EVENT_PREFIX = b'{"kind":"episode_end"'  # how every stored episode_end event starts (compact JSON)
END_EVENT_WAIT_S = 2.0  # after the final status, how long a stream waits for the episode_end event


def _http(exc: GatewayError) -> HTTPException:
    if isinstance(exc, InvalidError) and exc.field:
        detail: object = [{"loc": ["body", exc.field], "msg": exc.message, "type": "value_error"}]
    else:
        detail = exc.message
    return HTTPException(exc.status_code, detail=detail)


def _episode_id(episode_id: str) -> str:
    try:
        return keys.check_id(episode_id, "episode id")
    except ValueError as exc:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            detail=[{"loc": ["path", "episode_id"], "msg": str(exc), "type": "value_error"}],
        ) from exc


@router.post(
    "/questions",
    response_model=Submitted,
    status_code=status.HTTP_202_ACCEPTED,
    summary="Submit a question; returns the episode id (running or queued)",
    responses={
        409: {"description": "robot busy and EQA_BUSY_POLICY=refuse"},
        422: {"description": "invalid body: field-level messages"},
    },
)
def submit(body: QuestionRequest, manager: ManagerDep, _caller: CallerDep) -> Submitted:
    try:
        return manager.submit(body)
    except GatewayError as exc:
        raise _http(exc) from exc


@router.get("/episodes", response_model=EpisodeList, summary="Recent episodes, newest first")
def list_episodes(
    manager: ManagerDep,
    _caller: CallerDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    state: Annotated[EpisodeState | None, Query()] = None,
) -> EpisodeList:
    return EpisodeList(episodes=manager.list(limit=limit, state=state))


@router.get(
    "/episodes/{episode_id}",
    response_model=EpisodeStatus,
    summary="Status and result: answer, prediction set, steps, normalised steps, stop reason",
)
async def get_episode(episode_id: str, manager: ManagerDep, _caller: CallerDep) -> EpisodeStatus:
    eid = _episode_id(episode_id)
    live = manager.peek(eid)
    if live is not None:
        return live
    try:
        return await run_in_threadpool(manager.get, eid)
    except GatewayError as exc:
        raise _http(exc) from exc


@router.delete(
    "/episodes/{episode_id}",
    response_model=EpisodeStatus,
    summary="Cancel a queued or running episode (publishes EpisodeCancel)",
)
def cancel_episode(episode_id: str, manager: ManagerDep, _caller: CallerDep) -> EpisodeStatus:
    try:
        return manager.cancel(_episode_id(episode_id))
    except GatewayError as exc:
        raise _http(exc) from exc


@router.get(
    "/episodes/{episode_id}/events",
    summary="Server-Sent Events of an episode, resumable with Last-Event-ID",
    description=(
        "Each event is `id: <stream id>` and `data: <compact JSON summary of a bus message>` (fields `kind`, "
        "`episode_id`, `step`, ...). Reconnect with the `Last-Event-ID` header (or `?after=`) to get every "
        "later event exactly once. The stream closes after the `episode_end` event."
    ),
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {
                "text/event-stream": {
                    "example": 'id: 1763777000000-0\ndata: {"kind":"frame","episode_id":"ep-1","step":0}\n\n'
                }
            }
        }
    },
)
async def events(
    episode_id: str,
    request: Request,
    manager: ManagerDep,
    _caller: CallerDep,
    last_event_id: Annotated[str | None, Header(alias="Last-Event-ID")] = None,
    after: Annotated[str | None, Query(description="resume after this event id (same as Last-Event-ID)")] = None,
) -> StreamingResponse:
    eid = _episode_id(episode_id)
    start = last_event_id or after or "0-0"
    if not _EVENT_ID.match(start):
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            detail=[
                {
                    "loc": ["header", "Last-Event-ID"],
                    "msg": f"event id {start!r} must look like <ms>-<seq>",
                    "type": "value_error",
                }
            ],
        )
    try:
        await run_in_threadpool(manager.get, eid)
    except GatewayError as exc:
        raise _http(exc) from exc
    hub = request.app.state.hub

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

    return StreamingResponse(
        gen(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


@router.get(
    "/episodes/{episode_id}/recording",
    response_class=FileResponse,
    summary="The merged Rerun recording (.rrd) of an episode (all services)",
    responses={200: {"content": {"application/octet-stream": {}}}, 404: {"description": "no recording"}},
)
async def recording(episode_id: str, manager: ManagerDep, settings: SettingsDep, _caller: CallerDep) -> FileResponse:
    eid = _episode_id(episode_id)
    try:
        await run_in_threadpool(manager.get, eid)
    except GatewayError as exc:
        raise _http(exc) from exc
    try:
        path = await run_in_threadpool(recordings.merge, settings, eid)
    except FileNotFoundError as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc)) from exc
    except recordings.RecordingError as exc:
        log.error("merge of %s failed: %s", eid, exc)
        raise HTTPException(status.HTTP_500_INTERNAL_SERVER_ERROR, detail=str(exc)) from exc
    return FileResponse(path, media_type="application/octet-stream", filename=f"{eid}.rrd")
