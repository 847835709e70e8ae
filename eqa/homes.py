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
* ``eqa:home:{home}:*``        the mapper's parts of the home (its map and view memory).
"""

from __future__ import annotations

import hashlib
import re
import time

from pydantic import BaseModel, ConfigDict, Field

from eqa import keys
from eqa.store import Store

PREFIX = "eqa:home:"
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
    created_at: float = Field(default_factory=time.time)
    updated_at: float = Field(default_factory=time.time)
    scenes: list[str] = Field(default_factory=list, max_length=64)  # scenes its episodes ran in


def read_summary(store: Store, home: str) -> HomeSummary | None:
    """The stored summary of ``home`` (None when the home holds nothing)."""
    data = store.get_json(summary_key(home))
    return None if data is None else HomeSummary.model_validate(data)


def write_summary(store: Store, summary: HomeSummary, ttl_s: float | None = None) -> None:
    store.set_json(summary_key(summary.home), summary.model_dump(mode="json"), ttl_s=ttl_s)


def delete_home(store: Store, home: str) -> int:
    """Delete every key of ``home``; the number of keys deleted."""
    found = store.keys(prefix(home))
    if found:
        store.delete_many(found)
    return len(found)
