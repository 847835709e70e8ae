"""Request-body limits, enforced before the application reads a body (a pure ASGI middleware).

* A request that carries a body to an API route is authenticated first, from its headers alone: without a
  valid token it gets 401 (or 429 after too many failures) and not one byte of its body is read.
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

from gateway.auth import Authenticator

log = logging.getLogger(__name__)

BODY_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
OPEN_PREFIXES = ("/v1/health", "/v1/ready", "/docs", "/redoc", "/openapi.json")


async def _answer(send: Send, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
    await _answer_json(send, status, {"detail": detail}, headers)


async def _answer_json(send: Send, status: int, content: Any, headers: dict[str, str] | None = None) -> None:
    body = json.dumps(content).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
           (b"connection", b"close")]
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
        if scope["method"] not in BODY_METHODS and "transfer-encoding" not in headers and headers.get(
            "content-length", "0"
        ) in ("", "0"):
            await self.app(scope, receive, send)  # no body (a GET with a body is held to the same rules)
            return
        path: str = scope.get("path", "")
        auth: Authenticator | None = getattr(scope["app"].state, "auth", None) if "app" in scope else None
        if auth is not None and path.startswith("/v1/") and not path.startswith(OPEN_PREFIXES):
            peer = scope["client"][0] if scope.get("client") else "unknown"
            client = auth.client_of(peer, [v.decode("latin-1") for k, v in raw_headers if k.lower() ==
                                           b"x-forwarded-for"])
            try:
                auth.identify(headers, client)
            except HTTPException as exc:
                await _answer(send, exc.status_code, str(exc.detail), dict(exc.headers or {}))
                return
        length = headers.get("content-length")
        if length is not None:
            if not length.isdigit():
                await _answer(send, 400, "Content-Length is not a number")
                return
            if int(length) > self.max_bytes:
                await _answer(send, 413, f"body of {length} bytes is over the cap of {self.max_bytes} bytes")
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
