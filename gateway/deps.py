"""``Annotated`` dependencies of the routes."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from eqa.settings import SettingsView
from gateway.auth import Caller, authenticate, authenticate_docs, can_read, can_submit
from gateway.manager import EpisodeManager


# Async although they do no I/O: FastAPI runs a plain ``def`` dependency in its thread pool, a hop per request
# that costs more than the work under load.
async def get_settings(request: Request) -> SettingsView:
    return request.app.state.settings


async def get_manager(request: Request) -> EpisodeManager:
    manager = getattr(request.app.state, "manager", None)
    if manager is None:
        raise RuntimeError("the gateway is not started (no lifespan)")
    return manager


SettingsDep = Annotated[SettingsView, Depends(get_settings)]
ManagerDep = Annotated[EpisodeManager, Depends(get_manager)]
CallerDep = Annotated[Caller, Depends(authenticate)]
ReaderDep = Annotated[Caller, Depends(can_read)]
SubmitterDep = Annotated[Caller, Depends(can_submit)]
DocsCallerDep = Annotated[Caller, Depends(authenticate_docs)]
