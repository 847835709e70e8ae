"""Health (process up) and readiness (store reachable, bus open, which services are alive). Open routes:
no token needed."""

from __future__ import annotations

from fastapi import APIRouter, Response, status
from starlette.concurrency import run_in_threadpool

from gateway.deps import ManagerDep, SettingsDep
from gateway.schemas import Health, Readiness

router = APIRouter(prefix="/v1", tags=["health"])


@router.get("/health", response_model=Health, summary="Liveness: the gateway process answers")
def health(settings: SettingsDep) -> Health:
    return Health(instance=settings.instance)


@router.get(
    "/ready",
    response_model=Readiness,
    summary="Readiness: store, bus and the services' liveliness",
    responses={503: {"model": Readiness, "description": "not ready: see `missing`, `store`, `bus`"}},
)
async def ready(manager: ManagerDep, response: Response) -> Readiness:
    store_ok = await run_in_threadpool(manager.store.ping)
    try:
        bus_ok = manager.bus.session is not None
    except RuntimeError:  # closed
        bus_ok = False
    missing = manager.missing_services()
    robots = await run_in_threadpool(manager.robots) if store_ok else {}
    body = Readiness(
        ready=store_ok and bus_ok and not missing,
        store=store_ok,
        bus=bus_ok,
        services=manager.alive_services(),
        missing=missing,
        robots=robots,
    )
    if not body.ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    return body
