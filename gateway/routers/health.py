"""Health (process up) and readiness (store reachable, bus open, which services are alive). Open routes:
no token needed; without one, readiness says only ready or not (no episode ids, no instance names)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from starlette.concurrency import run_in_threadpool

from gateway.auth import optional_caller
from gateway.deps import ManagerDep, SettingsDep
from gateway.schemas import Health, Readiness

router = APIRouter(prefix="/v1", tags=["health"])


@router.get("/health", response_model=Health, summary="Liveness: the gateway process answers")
def health(settings: SettingsDep) -> Health:
    return Health(instance=settings.instance)


@router.get(
    "/ready",
    response_model=Readiness,
    response_model_exclude_none=True,
    summary="Readiness: store, bus and the services' liveliness (details with a token)",
    description="Without a valid token (when EQA_API_TOKENS is set) only `ready`; with one also the store, bus "
    "and service details, and the robots' episodes (another tenant's show as `busy`; all with admin).",
    responses={503: {"model": Readiness, "description": "not ready", "content": {
        "application/json": {"example": {"ready": False}}}}},
)
async def ready(manager: ManagerDep, request: Request, response: Response) -> Readiness:
    caller = optional_caller(request)
    store_ok = await run_in_threadpool(manager.store.ping)
    try:
        bus_ok = manager.bus.session is not None
    except RuntimeError:  # closed
        bus_ok = False
    missing = manager.missing_services()
    ok = store_ok and bus_ok and not missing
    if not ok:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    if caller is None:
        return Readiness(ready=ok)
    robots = await run_in_threadpool(manager.robots, caller) if store_ok else {}
    return Readiness(
        ready=ok,
        store=store_ok,
        bus=bus_ok,
        services=manager.alive_services(),
        missing=missing,
        robots=robots,
    )
