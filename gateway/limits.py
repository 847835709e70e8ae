"""Request-body limits, enforced before the application reads a body (a pure ASGI middleware).

* Every request to an API route is authenticated and rate-limited here, from its headers alone, before the
  router and the dependencies run: without a valid token it gets 401 (or 429 after too many failures) and not
  one byte of its body is read; over its rate it gets 429 (a request with a body once that body, within the
  cap, is in: the keep-alive connection stays usable). The caller goes to the route's dependency in the request
  state (:data:`CALLER_STATE`), which checks its scope without identifying or admitting it a second time.
  A refusal answered here skips the router and FastAPI's dependency resolution, several times the check's cost.
* A submission (``POST /v1/questions``, ``/v1/tasks``) while the token is at its cap or every robot's queue is
  full gets 429 with ``Retry-After`` once its body is in, before it is parsed or routed (the connection stays
  open; :meth:`gateway.manager.EpisodeManager.refuse_if_full`, from memory; a full queue of the one robot a body
  names is refused by the route once the body is parsed).
* ``Content-Length`` over ``EQA_MAX_BODY_BYTES`` gets 413 at once; a body without a length (chunked) is read
  while counting and gets 413 as soon as it passes the cap. A body within the cap is handed to the
  application from memory (at most the cap per request).
* Slow and short bodies: the whole body must arrive within ``EQA_BODY_TIMEOUT_S`` (each ``receive()`` is
  timed against that deadline), else 408 and the connection is closed. A trickle of one byte every few seconds
  (slow-loris) and a body shorter than its ``Content-Length`` both end there instead of holding a connection
  and a task for ever.
* At most ``EQA_MAX_CONCURRENT_UPLOADS`` bodies are read at once; one more gets 503 with ``Retry-After`` at
  once (nothing of it read), so slow uploads cannot take every connection the server has.

Every refusal here is answered from the headers (or the bytes counted so far) on the event loop, without a
thread hop, a store call or a lock: it costs microseconds at any rate. The client address of the failed-auth
limit is the one :func:`gateway.auth.client_ip` gives (``X-Forwarded-For`` only from trusted proxies).
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from gateway.auth import CALLER_STATE, Authenticator, Caller, retry_after
from gateway.errors import TooManyError

log = logging.getLogger(__name__)

BODY_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
OPEN_PREFIXES = ("/v1/health", "/v1/ready", "/docs", "/redoc", "/openapi.json")
SUBMIT_PATHS = frozenset({"/v1/questions", "/v1/tasks"})  # a full queue (every robot's) or token cap: 429 unread


async def _answer(send: Send, status: int, detail: str, headers: dict[str, str] | None = None,
                  close: bool = True) -> None:
    await _answer_json(send, status, {"detail": detail}, headers, close)


async def _answer_json(send: Send, status: int, content: Any, headers: dict[str, str] | None = None,
                       close: bool = True) -> None:
    """``close``: the request's body (if any) stays unread, so the connection cannot carry another request."""
    body = json.dumps(content).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if close:
        raw.append((b"connection", b"close"))
    raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


class BodyLimit:
    """ASGI middleware: authenticate body-bearing API requests before reading, then cap the body."""

    def __init__(self, app: ASGIApp, max_bytes: int, timeout_s: float = 10.0, max_uploads: int = 32) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self.max_uploads = max_uploads
        self.uploads = 0  # bodies being read now (event loop only: no lock)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        raw_headers = scope.get("headers", [])
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in raw_headers}
        has_body = scope["method"] in BODY_METHODS or "transfer-encoding" in headers or headers.get(
            "content-length", "0") not in ("", "0")  # a GET with a body is held to the same rules
        path: str = scope.get("path", "")
        auth: Authenticator | None = getattr(scope["app"].state, "auth", None) if "app" in scope else None
        caller = None
        if auth is not None and path.startswith("/v1/") and not path.startswith(OPEN_PREFIXES):
            peer = scope["client"][0] if scope.get("client") else "unknown"
            client = auth.client_of(peer, [v.decode("latin-1") for k, v in raw_headers if k.lower() ==
                                           b"x-forwarded-for"])
            try:
                caller = auth.identify(headers, client)
            except HTTPException as exc:
                await _answer(send, exc.status_code, str(exc.detail), dict(exc.headers or {}), close=has_body)
                return
        length = headers.get("content-length")
        if has_body and length is not None:
            if not length.isdigit():
                await _answer(send, 400, "Content-Length is not a number")
                return
            if int(length) > self.max_bytes:
                await _answer(send, 413, f"body of {length} bytes is over the cap of {self.max_bytes} bytes")
                return
        if not has_body:
            if caller is None or await self._admit(auth, caller, scope, send):
                await self.app(scope, receive, send)
            return
        if self.uploads >= self.max_uploads:
            await _answer(send, 503, f"{self.uploads} request bodies are being received, the most at once "
                          "(EQA_MAX_CONCURRENT_UPLOADS); retry in a second", {"Retry-After": "1"})
            return
        self.uploads += 1
        try:
            body = await self._read(scope, receive, send, path)
        finally:
            self.uploads -= 1
        if body is None:
            return
        # over the rate: refused once the body is in (a body within the cap), so the connection stays usable
        if caller is not None and not await self._admit(auth, caller, scope, send):
            return
        if caller is not None and scope["method"] == "POST" and path in SUBMIT_PATHS and caller.can("submit"):
            manager = getattr(scope["app"].state, "manager", None)
            try:
                if manager is not None:
                    manager.refuse_if_full(caller, None)  # memory only; refuses only when every robot is full
            except TooManyError as exc:  # the body is read: the connection stays usable
                await _answer_json(send, exc.status_code, {"detail": exc.detail()},
                                   {"Retry-After": retry_after(exc.retry_after_s)}
                                   if exc.retry_after_s is not None else None, close=False)
                return
        if body and "json" in headers.get("content-type", ""):
            try:
                body.decode("utf-8")
            except UnicodeDecodeError:  # FastAPI would answer a bare 400; every body error is a 422 here
                detail = [{"loc": ["body"], "msg": "the body is not UTF-8 text: send JSON encoded as UTF-8",
                           "type": "json_invalid"}]
                await _answer_json(send, 422, {"detail": detail})
                return
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


    @staticmethod
    async def _admit(auth: Authenticator | None, caller: Caller, scope: Scope, send: Send) -> bool:
        """Take one request of the caller's rate (429 when over it) and hand the caller to the route's
        dependency; False once answered."""
        if auth is None:
            return True
        try:
            auth.admit(caller)
        except HTTPException as exc:
            await _answer(send, exc.status_code, str(exc.detail), dict(exc.headers or {}), close=False)
            return False
        scope.setdefault("state", {})[CALLER_STATE] = caller
        return True

    async def _read(self, scope: Scope, receive: Receive, send: Send, path: str) -> bytes | None:
        """The whole body, or None once answered (413 over the cap, 408 past the deadline) or disconnected."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timeout_s
        chunks: list[bytes] = []
        total = 0
        while True:
            try:
                message = await asyncio.wait_for(receive(), timeout=max(0.0, deadline - loop.time()))
            except TimeoutError:
                log.warning("%s %s: body not received whole within %g s (%d bytes came); 408", scope["method"], path,
                            self.timeout_s, total)
                await _answer(send, 408, f"the request body did not arrive within {self.timeout_s:g} s "
                              f"(EQA_BODY_TIMEOUT_S; {total} bytes came): send it whole, with a true Content-Length")
                return None
            if message["type"] == "http.disconnect":
                return None
            chunk = message.get("body", b"")
            total += len(chunk)
            if total > self.max_bytes:
                log.warning("%s %s: body over %d bytes refused while streaming", scope["method"], path, self.max_bytes)
                await _answer(send, 413, f"body over the cap of {self.max_bytes} bytes (EQA_MAX_BODY_BYTES)")
                return None
            chunks.append(chunk)
            if not message.get("more_body", False):
                return b"".join(chunks)
