"""Episode bookkeeping of the gateway: submit, queue per robot, start, follow, end, cancel, watchdog, and
reconciliation after a restart. Everything is persisted in the :class:`eqa.store.Store` (Redis in
production), so a restarted gateway loses no episode and no stored event.

Store layout (all keys under ``gw:``):

* ``gw:ep:{episode_id}``  JSON ``{"status": EpisodeStatus, "start": EpisodeStart, "owner": tenant}`` - the
  episode record (``owner``: the tenant of the token that submitted it, :mod:`gateway.auth`).
* ``gw:ev:{episode_id}``  stream of compact JSON events (:mod:`eqa.event_log`; after a restart backfilled from
  the services' journals); the entry ids are the SSE event ids, so a client resuming with ``Last-Event-ID``
  gets every stored event exactly once.
* ``gw:robot:{robot}``    id of the episode running on the robot (absent = robot free).
* ``gw:queue:{robot}``    JSON list of queued episode ids (``EQA_BUSY_POLICY=queue``), at most
  ``EQA_QUEUE_MAX_PER_ROBOT``.
* ``gw:idx:all``, ``gw:idx:o:{owner}``, ``gw:idx:s:{state}``, ``gw:idx:o:{owner}:s:{state}`` - sorted
  indexes (score: creation time) of every stored episode, per tenant, per final state: the list route reads
  one page of one index and the records of that page (no scan of all records); ``gw:idx:active`` the queued
  and running ones (what a restarted gateway reconciles).
* ``gw:home:{home}``, ``gw:homes:*`` - the homes of each tenant (:mod:`gateway.homes`); an episode naming a home
  carries its internal id in ``EpisodeStart.home``.

Retention: ended episodes past ``EQA_EPISODE_RETENTION_COUNT`` (the oldest first) or older than
``EQA_EPISODE_RETENTION_DAYS`` are deleted with their events and recordings (:meth:`EpisodeManager.prune`,
run by the watchdog loop). Queued and running episodes are never pruned.

The state machine itself is pure (:mod:`gateway.state`); this module is its I/O shell.

Restart semantics. Bus messages published while no gateway runs are not seen by any gateway, but every
service journals what it publishes before publishing it (:mod:`eqa.event_log`). On start the gateway
reconciles: every episode stored as ``running`` gets a ``gateway_restart`` event (naming the time of the last
event it saw), then the events of the services' journals that its stream lacks (marked ``backfilled``; one
that also arrives live afterwards is stored once), and its watchdog clock restarts from the restart time.
The gateway alone writes ``gw:ev:*``; each service alone writes its journal (one writer per key).
If the services are still working on it, its later events are picked up live and the episode ends
normally on the stopper's ``EpisodeEnd``. If the episode ended while the gateway was down, the stopper's
copy of the ``EpisodeEnd`` in the store (``eqa:stopper:end:{episode_id}``, written before it publishes)
ends it with the stopper's answer and reason, at reconciliation or at the latest when the watchdog would
fire; the recovered ``episode_end`` event is marked ``recovered``. Only when no end is stored either does the
watchdog fail the episode after ``EQA_EPISODE_TIMEOUT_S``, with a reason saying that nothing arrived, which
services are not alive, and that the gateway restarted meanwhile. Queued episodes start as soon as their
robot is free. Every event stream ends with exactly one ``episode_end`` event (from the stopper or made by
the gateway).
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

from eqa import dataflow, keys
from eqa import homes as homes_layout
from eqa.budget import STEPS_PER_SQRT_M2, TASK_STEPS_PER_SQRT_M2, steps_for
from eqa.bus import Bus
from eqa.event_log import JOURNAL_SERVICES, Identity, event_identity, missing_events
from eqa.messages import (
    Ablation,
    EpisodeCancel,
    EpisodeStart,
    EpisodeStatus,
    ErrorReply,
    Message,
    Question,
    Task,
    new_id,
)
from eqa.recording import recording_dir
from eqa.settings import SettingsGroup
from eqa.store import Store, StoreUnavailable, episode_journal_key, stored_end, task_trace_key
from gateway import metrics as gateway_metrics
from gateway import state as lifecycle
from gateway.auth import ANONYMOUS, Caller, RateLimiter
from gateway.errors import (
    BusyError,
    ConflictError,
    GatewayError,
    InvalidError,
    NotFoundError,
    TooManyError,
)
from gateway.events import gateway_event, summarize
from gateway.homes import HomeDeleted, HomeInfo, HomeList, HomeRecord, HomeRegistry
from gateway.schemas import QuestionRequest, Submitted

__all__ = [
    "TERMINAL",
    "BusyError",
    "ConflictError",
    "EpisodeManager",
    "GatewayError",
    "InvalidError",
    "NotFoundError",
    "TooManyError",
]

log = logging.getLogger(__name__)

REQUIRED_SERVICES = dataflow.PIPELINE
TERMINAL = lifecycle.TERMINAL
DEFAULT_MAX_STEPS = 30  # 3*sqrt(100 m^2): a mid-sized home, when the floor area is unknown
PRUNE_BATCH = 500  # records deleted per retention pass (the lock is held meanwhile)
LEGACY_OWNER = "legacy"  # records stored before tenants existed: admin only
INDEX_VERSION = b"1"
NEW_SCENES_PER_MIN = 30  # scenes new to this gateway (a load, maybe a generated house) per tenant and minute
ENDED_CACHE = 4096  # final statuses kept in memory after a read (an ended episode's status never changes)
EVENTS_PER_STEP = 20  # events stored per step of an episode's budget at most (about 6 are normal; resends more)


def ep_key(episode_id: str) -> str:
    return f"gw:ep:{episode_id}"


def ev_key(episode_id: str) -> str:
    return f"gw:ev:{episode_id}"


def robot_key(robot: str) -> str:
    return f"gw:robot:{robot}"


def queue_key(robot: str) -> str:
    return f"gw:queue:{robot}"


IDX_ALL = "gw:idx:all"
IDX_ACTIVE = "gw:idx:active"
IDX_VERSION_KEY = "gw:idx:version"


def idx_owner(owner: str) -> str:
    return f"gw:idx:o:{owner}"


def idx_state(state: str) -> str:
    return f"gw:idx:s:{state}"


def idx_owner_state(owner: str, state: str) -> str:
    return f"gw:idx:o:{owner}:s:{state}"


@dataclass
class Record:
    status: EpisodeStatus
    start: EpisodeStart
    owner: str = ANONYMOUS
    last_activity: float = field(default_factory=time.time)  # watchdog clock (not persisted)
    last_error: str | None = None  # the last ErrorReply of the episode, for the watchdog's reason (not persisted)
    events: int = 0  # bus messages stored as events by this process (bounded per episode; not persisted)
    backfilled: set[Identity] = field(default_factory=set)  # events taken from the journals (not stored twice)

    def dump(self) -> dict[str, Any]:
        return {
            "status": self.status.model_dump(mode="json"),
            "start": self.start.model_dump(mode="json"),
            "owner": self.owner,
        }

    @classmethod
    def load(cls, raw: dict[str, Any]) -> Record:
        status = EpisodeStatus.model_validate(raw["status"])
        return cls(
            status=status,
            start=EpisodeStart.model_validate(raw["start"]),
            owner=str(raw.get("owner", LEGACY_OWNER)),
            last_activity=status.updated_at,
        )


# Floor area (m2) of a scene: ``(scene id, scenes dir, hm3d dir or None)``; raises when the scene cannot be
# loaded. The gateway imports no service: the process entry (``python -m gateway``, ``eqa gateway``) passes the
# simulator's scene library (``services.sim.library.floor_area``); without one, budgets are the default.
SceneArea = Callable[[str, Path, Path | None], float]


@lru_cache(maxsize=256)
def _scene_area(scene_area: SceneArea, scene: str, scenes_path: Path, hm3d_dir: Path | None) -> float:
    return float(scene_area(scene, scenes_path, hm3d_dir))


def step_budget(settings: SettingsGroup, req: QuestionRequest, scene_area: SceneArea | None = None,
                per_sqrt_m2: float = STEPS_PER_SQRT_M2) -> int:
    """``max_steps`` of an episode: the request's budget, else ``int(per_sqrt_m2 * sqrt(floor area))`` (a
    question: Explore-EQA section VI, T = 3 * sqrt(scene area); a task: 6, as the task benchmark), else
    :data:`DEFAULT_MAX_STEPS`. The scene is checked in every case,
    an explicit budget too (an unknown scene would otherwise be accepted here and fail in the sim). The
    422 says what a scene id looks like and never shows the server's paths or its list of scenes."""
    if req.scene is None or scene_area is None:
        return req.max_steps or DEFAULT_MAX_STEPS
    try:
        area = _scene_area(scene_area, req.scene, settings.scenes_path, settings.hm3d_dir)
    except LookupError as exc:
        log.info("unknown scene %r: %s", req.scene, exc)
        raise InvalidError(
            f"unknown scene {req.scene!r}: give gen-<number> (a generated house, e.g. gen-7) or the id of a scene "
            "installed on this server",
            field="scene",
        ) from exc
    except Exception as exc:
        log.warning("scene %r cannot be loaded: %s", req.scene, exc)
        raise InvalidError(f"scene {req.scene!r} cannot be loaded (the gateway log says why)", field="scene") from exc
    if req.max_steps is not None:
        return req.max_steps
    if area is None or not math.isfinite(area) or area <= 0:
        return DEFAULT_MAX_STEPS
    return steps_for(area, per_sqrt_m2)


class EpisodeManager:
    """The I/O shell of the episode state machine (:mod:`gateway.state`): persistence, event streams, bus,
    queues, tenants, limits, retention. Thread-safe (one lock); store and bus calls are blocking, so async
    callers run these methods in a worker thread."""

    def __init__(self, settings: SettingsGroup, store: Store, bus: Bus, notify: Callable[[], None] | None = None,
                 scene_area: SceneArea | None = None) -> None:
        self.settings = settings
        self.scene_area = scene_area
        self.store = store
        self.bus = bus
        self.notify = notify or (lambda: None)
        self._lock = threading.RLock()
        self._active: dict[str, Record] = {}
        # Copies of the active episodes' last saved status and owner, read without the lock (fast status route).
        self._snapshots: dict[str, tuple[str, EpisodeStatus]] = {}
        self._alive: dict[str, set[str]] = {}
        self._ended: dict[str, tuple[str, EpisodeStatus]] = {}  # final statuses read lately (insertion order)
        self._known_scenes: dict[str, None] = {}  # scenes loaded once (insertion order, bounded)
        self._new_scenes = RateLimiter(NEW_SCENES_PER_MIN / 60.0, burst=NEW_SCENES_PER_MIN)
        self._mean_episode_s = 60.0  # running mean of episode wall times (for Retry-After)
        self.homes = HomeRegistry(store, settings.home_ttl_s)
        self._resetting: set[str] = set()  # homes whose reset waits for a mapper's write-back (outside the lock)
        self.started_at = time.time()

    # ---- startup ----------------------------------------------------------------------------------------
    def start(self) -> None:
        """Watch liveliness, hold the gateway's token, reconcile stored episodes (call once the robot streams
        are subscribed)."""
        self.bus.watch_alive(keys.ALIVE_ANY, self._on_alive)
        self.bus.declare_alive()
        self.reconcile()

    def _on_alive(self, service: str, instance: str, alive: bool) -> None:
        with self._lock:
            group = self._alive.setdefault(service, set())
            (group.add if alive else group.discard)(instance)

    def alive_services(self) -> dict[str, list[str]]:
        with self._lock:
            return {s: sorted(i) for s, i in sorted(self._alive.items()) if i}

    def missing_services(self) -> list[str]:
        alive = self.alive_services()
        stand_ins = {s: [b for b, of in dataflow.STANDS_IN.items() if of == s] for s in REQUIRED_SERVICES}
        return [s for s in REQUIRED_SERVICES if not alive.get(s) and not any(alive.get(b) for b in stand_ins[s])]

    def _build_indexes(self) -> None:
        """Once per store: index records written before the indexes existed (one scan, at start)."""
        if self.store.get(IDX_VERSION_KEY) == INDEX_VERSION:
            return
        n = 0
        for k in self.store.keys("gw:ep:"):
            raw = self.store.get_json(k)
            try:
                episode = Record.load(raw)
            except Exception:
                log.warning("unreadable episode record %s; not indexed", k)
                continue
            self._index(episode)
            n += 1
        self.store.set(IDX_VERSION_KEY, INDEX_VERSION)
        log.info("indexed %d stored episode records", n)

    def reconcile(self) -> None:
        now = time.time()
        with self._lock:
            self._build_indexes()
            ids = self.store.index_page(IDX_ACTIVE, 1_000_000, newest_first=False)
            raws = self.store.get_many([ep_key(e) for e in ids])
            for eid, raw in zip(ids, raws, strict=True):
                if raw is None:
                    self.store.index_remove(IDX_ACTIVE, [eid])
                    continue
                try:
                    episode = Record.load(json.loads(raw))
                except Exception:
                    log.exception("unreadable episode record %s; skipped", eid)
                    continue
                st = episode.status
                if st.state in TERMINAL:
                    self.store.index_remove(IDX_ACTIVE, [eid])
                    continue
                self._active[st.episode_id] = episode
                self._snapshots[st.episode_id] = (episode.owner, st.model_copy(deep=True))
                if st.state == "running":
                    episode.last_activity = now
                    if self.store.get(robot_key(st.robot)) is None:
                        self.store.set(robot_key(st.robot), st.episode_id.encode())
                    self._append(
                        st.episode_id,
                        gateway_event(
                            "gateway_restart",
                            st.episode_id,
                            last_seen=st.updated_at,
                            step=st.step,
                            note="the gateway restarted; what the services published after last_seen while it "
                            "was down follows, backfilled from their journals",
                        ),
                    )
                    self._backfill(episode)
                    if self._recover_end(episode):
                        continue
                    log.info("reconciled running episode %s on %s (step %d)", st.episode_id, st.robot, st.step)
            for robot in self.settings.robots:
                holder = self._running_on(robot)
                if holder is not None and (
                    holder not in self._active or self._active[holder].status.state != "running"
                ):
                    log.warning("robot %s was held by %s, which is not running; freed", robot, holder)
                    self.store.delete(robot_key(robot))
                    holder = None
                if holder is None:
                    self._start_next(robot)

    # ---- persistence helpers ----------------------------------------------------------------------------
    def _index(self, episode: Record) -> None:
        st, score = episode.status, episode.status.created_at
        self.store.index_add(IDX_ALL, st.episode_id, score)
        self.store.index_add(idx_owner(episode.owner), st.episode_id, score)
        if st.state in TERMINAL:
            self.store.index_add(idx_state(st.state), st.episode_id, score)
            self.store.index_add(idx_owner_state(episode.owner, st.state), st.episode_id, score)
            self.store.index_remove(IDX_ACTIVE, [st.episode_id])
        else:
            self.store.index_add(IDX_ACTIVE, st.episode_id, score)

    def _save(self, episode: Record) -> None:
        self.store.set_json(ep_key(episode.status.episode_id), episode.dump())
        self._snapshots[episode.status.episode_id] = (episode.owner, episode.status.model_copy(deep=True))

    def _append(self, episode_id: str, event: dict[str, Any]) -> str:
        entry = self.store.append(ev_key(episode_id), json.dumps(event, separators=(",", ":")).encode())
        self.notify()
        return entry

    def _queue(self, robot: str) -> list[str]:
        return list(self.store.get_json(queue_key(robot)) or [])

    def _set_queue(self, robot: str, ids: list[str]) -> None:
        self.store.set_json(queue_key(robot), ids)

    def _running_on(self, robot: str) -> str | None:
        raw = self.store.get(robot_key(robot))
        return raw.decode() if raw else None

    def store_record(self, episode: Record) -> None:
        """Store and index an episode record as it is (an ended one from elsewhere: an import, a benchmark's
        stored history); active records are taken up by :meth:`reconcile` at the next start."""
        self.store.set_json(ep_key(episode.status.episode_id), episode.dump())
        self._index(episode)

    def load(self, episode_id: str) -> Record | None:
        raw = self.store.get_json(ep_key(episode_id))
        if raw is None:
            self._check_store_intact()
            return None
        return Record.load(raw)

    def _check_store_intact(self) -> None:
        """Before answering "no such episode": :class:`StoreUnavailable` (503) when the store has lost the
        gateway's data (its index marker is gone: a Redis restarted without persistence, or flushed), so a
        lost episode is never reported as one that never existed. One read, on a miss only."""
        if self.store.get(IDX_VERSION_KEY) is None:
            log.error("the store holds no gateway data (a Redis restarted without persistence, or flushed?): "
                      "episodes stored before are gone; run Redis with appendonly yes (docs/durability.md) and "
                      "restart the gateway")
            raise StoreUnavailable("the store has lost the gateway's data (restarted without persistence?)")

    # ---- queries (each checks the caller's tenant: another tenant's episode is "not found") --------------
    def peek(self, episode_id: str, caller: Caller | None = None) -> EpisodeStatus | None:
        """The saved status of a queued or running episode from memory (no store access), else None."""
        snap = self._snapshots.get(episode_id)
        if snap is None or (caller is not None and not caller.sees(snap[0])):
            return None
        return snap[1]

    def peek_ended(self, episode_id: str, caller: Caller | None = None) -> EpisodeStatus | None:
        """The final status of an ended episode read lately (memory only), else None."""
        hit = self._ended.get(episode_id)
        if hit is None or (caller is not None and not caller.sees(hit[0])):
            return None
        return hit[1]

    def get(self, episode_id: str, caller: Caller | None = None) -> EpisodeStatus:
        """The stored status (an ended episode's is final: kept in a small cache after the first read)."""
        keys.check_id(episode_id, "episode id")
        hit = self._ended.get(episode_id)
        if hit is None:
            raw = self.store.get(ep_key(episode_id))
            if raw is None:
                self._check_store_intact()
                raise NotFoundError(f"no episode {episode_id!r}")
            data = json.loads(raw)
            hit = (str(data.get("owner", LEGACY_OWNER)), EpisodeStatus.model_validate(data["status"]))
            if hit[1].state in TERMINAL:
                with self._lock:
                    self._ended[episode_id] = hit
                    while len(self._ended) > ENDED_CACHE:
                        self._ended.pop(next(iter(self._ended)))
        if caller is not None and not caller.sees(hit[0]):
            raise NotFoundError(f"no episode {episode_id!r}")
        return hit[1]

    def list(self, caller: Caller | None = None, limit: int = 50, state: str | None = None) -> list[EpisodeStatus]:
        """Newest first: queued/running ones from memory, the others from one page of one index."""
        limit = max(1, min(int(limit), 1000))
        admin = caller is None or caller.admin
        if state in lifecycle.ACTIVE:
            with self._lock:
                recs = [r for r in self._active.values() if r.status.state == state and (admin or r.owner ==
                        caller.tenant)]  # type: ignore[union-attr]
                out = [r.status.model_copy(deep=True) for r in recs]
            out.sort(key=lambda s: s.created_at, reverse=True)
            return out[:limit]
        if state is None:
            index = IDX_ALL if admin else idx_owner(caller.tenant)  # type: ignore[union-attr]
        else:
            index = idx_state(state) if admin else idx_owner_state(caller.tenant, state)  # type: ignore[union-attr]
        ids = self.store.index_page(index, limit)
        out = []
        for raw in self.store.get_many([ep_key(e) for e in ids]):
            if raw is None:
                continue
            try:
                out.append(EpisodeStatus.model_validate(json.loads(raw)["status"]))
            except Exception:
                log.warning("unreadable episode record in index %s; skipped", index)
        return out

    def events(self, episode_id: str, after: str = "0-0", count: int = 500) -> list[tuple[str, bytes]]:
        return self.store.read(ev_key(episode_id), after=after, count=count)

    def robots(self, caller: Caller | None = None) -> dict[str, str | None]:
        """The episode running on each robot; another tenant's shows as ``"busy"``."""
        out: dict[str, str | None] = {}
        for r in self.settings.robots:
            eid = self._running_on(r)
            if eid is not None and caller is not None and not caller.admin:
                snap = self._snapshots.get(eid)
                eid = eid if snap is not None and caller.sees(snap[0]) else "busy"
            out[r] = eid
        return out

    # ---- submit / start ---------------------------------------------------------------------------------
    def retry_after_s(self, waiting: int = 1) -> float:
        """A client's wait before a slot may be free: the mean episode time (at least 1 s, at most 1 h)."""
        return min(3600.0, max(1.0, self._mean_episode_s * max(1, waiting)))

    def _check_new_scene(self, scene: str | None, owner: str) -> None:
        """A scene this gateway has not loaded yet costs a load (a new ``gen-<seed>`` house is generated and
        saved: ~130 ms and ~114 KB): at most :data:`NEW_SCENES_PER_MIN` per tenant a minute, then 429."""
        if scene is None or self.scene_area is None or scene in self._known_scenes:
            return
        ok, wait = self._new_scenes.allow(owner)
        if not ok:
            raise TooManyError(
                f"this token asked for {NEW_SCENES_PER_MIN} scenes new to the gateway within a minute, the most it "
                f"may; retry in {wait:.0f} s or use a scene already loaded",
                retry_after_s=wait,
            )
        self._known_scenes[scene] = None
        while len(self._known_scenes) > 10_000:
            self._known_scenes.pop(next(iter(self._known_scenes)))

    def _check_token_cap(self, owned: int) -> None:
        """:class:`TooManyError` when a token already has ``owned`` queued or running episodes, its cap."""
        if owned >= self.settings.queue_max_per_token:
            wait = self.retry_after_s()
            raise TooManyError(
                f"this token has {owned} queued or running episodes, the most one token may have "
                f"(EQA_QUEUE_MAX_PER_TOKEN={self.settings.queue_max_per_token}); retry in about {wait:.0f} s",
                retry_after_s=wait,
            )
    def refuse_if_full(self, caller: Caller | None, robot: str | None) -> None:
        """:class:`TooManyError` when memory already shows that :meth:`submit` would refuse for a full queue
        or too many episodes of this token: the same limits, checked on the event loop from the lock-free
        snapshots of the active episodes, so a flood of submissions against a full queue is refused without
        a thread hop, the lock or a store call. Refuses nothing :meth:`submit` would take (it checks again)."""
        owner = caller.tenant if caller is not None else ANONYMOUS
        active = list(self._snapshots.values())  # one atomic copy (the dict changes on worker threads)
        self._check_token_cap(sum(1 for o, _ in active if o == owner))
        if self.settings.busy_policy != "queue" or (robot is not None and robot not in self.settings.robots):
            return
        candidates = [robot] if robot is not None else list(self.settings.robots)
        queued = {r: 0 for r in candidates}
        busy: set[str] = set()
        for _, st in active:
            if st.robot in queued:
                busy.add(st.robot)
                queued[st.robot] += st.state == "queued"
        cap = self.settings.queue_max_per_robot
        if all(r in busy and queued[r] >= cap for r in candidates):
            fullest = min(candidates, key=lambda r: queued[r])
            wait = self.retry_after_s(queued[fullest] // max(1, cap))
            raise TooManyError(
                f"the queue of robot {fullest} is full ({queued[fullest]} episodes, EQA_QUEUE_MAX_PER_ROBOT={cap}); "
                f"retry in about {wait:.0f} s",
                retry_after_s=wait,
            )

    def submit(self, req: QuestionRequest, caller: Caller | None = None, *, task: Task | None = None,
               ablation: Ablation = "helios", pick_limit: int | None = None, draws: str | None = None) -> Submitted:
        """A question episode; with ``task`` a HELIOS task episode whose stand-in question is ``req``
        (gateway/routers/tasks.py). ``draws``: the simulated models' draw key (``EpisodeStart.draws``)."""
        owner = caller.tenant if caller is not None else ANONYMOUS
        if req.robot is not None and req.robot not in self.settings.robots:
            raise InvalidError(f"unknown robot {req.robot!r}; known: {', '.join(self.settings.robots)}", field="robot")
        self._check_new_scene(req.scene, owner)
        budget = step_budget(self.settings, req, self.scene_area,
                             TASK_STEPS_PER_SQRT_M2 if task is not None else STEPS_PER_SQRT_M2)
        episode_id = new_id("ep")
        question = Question(
            text=req.question,
            choices=req.choices or [],
            scene=req.scene or "",
            start_pose=req.start_pose,
            max_steps=budget,
            answer=req.answer,
            **({"id": req.question_id} if req.question_id else {}),
        )
        with self._lock:
            self._check_token_cap(sum(1 for r in self._active.values() if r.owner == owner))
            candidates = [req.robot] if req.robot else list(self.settings.robots)
            queues = {r: self._queue(r) for r in candidates}
            free = [r for r in candidates if self._running_on(r) is None and not queues[r]]
            if free:
                robot, position = free[0], 0
            elif self.settings.busy_policy == "refuse":
                busy = ", ".join(f"{r} (running {self.robots(caller)[r]})" for r in candidates)
                raise BusyError(f"robot busy: {busy}; EQA_BUSY_POLICY=refuse, submit again later")
            else:
                robot = min(candidates, key=lambda r: len(queues[r]))
                if len(queues[robot]) >= self.settings.queue_max_per_robot:
                    wait = self.retry_after_s(len(queues[robot]) // max(1, self.settings.queue_max_per_robot))
                    raise TooManyError(
                        f"the queue of robot {robot} is full ({len(queues[robot])} episodes, "
                        f"EQA_QUEUE_MAX_PER_ROBOT={self.settings.queue_max_per_robot}); retry in about {wait:.0f} s",
                        retry_after_s=wait,
                    )
                position = len(queues[robot]) + 1
            home = self._use_home(owner, req.home, req.scene or "") if req.home is not None else None
            start = EpisodeStart(
                episode_id=episode_id,
                robot=robot,
                question=question,
                strategy=req.strategy,
                stop=req.stop_config(),
                max_steps=budget,
                seed=req.seed,
                record=req.record,
                task=task,
                ablation=ablation,
                pick_limit=pick_limit,
                home=home,
                draws=draws,
            )
            status = EpisodeStatus(
                episode_id=episode_id,
                robot=robot,
                state="queued",
                question=question,
                strategy=req.strategy,
                stop=start.stop,
                max_steps=budget,
                task=task,
                **({"ablation": ablation, "pick_limit": pick_limit} if task is not None else {}),
            )
            episode = Record(status=status, start=start, owner=owner)
            self._active[episode_id] = episode
            self._save(episode)
            self._index(episode)
            if position == 0:
                self._start(episode)
            else:
                self._set_queue(robot, [*queues[robot], episode_id])
                self._append(episode_id, gateway_event("queued", episode_id, robot=robot, position=position))
        return Submitted(
            episode_id=episode_id,
            robot=robot,
            state=episode.status.state,
            max_steps=budget,
            queue_position=position,
            links={
                "status": f"/v1/episodes/{episode_id}",
                "events": f"/v1/episodes/{episode_id}/events",
                "recording": f"/v1/episodes/{episode_id}/recording",
            },
        )

    # ---- homes ------------------------------------------------------------------------------------------
    def _use_home(self, owner: str, name: str, scene: str) -> str:
        """The internal id of ``owner``'s home ``name`` for one more episode in ``scene`` (the home is made if
        new). :class:`ConflictError` when the home is another house (its memory would mix two houses), or
        :class:`TooManyError` when it is new and the tenant already holds ``EQA_HOMES_MAX_PER_TENANT`` homes; then
        nothing is written."""
        house = homes_layout.house_of(scene)
        known = self.homes.get(owner, name)
        if known is not None and known.home in self._resetting:
            raise BusyError(f"home {name!r} is being reset; try again in a few seconds", retry_after_s=2.0)
        if known is not None and known.house != house:
            raise ConflictError(
                f"home {name!r} is the house {known.house or 'of the robot (no scene)'}; this episode is in "
                f"{house or 'the robot world (no scene)'}: name another home, or reset this one "
                f"(DELETE /v1/homes/{name})")
        self._check_home_bytes(owner, known.home if known is not None else homes_layout.home_id(owner, name))
        cap = self.settings.homes_max_per_tenant
        entry = self.homes.use(owner, name, house, cap)
        if entry is None:
            raise TooManyError(
                f"this token holds {self.homes.count(owner)} homes, the most one tenant may "
                f"(EQA_HOMES_MAX_PER_TENANT={cap}); name one of them, or delete one with DELETE /v1/homes/{{name}}",
            )
        return entry.home

    def _check_home_bytes(self, owner: str, home: str) -> None:
        """:class:`TooManyError` unless one more episode in ``home`` keeps ``owner``'s homes within
        ``EQA_HOMES_MAX_BYTES_PER_TENANT``: the tenant's other homes count their stored bytes (the mapper's
        summaries), or ``EQA_HOME_MAX_BYTES`` while an episode of theirs is queued or running (its commit may grow
        them to that), and this home ``EQA_HOME_MAX_BYTES``. So the bound holds whatever the episodes admitted
        write back (called under the manager's lock: admissions one at a time)."""
        s = self.settings
        cap, one = s.homes_max_bytes_per_tenant, s.home_max_bytes
        others = [r for r in self.homes.page(owner, s.homes_max_per_tenant, 0) if r.home != home]
        held = 0
        for r, summary in zip(others, self.homes.summaries(others), strict=True):
            held += one if self._home_episodes(r.home) else (summary.bytes if summary is not None else 0)
        if held + one > cap:
            raise TooManyError(
                f"this token's homes hold {held} bytes (homes with an episode queued or running counted at "
                f"EQA_HOME_MAX_BYTES={one}); one more episode in a home may add up to {one}, past the most one "
                f"tenant may hold (EQA_HOMES_MAX_BYTES_PER_TENANT={cap}); delete a home with "
                "DELETE /v1/homes/{name}, or wait for running episodes to end",
            )

    def _home_episodes(self, home: str) -> list[str]:
        """Queued and running episodes of the home with internal id ``home``."""
        return sorted(eid for eid, r in self._active.items() if r.start.home == home)

    def _home_info(self, entry: HomeRecord, summary: Any, now: float) -> HomeInfo:
        with self._lock:  # only the active episodes need it: the store reads of the read routes go without
            active = self._home_episodes(entry.home)
        return HomeInfo(name=entry.name, house=entry.house, created_at=entry.created_at,
                        last_used_at=entry.last_used_at, age_s=round(max(0.0, now - entry.created_at), 3),
                        episodes_submitted=entry.episodes, active_episodes=active, memory=summary)

    def _home_record(self, caller: Caller | None, name: str) -> HomeRecord:
        keys.check_id(name, "home")
        owner = caller.tenant if caller is not None else ANONYMOUS
        entry = self.homes.get(owner, name)
        if entry is None:
            self._check_store_intact()
            raise NotFoundError(f"no home {name!r}")
        return entry

    def home(self, name: str, caller: Caller | None = None) -> HomeInfo:
        """The caller's home ``name`` (another tenant's home of that name is a different home: 404 here), with the
        names of its stored parts."""
        entry = self._home_record(caller, name)
        info = self._home_info(entry, self.homes.summaries([entry])[0], time.time())
        parts = self.homes.parts(entry)
        has_map = homes_layout.map_png_key(entry.home) in [homes_layout.prefix(entry.home) + p for p in parts]
        return info.model_copy(update={"parts": parts, "map_png": f"/v1/homes/{name}/map.png" if has_map else None})

    def home_map_png(self, name: str, caller: Caller | None = None) -> bytes:
        """The PNG picture of the caller's home's map; :class:`NotFoundError` when there is none."""
        png = self.homes.map_png(self._home_record(caller, name))
        if png is None:
            raise NotFoundError(f"home {name!r} has no map picture (yet)")
        return png

    def list_homes(self, caller: Caller | None = None, limit: int = 50, offset: int = 0) -> HomeList:
        """One page of the caller's homes, newest first."""
        owner = caller.tenant if caller is not None else ANONYMOUS
        limit, offset = max(1, min(int(limit), 1000)), max(0, int(offset))
        entries = self.homes.page(owner, limit, offset)
        now = time.time()
        infos = [self._home_info(r, s, now) for r, s in zip(entries, self.homes.summaries(entries), strict=True)]
        return HomeList(homes=infos, total=self.homes.count(owner), offset=offset, limit=limit)

    def delete_home(self, name: str, caller: Caller | None = None) -> HomeDeleted:
        """Reset the caller's home ``name``: its memory and record go. :class:`ConflictError` (409) while an
        episode of it is queued or running (the mapper reads and writes the memory meanwhile), :class:`BusyError`
        (409 with Retry-After) while a mapper writes an ended episode back into it or another reset runs."""
        with self._lock:
            entry = self._home_record(caller, name)
        try:
            n = self._reset_home(entry)
        except homes_layout.HomeBusyError as exc:
            raise BusyError(f"home {name!r}: a mapper is writing an ended episode's memory into it; "
                            "try again in a few seconds", retry_after_s=2.0) from exc
        log.info("home %s of %s deleted (%d memory keys)", entry.home, entry.owner, n)
        return HomeDeleted(name=name, deleted_keys=n)

    def _reset_home(self, entry: HomeRecord) -> int:
        """Delete a home no episode of which is queued or running (:class:`ConflictError` otherwise,
        :class:`BusyError` while another reset of it runs); the memory keys deleted. No episode of the home is
        admitted until the reset is done, so the wait for a mapper's write-back (:func:`eqa.homes.delete_home`,
        :class:`eqa.homes.HomeBusyError` past it) runs without the manager's lock: other requests go on
        meanwhile."""
        with self._lock:
            busy = self._home_episodes(entry.home)
            if busy:
                raise ConflictError(f"home {entry.name!r} has {len(busy)} queued or running episodes "
                                    f"({', '.join(busy[:5])}{' ...' if len(busy) > 5 else ''}); cancel them or wait "
                                    "for their end")
            if entry.home in self._resetting:
                raise BusyError(f"home {entry.name!r} is being reset; try again in a few seconds", retry_after_s=2.0)
            self._resetting.add(entry.home)
        try:
            return self.homes.delete(entry)
        finally:
            with self._lock:
                self._resetting.discard(entry.home)

    def prune_homes(self, now: float | None = None, batch: int = PRUNE_BATCH) -> int:
        """Delete up to ``batch`` homes no episode used for ``EQA_HOMES_RETENTION_DAYS`` (never one with a queued
        or running episode); how many went."""
        now = time.time() if now is None else now
        cutoff = now - self.settings.homes_retention_days * 86400.0
        n = 0
        for entry in self.homes.unused_since(cutoff, batch):
            try:
                self._reset_home(entry)
            except (ConflictError, BusyError, homes_layout.HomeBusyError):
                continue  # in use, or being written back: a later round takes it
            n += 1
        if n:
            log.info("retention: %d homes unused for %g days deleted", n, self.settings.homes_retention_days)
        return n

    def _start(self, episode: Record) -> None:
        now = time.time()
        episode.status = lifecycle.started(episode.status, now)
        st = episode.status
        episode.last_activity = now
        episode.start = episode.start.model_copy(update={"sent_at": now})
        self._save(episode)
        self.store.set(robot_key(st.robot), st.episode_id.encode())
        self._append(st.episode_id, summarize(episode.start))
        try:
            self.bus.publish(keys.stream(st.robot, keys.EPISODE_START), episode.start)
        except Exception as exc:
            log.exception("could not publish EpisodeStart of %s", st.episode_id)
            self._finish(episode, lifecycle.Ending("failed", f"could not publish EpisodeStart on the bus: "
                                                  f"{type(exc).__name__}: {exc}"))
            return
        log.info("episode %s started on %s (max_steps %d)", st.episode_id, st.robot, st.max_steps)

    def _start_next(self, robot: str) -> None:
        queue = self._queue(robot)
        while queue:
            nxt = queue.pop(0)
            self._set_queue(robot, queue)
            episode = self._active.get(nxt)
            if episode is not None and episode.status.state == "queued":
                self._start(episode)
                return

    # ---- end / cancel -----------------------------------------------------------------------------------
    def _finish(self, episode: Record, ending: lifecycle.Ending) -> None:
        """Store the final status (before any end event), tell the services when the gateway decided the end
        of a running episode, free the robot and start its next queued episode."""
        was_running = episode.status.state == "running"
        if ending.tell_services and was_running:
            try:
                self.bus.publish(
                    keys.stream(episode.status.robot, keys.EPISODE_CANCEL),
                    EpisodeCancel(episode_id=episode.status.episode_id, reason=ending.reason),
                )
            except Exception:
                log.exception("could not publish EpisodeCancel for %s", episode.status.episode_id)
        now = time.time()
        rdir = recording_dir(self.settings, episode.status.episode_id)
        has_recording = rdir.is_dir() and any(rdir.glob("*.rrd"))
        trace = None
        if episode.status.task is not None:  # the sim's task trace names the phase and step of the first failure
            try:
                raw = self.store.get_json(task_trace_key(episode.status.episode_id))
                trace = raw if isinstance(raw, dict) else None
            except Exception:
                log.warning("task trace of %s unreadable; outcome from the metrics", episode.status.episode_id)
        episode.status = lifecycle.finished(episode.status, ending.state, ending.reason, now, end=ending.end,
                                            recording=has_recording, trace=trace)
        st = episode.status
        if was_running:
            self._mean_episode_s = 0.8 * self._mean_episode_s + 0.2 * max(0.0, now - st.created_at)
        self._save(episode)
        self._index(episode)
        self._active.pop(st.episode_id, None)
        self._snapshots.pop(st.episode_id, None)  # the store holds the final record
        if self._running_on(st.robot) == st.episode_id:
            self.store.delete(robot_key(st.robot))
        if ending.end is None:
            self._append(st.episode_id, lifecycle.end_event(st))
        log.info("episode %s %s: %s", st.episode_id, st.state, st.stop_reason)
        gateway_metrics.episode_ended(st)
        if self._running_on(st.robot) is None:  # a cancelled queued episode leaves its robot busy
            self._start_next(st.robot)

    def cancel(self, episode_id: str, caller: Caller | None = None, reason: str = "cancelled by user") -> EpisodeStatus:
        keys.check_id(episode_id, "episode id")
        with self._lock:
            episode = self._active.get(episode_id)
            if episode is None:
                stored = self.load(episode_id)
                if stored is None or (caller is not None and not caller.sees(stored.owner)):
                    raise NotFoundError(f"no episode {episode_id!r}")
                raise ConflictError(f"episode {episode_id} already ended ({stored.status.state})")
            if caller is not None and not caller.sees(episode.owner):
                raise NotFoundError(f"no episode {episode_id!r}")
            if episode.status.state == "queued":
                self._set_queue(episode.status.robot, [e for e in self._queue(episode.status.robot) if e != episode_id])
            self._finish(episode, lifecycle.Ending("cancelled", reason, tell_services=True))
            return episode.status

    # ---- bus messages -----------------------------------------------------------------------------------
    def is_active(self, episode_id: object) -> bool:
        """True for a queued or running episode of this gateway (read without the lock: a hint for the
        bus hand-off, which drops messages of other episodes before queueing them)."""
        return isinstance(episode_id, str) and episode_id in self._snapshots

    def handle(self, robot: str, msg: Message) -> None:
        """One message of a robot stream: the pure transition (:func:`gateway.state.on_message`), then its
        effects: the final status before the stopper's end event, the event, the save."""
        episode_id = getattr(msg, "episode_id", None)
        if not isinstance(episode_id, str):
            return
        with self._lock:
            episode = self._active.get(episode_id)
            if episode is None:
                log.debug("message %s for episode %s that is not running here; ignored", msg.kind, episode_id)
                return
            now = time.time()
            t = lifecycle.on_message(episode.status, robot, msg, now)
            for note in t.notes:
                log.warning("%s: a %s ignored", note, msg.kind)
            if t.ignore:
                return
            episode.last_activity = now
            if t.last_error is not None:
                episode.last_error = t.last_error
            if t.ending is not None and t.ending.end is not None:
                # The final status is stored before the end event: a client that reads the event and then
                # asks for the status gets the final one.
                self._finish(episode, t.ending)
                self._append(episode_id, summarize(msg))
                return
            episode.events += 1
            cap = EVENTS_PER_STEP * episode.status.max_steps + 100
            event = summarize(msg)
            if episode.backfilled and event_identity(event) in episode.backfilled:
                episode.backfilled.discard(event_identity(event))  # seen in a journal first: stored once
            elif episode.events <= cap or isinstance(msg, ErrorReply):
                self._append(episode_id, event)
            elif episode.events == cap + 1:
                log.warning("episode %s: over %d events (a flood on the bus?); further data messages are not "
                            "stored as events", episode_id, cap)
            if t.ending is not None:
                self._finish(episode, t.ending)
                return
            assert t.status is not None
            episode.status = t.status
            self._save(episode)

    def _backfill(self, episode: Record) -> int:
        """Append the events the services journalled (:mod:`eqa.event_log`) that the stored stream lacks: what
        was published while no gateway listened. Bounded by the episode's event cap; returns how many."""
        eid = episode.status.episode_id
        cap = EVENTS_PER_STEP * episode.status.max_steps + 100

        def events(key: str) -> list[dict[str, Any]]:
            out = []
            for _, raw in self.store.read(key, count=cap):
                try:
                    event = json.loads(raw)
                except ValueError:
                    continue
                if isinstance(event, dict) and event.get("episode_id") == eid:
                    out.append(event)
            return out

        missing = missing_events(events(ev_key(eid)), [events(episode_journal_key(s, eid)) for s in JOURNAL_SERVICES])
        for event in missing[:cap]:
            self._append(eid, event)
            episode.backfilled.add(event_identity(event))
        episode.events += len(missing)
        if missing:
            log.info("episode %s: %d events published while the gateway was down backfilled from the services' "
                     "journals", eid, len(missing))
        return len(missing)

    def _recover_end(self, episode: Record) -> bool:
        """End ``episode`` from the stopper's stored ``EpisodeEnd`` if there is one (an end not seen on the bus)."""
        end = stored_end(self.store, episode.status.episode_id)
        if end is None:
            return False
        event = summarize(end)
        event["recovered"] = "from the stopper's stored end: not seen on the bus by this gateway"
        self._finish(episode, lifecycle.Ending(end.state if end.state in TERMINAL else "stopped", end.reason, end=end))
        self._append(episode.status.episode_id, event)  # after the final status, as in handle()
        return True

    # ---- watchdog and retention -------------------------------------------------------------------------
    def check_timeouts(self, now: float | None = None) -> list[str]:
        """Fail running episodes with no message for ``episode_timeout_s``; return their ids."""
        now = time.time() if now is None else now
        timeout = self.settings.episode_timeout_s
        failed = []
        with self._lock:
            for episode in list(self._active.values()):
                st = episode.status
                if not lifecycle.timed_out(st.state, episode.last_activity, self.started_at, now, timeout):
                    continue
                if self._recover_end(episode):
                    continue
                reason = lifecycle.timeout_reason(
                    st, timeout, self.missing_services(), episode.last_error, restarted=st.updated_at < self.started_at
                )
                self._finish(episode, lifecycle.Ending("failed", reason, tell_services=True))
                failed.append(st.episode_id)
        return failed

    def prune(self, now: float | None = None, batch: int = PRUNE_BATCH) -> int:
        """Delete up to ``batch`` ended episodes past the retention count (oldest first) or age, with their
        events, index entries and recordings; return how many went."""
        now = time.time() if now is None else now
        cutoff = now - self.settings.episode_retention_days * 86400.0
        victims = self.store.index_below(IDX_ALL, cutoff, batch)
        excess = self.store.index_len(IDX_ALL) - self.settings.episode_retention_count
        if excess > 0:
            victims += self.store.index_page(IDX_ALL, min(excess + len(self._active), batch), newest_first=False)
        with self._lock:
            ids = list(dict.fromkeys(v for v in victims if v not in self._active))[:batch]
            if not ids:
                return 0
            raws = self.store.get_many([ep_key(e) for e in ids])
            drop: dict[str, list[str]] = {IDX_ALL: list(ids), IDX_ACTIVE: []}
            for eid, raw in zip(ids, raws, strict=True):
                try:
                    stored = json.loads(raw) if raw is not None else {}
                    owner, state = str(stored.get("owner", LEGACY_OWNER)), stored["status"]["state"]
                except Exception:
                    continue
                for index in (idx_owner(owner), idx_state(state), idx_owner_state(owner, state)):
                    drop.setdefault(index, []).append(eid)
            for index, members in drop.items():
                self.store.index_remove(index, members)
            for eid in ids:
                self._ended.pop(eid, None)
            self.store.delete_many([ep_key(e) for e in ids] + [ev_key(e) for e in ids]
                                   + [episode_journal_key(s, e) for e in ids for s in JOURNAL_SERVICES])
        for eid in ids:
            shutil.rmtree(recording_dir(self.settings, eid), ignore_errors=True)
        log.info("retention: %d ended episodes deleted (keep %d, at most %g days)", len(ids),
                 self.settings.episode_retention_count, self.settings.episode_retention_days)
        return len(ids)
