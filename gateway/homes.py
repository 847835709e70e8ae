"""Homes at the gateway: which tenant holds which home, under which name, and the home's bounds.

A client names a home (``home`` on ``POST /v1/questions`` and ``POST /v1/tasks``); the gateway turns the name
into the internal id :func:`eqa.homes.home_id` of (tenant, name), which is all the services see
(``EpisodeStart.home``). So another tenant's token can neither read, use nor delete a home: the same name
under its token is a different home, and ``GET``/``DELETE /v1/homes/{name}`` of a name it never used is 404.

Store layout (the gateway's part; the home's memory is the mapper's, under ``eqa:home:{home}:*``):

* ``gw:home:{home}``        JSON :class:`HomeRecord` (owner tenant, client name, times, episodes submitted);
* ``gw:homes:o:{owner}``    sorted index (score: creation time) of a tenant's homes, for the paged list and
  the per-tenant bound ``EQA_HOMES_MAX_PER_TENANT``;
* ``gw:homes:used``         sorted index (score: last use) of every home, for retention
  (``EQA_HOMES_RETENTION_DAYS``).

Nothing here locks: :class:`gateway.manager.EpisodeManager` makes, bounds and deletes homes under its lock,
which also guards the active episodes a delete must not pull the memory from under; reads go without it.
"""

from __future__ import annotations

import logging
import time

from pydantic import BaseModel, ConfigDict, Field

from eqa import homes, keys
from eqa.homes import HomeSummary
from eqa.store import Store

log = logging.getLogger(__name__)

IDX_USED = "gw:homes:used"
MAX_PARTS_SHOWN = 64
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def record_key(home: str) -> str:
    return f"gw:home:{keys.check_id(home, 'home')}"


def idx_owner(owner: str) -> str:
    return f"gw:homes:o:{owner}"


class HomeRecord(BaseModel):
    """The gateway's record of one home."""

    model_config = ConfigDict(extra="forbid")
    home: str  # the internal id (eqa.homes.home_id)
    name: str  # the client's name
    owner: str  # the tenant
    house: str = ""  # the house its episodes run in (eqa.homes.house_of their scene; "": a real robot's world)
    created_at: float = Field(default_factory=time.time)
    last_used_at: float = Field(default_factory=time.time)
    episodes: int = Field(default=0, ge=0)  # episodes submitted naming it


class HomeInfo(BaseModel):
    """A home as ``GET /v1/homes/{name}`` shows it: the gateway's record and what the mapper stored of it."""

    name: str
    house: str = Field(description="the house (scene, changed versions included) its episodes run in; \"\": a real "
                       "robot's own world")
    created_at: float
    last_used_at: float
    age_s: float = Field(description="seconds since the home was first named")
    episodes_submitted: int = Field(description="episodes submitted naming this home")
    active_episodes: list[str] = Field(default_factory=list, description="its queued or running episodes")
    memory: HomeSummary | None = Field(
        default=None, description="what the mapper keeps of it (views, bytes, episodes that updated it, scenes); "
        "null until an episode of the home has been mapped"
    )
    parts: list[str] | None = Field(
        default=None, description=f"names of the parts of its memory in the store (at most {MAX_PARTS_SHOWN}; "
        "one home only, not in the list)"
    )
    map_png: str | None = Field(default=None, description="link of the picture of its map, when the mapper keeps one")


class HomeList(BaseModel):
    homes: list[HomeInfo]
    total: int = Field(description="homes this token holds")
    offset: int
    limit: int


class HomeDeleted(BaseModel):
    name: str
    deleted_keys: int = Field(description="store keys of the home's memory deleted")


class HomeRegistry:
    """Store I/O of the gateway's home records (writes under the manager's lock)."""

    def __init__(self, store: Store, memory_ttl_s: float) -> None:
        self.store = store
        self.memory_ttl_s = memory_ttl_s  # EQA_HOME_TTL_S: how long a reset's token outlives the reset
        self.reset_wait_s = 2.0  # a reset waits this long for a mapper's write-back, then answers 409

    def get(self, owner: str, name: str) -> HomeRecord | None:
        raw = self.store.get_json(record_key(homes.home_id(owner, name)))
        if raw is None:
            return None
        entry = HomeRecord.model_validate(raw)
        return entry if entry.owner == owner else None

    def count(self, owner: str) -> int:
        return self.store.index_len(idx_owner(owner))

    def use(self, owner: str, name: str, house: str, cap: int, now: float | None = None) -> HomeRecord | None:
        """The record of ``owner``'s home ``name`` after one more episode in ``house`` named it (made if new);
        None (and nothing written) when it is new and ``owner`` already holds ``cap`` homes."""
        now = time.time() if now is None else now
        entry = self.get(owner, name)
        if entry is None:
            if self.count(owner) >= cap:
                return None
            entry = HomeRecord(home=homes.home_id(owner, name), name=name, owner=owner, house=house, created_at=now,
                             last_used_at=now)
        entry.last_used_at = now
        entry.episodes += 1
        # the record before the indexes (a reader never finds an indexed home without its record), and both
        # indexes each time (a delete cut short after its index removals leaves a record that is indexed again)
        self.store.set_json(record_key(entry.home), entry.model_dump(mode="json"))
        self.store.index_add(idx_owner(owner), entry.home, entry.created_at)
        self.store.index_add(IDX_USED, entry.home, now)
        return entry

    def page(self, owner: str, limit: int, offset: int) -> list[HomeRecord]:
        """One page of ``owner``'s homes, newest first."""
        ids = self.store.index_page(idx_owner(owner), limit, offset)
        out = []
        for hid, raw in zip(ids, self.store.get_many([record_key(h) for h in ids]), strict=True):
            if raw is None:  # deleted since the index was read
                continue
            try:
                out.append(HomeRecord.model_validate_json(raw))
            except ValueError:
                log.warning("unreadable home record %s; skipped", hid)
        return out

    def summaries(self, records: list[HomeRecord]) -> list[HomeSummary | None]:
        """The mapper's summaries of ``records`` (one store round trip)."""
        raws = self.store.get_many([homes.summary_key(r.home) for r in records])
        out: list[HomeSummary | None] = []
        for r, raw in zip(records, raws, strict=True):
            try:
                out.append(None if raw is None else HomeSummary.model_validate_json(raw))
            except ValueError:
                log.warning("unreadable summary of home %s; shown as empty", r.home)
                out.append(None)
        return out

    def parts(self, entry: HomeRecord) -> list[str]:
        """Names of the stored parts of the home's memory (key suffixes after :func:`eqa.homes.prefix`)."""
        pre = homes.prefix(entry.home)
        return [k[len(pre):] for k in self.store.keys(pre)][:MAX_PARTS_SHOWN]

    def map_png(self, entry: HomeRecord) -> bytes | None:
        """The picture of the home's map the mapper keeps (PNG bytes), if any."""
        raw = self.store.get(homes.map_png_key(entry.home))
        return raw if raw is not None and raw.startswith(PNG_SIGNATURE) else None

    def delete(self, entry: HomeRecord) -> int:
        """Delete the home's memory (:func:`eqa.homes.delete_home`), then the gateway's index entries and record;
        the number of memory keys deleted. While a mapper writes an episode back into the home
        :class:`eqa.homes.HomeBusyError` is raised and nothing is deleted."""
        n = homes.delete_home(self.store, entry.home, self.memory_ttl_s, self.reset_wait_s)
        self.store.index_remove(idx_owner(entry.owner), [entry.home])
        self.store.index_remove(IDX_USED, [entry.home])
        self.store.delete(record_key(entry.home))
        return n

    def unused_since(self, cutoff: float, limit: int) -> list[HomeRecord]:
        """Homes last used before ``cutoff`` (oldest first, at most ``limit``)."""
        ids = self.store.index_below(IDX_USED, cutoff, limit)
        out = []
        for hid, raw in zip(ids, self.store.get_many([record_key(h) for h in ids]), strict=True):
            if raw is None:
                try:  # memory left without a record: nobody can name it
                    homes.delete_home(self.store, hid, self.memory_ttl_s)
                except homes.HomeBusyError:
                    log.info("home %s: being written; its memory goes at the next retention round", hid)
                    continue
                self.store.index_remove(IDX_USED, [hid])
                continue
            out.append(HomeRecord.model_validate_json(raw))
        return out
