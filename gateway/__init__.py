"""The HTTP gateway (FastAPI): submit questions, follow episodes, fetch results and recordings.

Routes (``/docs`` has the OpenAPI page with examples):

* ``POST /v1/questions`` -> 202 ``{episode_id, robot, state, max_steps, queue_position}``
* ``GET /v1/episodes`` (recent, ``?state=&limit=``), ``GET /v1/episodes/{id}`` (``EpisodeStatus``),
  ``DELETE /v1/episodes/{id}`` (cancel: publishes ``EpisodeCancel``)
* ``GET /v1/episodes/{id}/events``: Server-Sent Events, ids = Redis stream ids, resumable with
  ``Last-Event-ID``; ``GET /v1/episodes/{id}/recording``: merged Rerun ``.rrd``
* ``GET /v1/health`` (process up), ``GET /v1/ready`` (store, bus, services alive): open; without a token
  readiness says only ready or not
* ``/docs``, ``/redoc``, ``/openapi.json``: need the token when tokens are configured (bearer, or the
  password of HTTP Basic authentication for a browser)

Modules: :mod:`gateway.app` (app factory, lifespan, bus -> asyncio hand-off, error handlers),
:mod:`gateway.state` (the episode state machine, pure), :mod:`gateway.manager` (its I/O shell: persistence,
indexes and retention, queueing and limits, tenants, watchdog, restart reconciliation), :mod:`gateway.errors`
(what the episode logic refuses, one handler turns it into HTTP), :mod:`gateway.events` (compact JSON event
summaries), :mod:`gateway.auth` (tokens with scopes, tenants, rate and failed-auth limits),
:mod:`gateway.limits` (body cap and authentication before a body is read), :mod:`gateway.recordings`
(``rerun rrd merge``) and :mod:`gateway.routers` (HTTP). Test support (the gateway in a thread or a
process next to a real fleet, an SSE client) is ``tests/support/fleet.py``, outside the package.
"""
