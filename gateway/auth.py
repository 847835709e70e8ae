"""Bearer-token authentication and a per-token rate limit (token bucket).

With ``EQA_API_TOKENS`` empty authentication is off (local use); the rate limit then applies per client
address. Tokens are compared in constant time.

The API documentation (``/docs``, ``/redoc``, ``/openapi.json``) needs a token too when tokens are
configured. A browser cannot send a bearer header when it opens a page, so those three routes also take the
token as the password of HTTP Basic authentication (any user name): their 401 answer offers both schemes,
the browser asks for the credentials once and sends them with the page and with its fetch of the spec.
The API routes themselves take only ``Authorization: Bearer <token>``.
"""

from __future__ import annotations

import base64
import binascii
import hmac
import threading
import time

from fastapi import HTTPException, Request, status


class RateLimiter:
    """Token bucket per key: ``rate`` requests per second sustained, bursts up to ``burst``."""

    def __init__(self, rate: float, burst: float | None = None, max_keys: int = 10_000) -> None:
        self.rate = float(rate)
        self.burst = float(burst if burst is not None else max(1.0, rate))
        self.max_keys = max_keys
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def allow(self, key: str, now: float | None = None) -> tuple[bool, float]:
        """``(allowed, seconds until the next request would be allowed)``."""
        now = time.monotonic() if now is None else now
        with self._lock:
            tokens, last = self._buckets.get(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - last) * self.rate)
            if tokens >= 1.0:
                self._buckets[key] = (tokens - 1.0, now)
                ok, wait = True, 0.0
            else:
                self._buckets[key] = (tokens, now)
                ok, wait = False, (1.0 - tokens) / self.rate
            if len(self._buckets) > self.max_keys:  # forget idle clients
                for k in [k for k, (_, t) in self._buckets.items() if now - t > 60]:
                    del self._buckets[k]
        return ok, wait


def bearer_token(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    return token.strip()


def basic_password(request: Request) -> str | None:
    """The password of an ``Authorization: Basic`` header (the token, for the documentation routes)."""
    header = request.headers.get("authorization", "")
    scheme, _, blob = header.partition(" ")
    if scheme.lower() != "basic" or not blob.strip():
        return None
    try:
        decoded = base64.b64decode(blob.strip(), validate=True).decode("utf-8")
    except (binascii.Error, UnicodeDecodeError):
        return None
    _user, sep, password = decoded.partition(":")
    return password if sep and password else None


def check_token(tokens: list[str], presented: str | None) -> bool:
    if presented is None:
        return False
    hit = False
    for t in tokens:  # no early exit: constant time over the token list
        hit |= hmac.compare_digest(t.encode(), presented.encode())
    return hit


def _caller(request: Request, allow_basic: bool) -> str:
    """Check the token (when tokens are configured) and the rate limit; return the caller's identity."""
    settings = request.app.state.settings
    limiter: RateLimiter = request.app.state.limiter
    if settings.api_tokens:
        token, via = bearer_token(request), "bearer token"
        if token is None and allow_basic:
            token, via = basic_password(request), "token (basic auth password)"
        if not check_token(settings.api_tokens, token):
            challenge = 'Bearer, Basic realm="EQA gateway API docs", charset="UTF-8"' if allow_basic else "Bearer"
            raise HTTPException(
                status.HTTP_401_UNAUTHORIZED,
                detail="missing bearer token" if token is None else f"invalid {via}",
                headers={"WWW-Authenticate": challenge},
            )
        who = f"token:{token}"
    else:
        who = f"addr:{request.client.host if request.client else 'unknown'}"
    ok, wait = limiter.allow(who)
    if not ok:
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            detail=f"rate limit of {limiter.rate:g} requests/s exceeded",
            headers={"Retry-After": str(max(1, round(wait + 0.5)))},
        )
    return who


async def authenticate(request: Request) -> str:
    """FastAPI dependency: 401 without a valid bearer token (when tokens are configured), 429 over the
    rate limit. Returns the caller's identity (the token, or the client address with auth off). Async: it
    does no I/O, so it runs on the event loop instead of costing a worker-thread hop per request."""
    return _caller(request, allow_basic=False)


async def authenticate_docs(request: Request) -> str:
    """The same for ``/docs``, ``/redoc`` and ``/openapi.json``: the token as a bearer token or as the
    password of HTTP Basic authentication (what a browser can send when it opens the page)."""
    return _caller(request, allow_basic=True)
