"""Bearer tokens with scopes, tenants, a per-token rate limit and a per-client limit on failed authentication.

``EQA_API_TOKENS`` lists tokens, each ``token`` or ``token:scope+scope`` with the scopes ``submit`` (POST a
question, cancel one's own episodes), ``read`` (status, list, events, recording of one's own episodes) and
``admin`` (everything, every tenant's episodes, the readiness details). A bare token has ``submit+read``.
Each token is a tenant: an episode belongs to the token that created it, and every other non-admin token gets
404 for it, as for an episode that does not exist. The tenant id stored with an episode is a hash of the
token (``t-<16 hex>``), never the token. With ``EQA_API_TOKENS`` empty authentication is off (local use):
every caller is the tenant ``anon`` with every scope, and the rate limit applies per client address.

Tokens are compared in constant time. Failed authentication is limited without ever refusing a valid token:
a request is checked for a valid token first, and one that carries one is served whatever other requests from
its address did (behind a NAT or a reverse proxy one address is many users). Wrong or missing tokens are
counted per client address (``EQA_AUTH_FAILURES_PER_MIN``) and wrong tokens also per token prefix (their first
:data:`PREFIX_CHARS` characters, from any address: ``EQA_AUTH_FAILURES_PER_PREFIX_PER_MIN``); over either a
wrong token gets 429 with ``Retry-After`` instead of 401 until the bucket refills. So the limit bounds the
failed attempts a client can make and what they cost; it does not make a guessable token safe: tokens must be
long random strings (``eqa`` warns at start about tokens shorter than :data:`MIN_TOKEN_CHARS`).

The client address is the TCP peer, or, when the peer is one of ``EQA_TRUSTED_PROXIES`` (CIDRs), the address
its ``X-Forwarded-For`` names (read from the right, skipping trusted proxies): a client that is not a trusted
proxy cannot choose its address by sending the header (:func:`client_ip`).

The API documentation (``/docs``, ``/redoc``, ``/openapi.json``) needs a token too when tokens are
configured. A browser cannot send a bearer header when it opens a page, so those three routes also take the
token as the password of HTTP Basic authentication (any user name): their 401 answer offers both schemes,
the browser asks for the credentials once and sends them with the page and with its fetch of the spec.
The API routes themselves take only ``Authorization: Bearer <token>``.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import ipaddress
import logging
import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass

from fastapi import HTTPException, Request, status

from eqa.settings import SettingsGroup

CALLER_STATE = "eqa_caller"  # request-state key of the caller gateway.limits.BodyLimit identified and admitted

log = logging.getLogger(__name__)

SCOPES = ("submit", "read", "admin")
DEFAULT_SCOPES = frozenset({"submit", "read"})
ANONYMOUS = "anon"
PREFIX_CHARS = 6  # wrong tokens sharing their first characters share a failure bucket
MIN_TOKEN_CHARS = 24  # shorter tokens are logged as guessable at start
MAX_FORWARDED_HOPS = 32  # X-Forwarded-For entries looked at (from the right)

Network = ipaddress.IPv4Network | ipaddress.IPv6Network


@dataclass(frozen=True)
class Caller:
    """Who calls: ``tenant`` owns the episodes it submits; ``key`` is its rate-limit bucket."""

    tenant: str
    scopes: frozenset[str]
    key: str

    @property
    def admin(self) -> bool:
        return "admin" in self.scopes

    def can(self, scope: str) -> bool:
        return self.admin or scope in self.scopes

    def sees(self, owner: str) -> bool:
        """True when this caller may see an episode of tenant ``owner``."""
        return self.admin or owner == self.tenant


def tenant_of(token: str) -> str:
    return "t-" + hashlib.sha256(token.encode()).hexdigest()[:16]


def parse_tokens(entries: list[str]) -> dict[str, frozenset[str]]:
    """``token -> scopes`` from ``EQA_API_TOKENS`` entries; ``ValueError`` names a bad entry."""
    out: dict[str, frozenset[str]] = {}
    for entry in entries:
        token, sep, scopes_text = entry.partition(":")
        if not token or any(c.isspace() for c in token) or any(ord(c) < 32 for c in token):
            raise ValueError("an EQA_API_TOKENS entry has an empty token or one with spaces or control characters")
        scopes = frozenset(s.strip() for s in scopes_text.split("+") if s.strip()) if sep else DEFAULT_SCOPES
        unknown = scopes - set(SCOPES)
        if not scopes or unknown:
            raise ValueError(
                f"EQA_API_TOKENS entry for token {token[:4]}...: unknown scope(s) {sorted(unknown) or '(none)'}; "
                f"write token:scope+scope with scopes from {', '.join(SCOPES)}"
            )
        out[token] = scopes
    return out


class RateLimiter:
    """Token bucket per key: ``rate`` requests per second sustained, bursts up to ``burst``."""

    def __init__(self, rate: float, burst: float | None = None, max_keys: int = 10_000) -> None:
        self.rate = float(rate)
        self.burst = float(burst if burst is not None else max(1.0, rate))
        self.max_keys = max_keys
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def _level(self, key: str, now: float) -> float:
        tokens, last = self._buckets.get(key, (self.burst, now))
        return min(self.burst, tokens + (now - last) * self.rate)

    def allow(self, key: str, now: float | None = None) -> tuple[bool, float]:
        """``(allowed, seconds until the next request would be allowed)``; an allowed request takes a token."""
        now = time.monotonic() if now is None else now
        with self._lock:
            tokens = self._level(key, now)
            if tokens >= 1.0:
                self._buckets[key] = (tokens - 1.0, now)
                ok, wait = True, 0.0
            else:
                self._buckets[key] = (tokens, now)
                ok, wait = False, (1.0 - tokens) / self.rate
            if len(self._buckets) > self.max_keys:  # forget idle clients, then (many at once) the oldest half
                for k in [k for k, (_, t) in self._buckets.items() if now - t > 60]:
                    del self._buckets[k]
                if len(self._buckets) > self.max_keys:
                    for k in sorted(self._buckets, key=lambda k: self._buckets[k][1])[: len(self._buckets) // 2]:
                        del self._buckets[k]
        return ok, wait

    def blocked(self, key: str, now: float | None = None) -> float:
        """Seconds until ``key`` has a token again (0 when it has one now); takes nothing."""
        now = time.monotonic() if now is None else now
        with self._lock:
            tokens = self._level(key, now)
        return 0.0 if tokens >= 1.0 else (1.0 - tokens) / self.rate


def retry_after(seconds: float) -> str:
    return str(max(1, math.ceil(seconds)))


def parse_networks(cidrs: list[str]) -> tuple[Network, ...]:
    """``EQA_TRUSTED_PROXIES`` entries as networks (a bare address is a /32 or /128)."""
    return tuple(ipaddress.ip_network(c.strip(), strict=False) for c in cidrs if c.strip())


def _ip(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(text.strip().strip("[]"))
    except ValueError:
        return None


def client_ip(peer: str, forwarded: list[str], trusted: tuple[Network, ...]) -> str:
    """The client address of a request from TCP peer ``peer`` with ``X-Forwarded-For`` values ``forwarded``:
    the peer itself unless it is a trusted proxy; then the entry the proxy appended (the rightmost), and on
    leftwards while that one is a trusted proxy too. An entry that is not an address stops the walk at the
    last trusted hop (whose address is then the client's: a broken proxy header lumps its clients together
    rather than letting them pick an address). Pure."""
    if not trusted:
        return peer
    hops = [h for value in forwarded for h in value.split(",") if h.strip()][-MAX_FORWARDED_HOPS:]
    addr = peer
    while hops:
        ip = _ip(addr)
        if ip is None or not any(ip in net for net in trusted):
            break
        nxt = hops.pop()
        if _ip(nxt) is None:
            break
        addr = str(_ip(nxt))
    return addr


class Authenticator:
    """Token check, tenants and scopes, failed-auth limits (per client address, per token prefix) that never
    refuse a valid token, rate limit per caller, client address behind trusted proxies."""

    def __init__(self, settings: SettingsGroup) -> None:
        self.tokens = parse_tokens(list(settings.api_tokens))
        self.limiter = RateLimiter(settings.rate_limit_per_s)
        per_min = settings.auth_failures_per_min
        self.failures = RateLimiter(per_min / 60.0, burst=max(1.0, per_min))
        per_prefix = settings.auth_failures_per_prefix_per_min
        self.prefix_failures = RateLimiter(per_prefix / 60.0, burst=max(1.0, per_prefix))
        self.trusted = parse_networks(list(settings.trusted_proxies))
        short = [t[:4] + "..." for t in self.tokens if len(t) < MIN_TOKEN_CHARS]
        if short:
            log.warning("%d API token(s) shorter than %d characters (%s): a failure limit does not make a short "
                        "token safe; use long random tokens (e.g. `openssl rand -hex 24`)", len(short),
                        MIN_TOKEN_CHARS, ", ".join(short))

    @property
    def enabled(self) -> bool:
        return bool(self.tokens)

    def lookup(self, presented: str | None) -> frozenset[str] | None:
        return lookup_token(self.tokens, presented)

    def client_of(self, peer: str, forwarded: list[str]) -> str:
        return client_ip(peer, forwarded, self.trusted)

    def identify(self, headers: Mapping[str, str], client: str, allow_basic: bool = False) -> Caller:
        """The caller of a request, or :class:`HTTPException` 401 (bad or missing token) / 429 (a wrong or
        missing token from a client, or of a token prefix, that failed too often). A valid token is never
        refused here. Rate limit not applied here (see :meth:`admit`)."""
        if not self.enabled:
            return Caller(tenant=ANONYMOUS, scopes=frozenset(SCOPES), key=f"addr:{client}")
        token, via = bearer_token(headers), "bearer token"
        if token is None and allow_basic:
            token, via = basic_password(headers), "token (basic auth password)"
        scopes = self.lookup(token)
        if scopes is not None:
            tenant = tenant_of(token)  # type: ignore[arg-type]
            return Caller(tenant=tenant, scopes=scopes, key=f"tenant:{tenant}")
        prefix = None if token is None else "p-" + hashlib.sha256(token[:PREFIX_CHARS].encode()).hexdigest()[:16]
        wait = self.failures.blocked(client)
        what = f"from {client}"
        if prefix is not None and wait <= 0:
            wait, what = self.prefix_failures.blocked(prefix), "with tokens of this prefix"
        if wait > 0:
            raise HTTPException(
                status.HTTP_429_TOO_MANY_REQUESTS,
                detail=f"too many failed authentications {what}; wait {retry_after(wait)} s (a valid token is "
                "still served)",
                headers={"Retry-After": retry_after(wait)},
            )
        self.failures.allow(client)  # one failure taken from this client's bucket
        if prefix is not None:
            self.prefix_failures.allow(prefix)
        challenge = 'Bearer, Basic realm="EQA gateway API docs", charset="UTF-8"' if allow_basic else "Bearer"
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            detail="missing bearer token" if token is None else f"invalid {via}",
            headers={"WWW-Authenticate": challenge},
        )

    def admit(self, caller: Caller) -> None:
        """429 with ``Retry-After`` over the caller's request rate."""
        ok, wait = self.limiter.allow(caller.key)
        if not ok:
            raise HTTPException(
                status.HTTP_429_TOO_MANY_REQUESTS,
                detail=f"rate limit of {self.limiter.rate:g} requests/s exceeded",
                headers={"Retry-After": retry_after(wait)},
            )


def bearer_token(headers: Mapping[str, str]) -> str | None:
    header = headers.get("authorization", "")
    scheme, _, token = header.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        return None
    return token.strip()


def basic_password(headers: Mapping[str, str]) -> str | None:
    """The password of an ``Authorization: Basic`` header (the token, for the documentation routes)."""
    header = headers.get("authorization", "")
    scheme, _, blob = header.partition(" ")
    if scheme.lower() != "basic" or not blob.strip():
        return None
    try:
        decoded = base64.b64decode(blob.strip(), validate=True).decode("utf-8")
    except (binascii.Error, UnicodeDecodeError):
        return None
    _user, sep, password = decoded.partition(":")
    return password if sep and password else None


def lookup_token(tokens: dict[str, frozenset[str]], presented: str | None) -> frozenset[str] | None:
    """Scopes of a presented token (constant time over the token list), or None."""
    if presented is None:
        return None
    found: frozenset[str] | None = None
    raw = presented.encode()
    for token, scopes in tokens.items():  # no early exit
        if hmac.compare_digest(token.encode(), raw):
            found = scopes
    return found


def check_token(tokens: list[str], presented: str | None) -> bool:
    """True when ``presented`` is one of ``tokens`` (entries may carry ``:scopes``)."""
    return lookup_token(parse_tokens(tokens), presented) is not None


def client_address(request: Request) -> str:
    """The client address of a request (:func:`client_ip`: the peer, or behind a trusted proxy the client)."""
    peer = request.client.host if request.client else "unknown"
    auth: Authenticator = request.app.state.auth
    return auth.client_of(peer, request.headers.getlist("x-forwarded-for"))


def _caller(request: Request, allow_basic: bool, scope: str | None) -> Caller:
    auth: Authenticator = request.app.state.auth
    # identified and admitted (rate) already by gateway.limits.BodyLimit, before the router ran
    caller: Caller | None = None if allow_basic else request.scope.get("state", {}).get(CALLER_STATE)
    if caller is None:
        caller = auth.identify(request.headers, client_address(request), allow_basic=allow_basic)
        auth.admit(caller)
    if scope is not None and not caller.can(scope):
        raise HTTPException(
            status.HTTP_403_FORBIDDEN,
            detail=f"this token lacks the {scope!r} scope (it has {'+'.join(sorted(caller.scopes))}); "
            f"give it in EQA_API_TOKENS as token:{'+'.join(sorted({*caller.scopes, scope}))}",
        )
    return caller


async def authenticate(request: Request) -> Caller:
    """FastAPI dependency: 401 without a valid bearer token (when tokens are configured), 429 over the
    rate limit or after too many failures. Async: it does no I/O, so it runs on the event loop."""
    return _caller(request, allow_basic=False, scope=None)


async def can_submit(request: Request) -> Caller:
    return _caller(request, allow_basic=False, scope="submit")


async def can_read(request: Request) -> Caller:
    return _caller(request, allow_basic=False, scope="read")


async def authenticate_docs(request: Request) -> Caller:
    """The same for ``/docs``, ``/redoc`` and ``/openapi.json``: the token as a bearer token or as the
    password of HTTP Basic authentication (what a browser can send when it opens the page)."""
    return _caller(request, allow_basic=True, scope=None)


def optional_caller(request: Request) -> Caller | None:
    """The caller when the request carries a valid token (or auth is off), else None; never raises and
    takes no rate-limit token (``/v1/ready``)."""
    auth: Authenticator = request.app.state.auth
    if not auth.enabled:
        return Caller(tenant=ANONYMOUS, scopes=frozenset(SCOPES), key="")
    scopes = auth.lookup(bearer_token(request.headers))
    if scopes is None:
        return None
    return Caller(tenant=tenant_of(bearer_token(request.headers) or ""), scopes=scopes, key="")
