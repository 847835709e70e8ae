"""``Annotated`` dependencies of the routes."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from eqa.settings import Settings
from gateway.auth import authenticate, authenticate_docs
from gateway.manager import EpisodeManager


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_manager(request: Request) -> EpisodeManager:
    manager = getattr(request.app.state, "manager", None)
    if manager is None:
        raise RuntimeError("the gateway is not started (no lifespan)")
    return manager


SettingsDep = Annotated[Settings, Depends(get_settings)]
ManagerDep = Annotated[EpisodeManager, Depends(get_manager)]
CallerDep = Annotated[str, Depends(authenticate)]
DocsCallerDep = Annotated[str, Depends(authenticate_docs)]
