"""Homes: the caller's homes (paged), one home's summary, and reset (delete). A home is made by naming it in
``home`` of ``POST /v1/questions`` or ``POST /v1/tasks``; it belongs to the token's tenant (:mod:`gateway.homes`):
another tenant's token gets 404 for it, as for episodes."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response, status
from fastapi import Path as PathParam
from starlette.concurrency import run_in_threadpool

from gateway.deps import ManagerDep, ReaderDep, SubmitterDep
from gateway.homes import HomeDeleted, HomeInfo, HomeList
from gateway.routers.episodes import READ_ERRORS, errors, path_id
from gateway.schemas import Problem

router = APIRouter(prefix="/v1", tags=["homes"])


def _problem(description: str, example: str) -> dict[str, object]:
    return {"model": Problem, "description": description,
            "content": {"application/json": {"example": {"detail": example}}}}


_NOT_FOUND = {404: _problem("no such home of this token (another tenant's home of that name is not this one)",
                            "no home 'flat-1'")}
_BUSY = {409: _problem("an episode of the home is queued or running",
                       "home 'flat-1' has 1 queued or running episodes (ep-0); cancel them or wait for their end")}

HomeNameParam = Annotated[
    str, PathParam(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$",
                   description="your name of the home (as given in `home` when submitting)")
]


def _name(name: str) -> str:
    return path_id(name, "name", "home")


LIST_PARAMS = frozenset({"limit", "offset"})


def _known_params(request: Request) -> None:
    """A query parameter the route does not take is a 422 (``?limt=5`` is not silently a page of 50)."""
    unknown = sorted(set(request.query_params) - LIST_PARAMS)
    if unknown:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            detail=[{"loc": ["query", name[:40]], "msg": f"unknown query parameter; this route takes "
                     f"{', '.join(sorted(LIST_PARAMS))}", "type": "extra_forbidden"} for name in unknown[:10]],
        )


@router.get(
    "/homes",
    response_model=HomeList,
    dependencies=[Depends(_known_params)],
    summary="This token's homes, newest first (paged with limit and offset)",
    responses=errors(*READ_ERRORS),
)
async def list_homes(
    manager: ManagerDep,
    caller: ReaderDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=100_000)] = 0,
) -> HomeList:
    return await run_in_threadpool(manager.list_homes, caller, limit, offset)


@router.get(
    "/homes/{name}",
    response_model=HomeInfo,
    summary="One home: its memory's size (views, bytes), age, episodes, and the episodes using it now",
    responses={**errors(*READ_ERRORS), **_NOT_FOUND},
)
async def get_home(name: HomeNameParam, manager: ManagerDep, caller: ReaderDep) -> HomeInfo:
    return await run_in_threadpool(manager.home, _name(name), caller)


@router.delete(
    "/homes/{name}",
    response_model=HomeDeleted,
    summary="Reset a home: delete its memory and the name (409 while an episode of it is queued or running)",
    responses={**errors(*READ_ERRORS), **_NOT_FOUND, **_BUSY},
)
async def delete_home(name: HomeNameParam, manager: ManagerDep, caller: SubmitterDep) -> HomeDeleted:
    return await run_in_threadpool(manager.delete_home, _name(name), caller)


@router.get(
    "/homes/{name}/map.png",
    response_class=Response,
    summary="The picture of a home's map, as the mapper keeps it (PNG)",
    responses={**errors(*READ_ERRORS),
               404: _problem("no such home of this token, or no map picture of it (yet)",
                             "home 'flat-1' has no map picture (yet)"),
               200: {"content": {"image/png": {}}, "description": "PNG image"}},
)
async def home_map(name: HomeNameParam, manager: ManagerDep, caller: ReaderDep) -> Response:
    png = await run_in_threadpool(manager.home_map_png, _name(name), caller)
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})
