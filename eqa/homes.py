"""Homes: the store layout of a house's persistent memory, shared by the mapper (which writes it) and the
gateway (which lists, sizes and deletes it).

A home is named by the client (``home`` on ``POST /v1/questions`` and ``POST /v1/tasks``) and belongs to the
tenant of the token that first used it. On the bus and in the store a home is its *internal id*
(:func:`home_id`): a hash of (tenant, client name), so two tenants' homes of the same name never meet and no
service but the gateway needs to know about tenants.

Store layout (every key of one home starts with :func:`prefix`):

* ``eqa:home:{home}:summary``  JSON :class:`HomeSummary`, rewritten by the mapper whenever the home changes;
* ``eqa:home:{home}:map.png``  optional: a PNG picture of the home's map, which the gateway serves and the
  console shows as it is (``GET /v1/homes/{name}/map.png``);
* ``eqa:home:{home}:lock``     held by whoever writes or deletes the home (:func:`take_lock`): its holder's token;
* ``eqa:home:{home}:*``        the mapper's parts of the home (its map and view memory);
* ``eqa:homereset:{home}``     a token written by every reset (:func:`delete_home`), outside the home's prefix
  so it outlives the reset: an episode that started before a reset and ends after it finds another token and
  does not write its memory back into the home the user emptied.
"""

from __future__ import annotations

import hashlib
import logging
import re
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

from pydantic import BaseModel, ConfigDict, Field

from eqa import keys
from eqa.store import Store

log = logging.getLogger(__name__)

PREFIX = "eqa:home:"
RESET_PREFIX = "eqa:homereset:"
LOCK_TTL_S = 30.0  # a dead holder blocks the home this long at most
# A generated house after k rounds of changes (services.sim.changes): the same house, so the same home.
CHANGED_SCENE = re.compile(r"^(gen-\d{1,9})-c(\d{1,3})$")


def house_of(scene: str) -> str:
    """The house a scene id shows: ``gen-00042-c2`` (house gen-00042 after two rounds of changes) is
    ``gen-00042``; any other id (``""``: a real robot's own world) is its own house. A home is one house."""
    m = CHANGED_SCENE.match(scene)
    return m.group(1) if m else scene


def home_id(tenant: str, name: str) -> str:
    """The internal id of the client's home ``name`` of ``tenant`` (safe as a key chunk, 18 characters)."""
    keys.check_id(name, "home")
    digest = hashlib.blake2b(f"{tenant}\x00{name}".encode(), digest_size=8).hexdigest()
    return f"h-{digest}"


def prefix(home: str) -> str:
    """The store prefix of every key of one home."""
    return f"{PREFIX}{keys.check_id(home, 'home')}:"


def summary_key(home: str) -> str:
    return prefix(home) + "summary"


def map_png_key(home: str) -> str:
    return prefix(home) + "map.png"


class HomeSummary(BaseModel):
    """What a home holds, for ``GET /v1/homes/{id}`` and for the per-home bounds."""

    model_config = ConfigDict(extra="forbid")
    home: str
    episodes: int = Field(default=0, ge=0)  # episodes that updated the home
    views: int = Field(default=0, ge=0)  # keyframes in the view memory
    bytes: int = Field(default=0, ge=0)  # stored size of the home's parts
    gaussians: int = Field(default=0, ge=0)  # in the HELIOS object layer its task episodes left
    created_at: float = Field(default_factory=time.time)
    updated_at: float = Field(default_factory=time.time)
    scenes: list[str] = Field(default_factory=list, max_length=64)  # scenes its episodes ran in


def read_summary(store: Store, home: str) -> HomeSummary | None:
    """The stored summary of ``home`` (None when the home holds nothing)."""
    data = store.get_json(summary_key(home))
    return None if data is None else HomeSummary.model_validate(data)


def write_summary(store: Store, summary: HomeSummary, ttl_s: float | None = None) -> None:
    store.set_json(summary_key(summary.home), summary.model_dump(mode="json"), ttl_s=ttl_s)


class HomeBusyError(RuntimeError):
    """The home's lock is held (its memory is being written) longer than a caller waits."""


def lock_key(home: str) -> str:
    return prefix(home) + "lock"


def reset_key(home: str) -> str:
    return f"{RESET_PREFIX}{keys.check_id(home, 'home')}"


def take_lock(store: Store, home: str, holder: str, wait_s: float, ttl_s: float | None = None) -> str | None:
    """Take the home's lock, waiting up to ``wait_s``: its token (``holder`` and a random part, so two takes by
    one instance differ), or None when another holder kept it that long. The lock expires after ``ttl_s``
    (:data:`LOCK_TTL_S`) so that a dead holder does not block the home; a live holder slower than that loses it,
    and its release (:func:`release_lock`) then deletes nothing: it names the token it took, and the store
    deletes the key only while it still holds that token (``Store.delete_if_equal``). What the holder writes
    must therefore be guarded on its own (the mapper's commit: a compare-and-set on the home's index,
    ``Store.set_many_if``)."""
    token = f"{holder}:{uuid.uuid4().hex}"
    deadline = time.monotonic() + wait_s
    while True:
        if store.set_if_absent(lock_key(home), token.encode(), ttl_s=LOCK_TTL_S if ttl_s is None else ttl_s):
            return token
        if time.monotonic() > deadline:
            return None
        time.sleep(0.05)


def release_lock(store: Store, home: str, token: str) -> bool:
    """Release the home's lock taken with ``token``: True when it was still held by it (deleted), False when it
    had expired (and maybe been taken by another holder, whose lock stays)."""
    return store.delete_if_equal(lock_key(home), token.encode())


@contextmanager
def locked(store: Store, home: str, holder: str, wait_s: float, ttl_s: float | None = None) -> Iterator[str | None]:
    """The home's lock for the ``with`` block (:func:`take_lock`): yields its token (None: not taken); a taken
    lock is released at the block's end, whatever happens in it, if it is still this holder's."""
    token = take_lock(store, home, holder, wait_s, ttl_s)
    try:
        yield token
    finally:
        if token is not None and not release_lock(store, home, token):
            log.warning("home %s: the lock of %s expired before its release (held past its TTL)", home, holder)


def reset_mark(store: Store, home: str) -> str | None:
    """The token of the home's last reset (None: never reset, or so long ago that its memory expired too)."""
    raw = store.get(reset_key(home))
    return None if raw is None else raw.decode("ascii", "replace")


def delete_home(store: Store, home: str, mark_ttl_s: float, wait_s: float = 2.0) -> int:
    """Reset ``home``: under its lock, write a new reset token (kept ``mark_ttl_s``: the home's TTL, the longest
    an episode's memory could still be written back) and delete every key of the home; the number of keys
    deleted. :class:`HomeBusyError` when a mapper holds the lock (it is writing an episode back) past
    ``wait_s``: nothing is deleted then."""
    with locked(store, home, "reset", wait_s) as taken:
        if not taken:
            raise HomeBusyError(f"home {home}: its memory is being written; try again in a few seconds")
        store.set(reset_key(home), uuid.uuid4().hex.encode(), ttl_s=mark_ttl_s)
        found = [k for k in store.keys(prefix(home)) if k != lock_key(home)]
        if found:
            store.delete_many(found)
        return len(found)
