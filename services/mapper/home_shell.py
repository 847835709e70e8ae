"""The mapper's home memory over the store: load a home into an episode, keep its candidate keyframes, warm
start a question from the view memory, write the home back when the episode ends.

Store layout (under :func:`eqa.homes.prefix`, every key with ``EQA_HOME_TTL_S``):

* ``index``          :class:`~services.mapper.home_memory.HomeIndex` (version, the kept views' covered cells);
* ``map``            :class:`~services.mapper.home_memory.HomeMap` (TSDF volume, traversed plane);
* ``objects``        :class:`~services.mapper.home_objects.HomeObjects` (the HELIOS object layer of its task
  episodes); ``objects-base:{episode}`` the layer a running task started from (its commit adds what it saw);
* ``view:{id}``      one :class:`~services.mapper.home_memory.Keyframe` each (the kept views, and the candidates
  of running episodes: a frame is written when its episode's pool keeps it, so a mapper that dies mid-episode
  loses nothing its successor needs);
* ``summary``        :class:`eqa.homes.HomeSummary` for the gateway; ``lock`` while a commit runs.

**One home, any mapper instance.** Nothing of a home lives in a mapper's memory between episodes: the next
episode, on whichever instance, reads the store. A running episode's own part (which home, the version it
started from, its candidate views, its memory steps) is a part of the mapper's episode state
(:data:`STATE_KEY`), so a restarted mapper or the instance its robot moves to continues it and commits it.

**Concurrent episodes in one home** (optimistic version check, the last writer merges): an episode remembers the
home's ``version`` it started from. At its end it takes the home's lock (``set_if_absent``, a TTL so a dead
holder does not block it) and reads the index: still that version, its map replaces the stored one (it
started from it and only added observations); a newer version (another episode committed meanwhile), the
stored map and its map are fused (:meth:`HomeMap.merge`, both keep the other's observations). Either way the
views are chosen again from the stored ones and the episode's candidates together (:func:`select_views`), the
version goes up by one, and the views left out are deleted. The lock orders commits but cannot make them
exclusive (it expires, so a commit slower than its TTL loses it): the map, object layer and index are written
in one compare-and-set on the index read at the commit's start (``Store.set_many_if``), and a commit whose index
changed meanwhile writes nothing and runs again, merging what the other writer committed.

**A task in a home** (:meth:`HomeMemory.start` with its object layer, :meth:`HomeMemory.warm_objects`): it starts
from the home's Gaussians that hold evidence for its classes (the carry-over rule of
:mod:`services.mapper.home_objects`), counts as explored only the floor explored for all of its classes, and
re-detects up to ``EQA_HOME_REDETECT_VIEWS`` remembered views at its first frame when a class of it was never asked.

**Warm start** (:meth:`HomeMemory.warm`): at the first frame of an episode in a home with views, the mapper
re-scores up to ``EQA_HOME_WARM_VIEWS`` remembered views for the new question (the most covering first),
``EQA_HOME_WARM_PARALLEL`` requests in flight at once through the scorer pool (whose replicas batch concurrent
requests), waiting ``EQA_HOME_WARM_TIMEOUT_S`` at most. Their LSV / GSV are written into the question's layer
(Eq. 3) before the frontiers are weighed (Eq. A6), so the planner heads where the memory points; the answer
distributions and relevances of all of them, or of the ``EQA_HOME_MEMORY_STEPS`` most relevant, go to the stopper
with step 0 (:attr:`eqa.messages.StepScores.memory`).
"""

from __future__ import annotations

import logging
import math
import time
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from eqa import homes
from eqa.budget import warm_step_limit
from eqa.messages import (
    DetectResult,
    EpisodeStart,
    ErrorReply,
    Frame,
    MemoryBounds,
    MemoryScore,
    ScoreRequest,
    ScoreResult,
    WarmStart,
)
from eqa.settings import SettingsGroup
from eqa.store import Store
from services.mapper.episode_map import EpisodeMap
from services.mapper.extension import MapperExtension, StepOutputs
from services.mapper.home_memory import (
    CHANGE_VIEWS,
    MAX_CHANGES,
    HomeIndex,
    HomeMap,
    Keyframe,
    ObservedChange,
    ViewInfo,
    ViewPool,
    back_band_cells,
    cell_keys,
    disagreement,
    observed_floor,
    select_views,
    stale_weights,
)
from services.mapper.home_objects import FloorMask, HomeObjects, commit_layer, floor_of
from services.mapper.projection import known_columns
from services.mapper.prompt_points import prompt_points

if TYPE_CHECKING:
    from services.mapper.object_map import ObjectMap

log = logging.getLogger(__name__)

STATE_KEY = "home"  # this memory's part of the mapper's episode state
LOCK_WAIT_S = 20.0
COMMIT_ATTEMPTS = 3  # commits of one episode whose index changed under them before it is given up


def index_key(home: str) -> str:
    return homes.prefix(home) + "index"


def map_key(home: str) -> str:
    return homes.prefix(home) + "map"


def view_key(home: str, view_id: str) -> str:
    return homes.prefix(home) + "view:" + view_id


def objects_key(home: str) -> str:
    return homes.prefix(home) + "objects"


def objects_base_key(home: str, episode_id: str) -> str:
    """The home's object layer as a running task found it (its commit adds what it saw to this)."""
    return homes.prefix(home) + "objects-base:" + episode_id


def memory_seed(seed: int, view_id: str) -> int:
    """The scorer seed of a remembered view's request: the episode's seed and the view, so two views never share
    the draws of a seeded (simulated) perception model and the same view gets the same ones again."""
    return (int(seed) * 1_000_003 + zlib.crc32(view_id.encode())) % (2**31)


@dataclass
class EpisodeHome:
    """The home part of one running episode."""

    home: str
    base_version: int
    pool: ViewPool
    reset: str | None = None  # the home's reset token when the episode started (eqa.homes.delete_home)
    warm_ids: list[str] = field(default_factory=list)  # committed views to re-score at the first frame
    memory: list[MemoryScore] | None = None  # the memory steps, once scored (None: not yet)
    loaded_cells: int = 0  # floor cells A_e of the home map it started from (EQA_HOME_WARM_AREA)
    step_limit: int | None = None  # a question's budget in the explored house (eqa.budget.warm_step_limit)
    geometry_only: bool = False  # started from the home map without its explored mask (a task)
    changes: list[ObservedChange] = field(default_factory=list)  # changes its frames showed against the memory
    objects_base: bool = False  # a task that started from the home's object layer (its copy at objects_base_key)
    redetect_ids: list[str] = field(default_factory=list)  # views to re-detect for classes never asked before
    redetect_without: list[str] = field(default_factory=list)  # the task's classes asked before (not re-counted)
    objects_warmed: bool = False  # the re-detection ran (at the first frame)

    def dump(self) -> dict[str, Any]:
        return {"home": self.home, "base_version": self.base_version, "reset": self.reset,
                "pool": [{"view_id": v.view_id, "t": v.t, "nbytes": v.nbytes, "step": v.step} for v in self.pool.views],
                "warm_ids": self.warm_ids, "loaded_cells": self.loaded_cells, "step_limit": self.step_limit,
                "geometry_only": self.geometry_only, "objects_base": self.objects_base,
                "redetect_ids": self.redetect_ids, "redetect_without": self.redetect_without,
                "objects_warmed": self.objects_warmed,
                "memory": None if self.memory is None else [m.model_dump() for m in self.memory],
                "changes": [c.to_json() for c in self.changes]}


class HomeMemory(MapperExtension):
    """The home memory of the mapper's episodes, the last of
    :class:`services.mapper.service.MapperService`'s extensions (:mod:`services.mapper.extension`): it starts an
    episode's map (and a task's object layer, ``objects``) from its home's at :meth:`begin`, re-scores the
    remembered views at the first frame in :meth:`observe`, and commits the episode at :meth:`finish`, which
    runs before the object layer drops its state."""

    state_key = STATE_KEY

    def __init__(self, settings: SettingsGroup, store: Callable[[], Store],
                 scorer: Callable[[], Callable[[ScoreRequest], Any]], *,
                 objects: Callable[[str], ObjectMap | None] = lambda episode_id: None,
                 detect: Callable[[], Callable[[Any], Any]] | None = None) -> None:
        self.settings = settings
        self._store = store  # the service's store, opened when first used
        self.scorer = scorer
        self.objects = objects  # a task episode's object layer (the object layer extension's state)
        self.detect = detect  # the pool's detector call (remembered views re-detected for a task)
        self.episodes: dict[str, EpisodeHome] = {}
        # the remembered views a running episode's frames are checked against for changes (read again from the
        # store after a restore: not part of the episode state)
        self._remembered: dict[str, list[Keyframe]] = {}
        self.clock: Callable[[], float] = time.time  # a view's time and a change's (a benchmark sets its own)

    @property
    def store(self) -> Store:
        return self._store()

    # ---- the mapper's hooks (services.mapper.extension) ------------------------------------------------
    def begin(self, episode_map: EpisodeMap, part: Any | None, restored: bool) -> None:
        if restored:
            self.restore(episode_map.episode_id, part)
        else:
            self.start(episode_map.start, episode_map, self.objects(episode_map.episode_id))

    def observe(self, robot: str, episode_map: EpisodeMap, frame: Frame, out: StepOutputs,
                timing: dict[str, float]) -> None:
        """The frame is a candidate view of the home; at the first frame in a known home the remembered views are
        re-scored for the question (or re-detected for a task's new classes) before the step's own requests."""
        t0 = time.perf_counter()
        self.offer_view(episode_map, frame)
        out.memory = self.warm(episode_map, frame)
        if frame.step == 0:
            out.step_limit = self.step_limit(episode_map.episode_id)
            out.warm = self.warm_start(episode_map.episode_id)
            if self.detect is not None:
                self.warm_objects(episode_map, self.objects(episode_map.episode_id), frame, self.detect)
        timing["home_warm"] = timing.get("home_warm", 0.0) + (time.perf_counter() - t0) * 1000.0

    def scores(self, episode_map: EpisodeMap, frame: Frame, result: ScoreResult, out: StepOutputs,
               timing: dict[str, float], again: bool) -> ScoreResult:
        if again and frame.step == 0:  # the first step sent again carries its memory steps and budget again
            out.memory = self.memory(episode_map.episode_id)
            out.step_limit = self.step_limit(episode_map.episode_id)
            out.warm = self.warm_start(episode_map.episode_id)
        return result

    def finish(self, episode_map: EpisodeMap) -> None:
        """The episode's map, views and object layer written back to its home."""
        self.commit(episode_map, self.objects(episode_map.episode_id))

    # ---- reading a home ---------------------------------------------------------------------------------
    def _read(self, key: str, decode: Callable[[bytes], Any], home: str, what: str, level: int = logging.ERROR) -> Any:
        """The part at ``key`` decoded, None when absent or unusable (logged at ``level``: ``what``, and what
        follows)."""
        raw = self.store.get(key)
        if raw is None:
            return None
        try:
            return decode(raw)
        except (ValueError, KeyError, TypeError) as exc:
            log.log(level, "home %s: %s unusable (%s)", home, what, exc)
            return None

    def read_index(self, home: str) -> HomeIndex | None:
        return self._read(index_key(home), HomeIndex.from_bytes, home, "stored index (the home starts over)")

    def read_map(self, home: str) -> HomeMap | None:
        return self._read(map_key(home), HomeMap.from_bytes, home, "stored map (ignored)")

    def read_objects(self, home: str, key: str | None = None) -> HomeObjects | None:
        return self._read(key or objects_key(home), HomeObjects.from_bytes, home, "stored object layer (ignored)")

    def read_view(self, home: str, view_id: str) -> Keyframe | None:
        return self._read(view_key(home, view_id), Keyframe.from_bytes, home, f"view {view_id} (skipped)",
                          logging.WARNING)

    # ---- an episode -------------------------------------------------------------------------------------
    def _pool(self, views: list[ViewInfo] | None = None) -> ViewPool:
        return ViewPool(self.settings.home_max_views, self.settings.home_max_bytes, views or [])

    def start(self, start: EpisodeStart, em: EpisodeMap, objects: ObjectMap | None = None) -> None:
        """An episode in a home starts from the home's map (``em`` is fresh); None home: nothing happens. A task
        episode's object layer ``objects`` (fresh) starts from the home's (:meth:`_start_objects`)."""
        if start.home is None:
            return
        index = self.read_index(start.home)
        ep = EpisodeHome(start.home, index.version if index else 0, self._pool(),
                         reset=homes.reset_mark(self.store, start.home))
        if index is not None:
            home_map = self.read_map(start.home)
            task = start.task is not None
            floor = self._start_objects(start, ep, objects, index) if task and objects is not None else None
            if home_map is not None:
                try:
                    # a task searches with the HELIOS layers of its own classes: it starts from the remembered
                    # geometry (paths through known space) and counts as explored only the floor a detector asked
                    # for every one of its classes explored (the object layer holds what it found there); the
                    # rest of the explored map would send it past places whose objects it never detected
                    explored: bool | np.ndarray = not task
                    if floor is not None:
                        explored = floor.on_grid(home_map.origin_x, home_map.origin_y, home_map.shape2d)
                    home_map.apply_to(em, explored=explored)
                    ep.geometry_only = task
                    if task:  # a task keeps its budget (its planner ends it)
                        ep.loaded_cells = int(em.volume.explored.any(axis=2).sum())
                    else:
                        ep.loaded_cells = self._covered_cells(home_map, em)
                        ep.step_limit = self._step_limit(start, ep.loaded_cells * float(em.resolution) ** 2)
                except ValueError as exc:
                    log.error("episode %s: home %s map not used: %s", start.episode_id, start.home, exc)
            # the view memory answers questions (Eq. 9's memory steps); a task's stopper has nothing to answer
            ep.warm_ids = [] if task else [v.view_id for v in index.views[: self.settings.home_warm_views]]
        self.episodes[start.episode_id] = ep
        log.info("episode %s: home %s (version %d): %d covered cells, %d views to re-score, step limit %s",
                 start.episode_id, start.home, ep.base_version, ep.loaded_cells, len(ep.warm_ids),
                 ep.step_limit or start.max_steps)

    def _start_objects(self, start: EpisodeStart, ep: EpisodeHome, objects: ObjectMap,
                       index: HomeIndex) -> FloorMask | None:
        """A task's object layer from the home's (:mod:`services.mapper.home_objects`): the Gaussians with evidence
        for one of the task's classes, with the concentrations the carry-over rule gives for them; the remembered
        views to re-detect at the first frame when a class was never asked for; the floor explored for all of its
        classes (None: none)."""
        if objects.single_frame:  # the trusting agent keeps no 3D layer, so it has nothing to start from
            return None
        stored = self.read_objects(ep.home)
        classes = objects.task_classes
        if stored is not None:
            self.store.set(objects_base_key(ep.home, start.episode_id), stored.to_bytes(),
                           ttl_s=self.settings.home_ttl_s)
            ep.objects_base = True
            keep, gamma = stored.restorable(classes, objects.layer.config.prior,
                                             self.settings.home_restore_objects)
            if len(keep):
                objects.load_home(stored.uid[keep], stored.means[keep], stored.sigma[keep], stored.opacity[keep],
                                  gamma)
        asked = [c for c in classes if stored is not None and stored.asked(c)]
        if len(asked) < len(classes):
            ep.redetect_ids = [v.view_id for v in index.views[: self.settings.home_redetect_views]]
            ep.redetect_without = asked
        floor = None if stored is None else stored.explored_for(classes)
        log.info("episode %s: home %s object layer: %d Gaussians, classes asked before %s, %d views to re-detect",
                 start.episode_id, ep.home, 0 if stored is None else len(stored), asked, len(ep.redetect_ids))
        return floor

    def warm_objects(self, em: EpisodeMap, objects: ObjectMap | None, frame: Frame, detect: Callable[[], Any]) -> int:
        """At a task's first frame (before its own detections): the remembered views re-detected for the task's
        classes through the scorer pool (``detect()``: its DetectRequest call; bounded, parallel, with a
        deadline, as :meth:`warm`) and fused into ``objects`` as frames are, except the pixels of classes the
        home's layer already holds evidence for (counted once). Returns the views fused."""
        ep = self.episodes.get(em.episode_id)
        if ep is None or objects is None or ep.objects_warmed:
            return 0
        ep.objects_warmed = True
        if not ep.redetect_ids:
            return 0
        views = sorted((kf for kf in (self.read_view(ep.home, v) for v in ep.redetect_ids) if kf is not None),
                       key=lambda kf: (kf.t, kf.view_id))  # oldest first: the order they were seen in
        shown = [Frame(episode_id=em.episode_id, step=frame.step, pose=kf.pose, camera_pose=kf.camera_pose,
                       intrinsics=kf.intrinsics, rgb=kf.rgb, depth=kf.depth, instances=kf.instances, labels=kf.labels)
                 for kf in views]
        replies = self._ask_all(detect(), [objects.detect_request(f, seed=memory_seed(em.start.seed, kf.view_id))
                                           for f, kf in zip(shown, views, strict=True)],
                                em.episode_id, [kf.view_id for kf in views])
        without = frozenset(ep.redetect_without)
        fused = 0
        for f, kf, reply in zip(shown, views, replies, strict=True):
            if not isinstance(reply, DetectResult):
                if reply is not None:
                    log.warning("episode %s: remembered view %s not re-detected: %s", em.episode_id, kf.view_id,
                                getattr(reply, "reason", reply))
                continue
            try:
                objects.integrate(f, reply, without)
                fused += 1
            except Exception:
                log.exception("episode %s: remembered view %s not fused", em.episode_id, kf.view_id)
        log.info("episode %s: %d of %d remembered views re-detected for %s", em.episode_id, fused, len(views),
                 objects.task_classes)
        return fused

    def _ask_all(self, call: Callable[[Any], Any], requests: list[Any], episode_id: str,
                 names: list[str]) -> list[Any]:
        """Every request through the scorer pool, ``EQA_HOME_WARM_PARALLEL`` in flight, waiting
        ``EQA_HOME_WARM_TIMEOUT_S`` at most: each reply, or None for a request not answered in time or failed
        (logged)."""
        deadline = time.monotonic() + self.settings.home_warm_timeout_s
        pool = ThreadPoolExecutor(max_workers=self.settings.home_warm_parallel, thread_name_prefix="home-warm")
        try:
            futures = [pool.submit(call, req) for req in requests]
            wait(futures, timeout=max(0.0, deadline - time.monotonic()))
        finally:
            pool.shutdown(wait=False, cancel_futures=True)
        out: list[Any] = []
        for name, fut in zip(names, futures, strict=True):
            if not fut.done() or fut.cancelled() or fut.exception() is not None:
                why = "not answered in time" if not fut.done() or fut.cancelled() else repr(fut.exception())
                log.warning("episode %s: remembered view %s left out: %s", episode_id, name, why)
                out.append(None)
                continue
            out.append(fut.result())
        return out

    def _covered_cells(self, home_map: HomeMap, em: EpisodeMap) -> int:
        """The floor cells ``A_e`` of the warm budget in the home map ``em`` just started from
        (``EQA_HOME_WARM_AREA``): those it observed inside the house, or those with an explored voxel."""
        if self.settings.home_warm_area == "explored":
            return home_map.explored_cells()
        known, free = known_columns(em.volume, em.config.projection)
        back = back_band_cells(em.config.projection.occupied_band, em.volume.config.trunc_voxels)
        return int(observed_floor(known, free, back).sum())

    def _step_limit(self, start: EpisodeStart, covered_m2: float) -> int | None:
        """A question's step limit in a house the home map covers ``covered_m2`` of (None: ``max_steps``)."""
        limit = warm_step_limit(start.max_steps, covered_m2, self.settings.home_warm_budget)
        return limit if limit < start.max_steps else None

    def warm_start(self, episode_id: str) -> WarmStart | None:
        """:attr:`eqa.messages.StepScores.warm` of a question that started from its home's memory (the home held
        a committed episode), with the bounds its memory steps and budget were made with; None: a cold start (no
        home, an empty home, a task)."""
        ep = self.episodes.get(episode_id)
        if ep is None or ep.base_version < 1 or ep.geometry_only:
            return None
        s = self.settings
        return WarmStart(version=ep.base_version, bounds=MemoryBounds(
            max_views=s.home_max_views, warm_views=s.home_warm_views, memory_steps=s.home_memory_steps,
            warm_budget=s.home_warm_budget, warm_area=s.home_warm_area, stale_weight=s.home_stale_weight))

    def step_limit(self, episode_id: str) -> int | None:
        """The episode's step limit for the stopper (:attr:`eqa.messages.StepScores.step_limit`), None: its own."""
        ep = self.episodes.get(episode_id)
        return None if ep is None else ep.step_limit

    def offer_view(self, em: EpisodeMap, frame: Frame) -> None:
        """A frame just integrated: a candidate keyframe of the episode's pool (written when kept)."""
        ep = self.episodes.get(em.episode_id)
        if ep is None or self.settings.home_max_views == 0:
            return
        kf = Keyframe.from_frame(frame, f"{em.episode_id}-{frame.step}", em.resolution, t=self.clock(),
                                 max_depth=em.config.volume.max_depth)
        if ep.memory is not None:  # warm start done: the views it used are what this frame may contradict
            if em.episode_id not in self._remembered:
                self._remembered[em.episode_id] = [k for k in (self.read_view(ep.home, v) for v in ep.warm_ids)
                                                   if k is not None]
            self._check(ep, em, kf, self._remembered[em.episode_id])
        blob = kf.to_bytes()
        kept, evicted = ep.pool.offer(kf.info(len(blob)))
        ttl = self.settings.home_ttl_s
        if kept:
            self.store.set(view_key(ep.home, kf.view_id), blob, ttl_s=ttl)
        if evicted:
            self.store.delete_many([view_key(ep.home, v) for v in evicted])

    def _check(self, ep: EpisodeHome, em: EpisodeMap, current: Keyframe, views: list[Keyframe]) -> None:
        """Record a change when ``current`` contradicts a remembered view that sees the same floor cells."""
        if self.settings.home_stale_weight >= 1.0:  # stale evidence not down-weighted: nothing to look for
            return
        mine = cell_keys(current.cells)
        shared = sorted(((len(mine & cell_keys(kf.cells)), kf.view_id, kf) for kf in views),
                        key=lambda s: (-s[0], s[1]))
        cells, ids = [], []
        for n, _, kf in shared[:CHANGE_VIEWS]:
            if n == 0:
                break
            bad = disagreement(kf, current, em.resolution, max_depth=em.config.volume.max_depth)
            if len(bad):
                cells.append(bad)
                ids.append(kf.view_id)
        if ids:
            ep.changes.append(ObservedChange(current.t, np.unique(np.concatenate(cells), axis=0), tuple(ids)))
            log.info("episode %s: step %d contradicts %d remembered views (%d cells): their evidence is stale",
                     em.episode_id, current.step, len(ids), len(ep.changes[-1].cells))

    def memory(self, episode_id: str) -> list[MemoryScore]:
        ep = self.episodes.get(episode_id)
        return [] if ep is None or ep.memory is None else list(ep.memory)

    def warm(self, em: EpisodeMap, frame: Frame) -> list[MemoryScore]:
        """At the episode's first frame (integrated, before its own scores are applied): re-score the remembered
        views for this question, write their semantic values, return the memory steps (oldest view first)."""
        ep = self.episodes.get(em.episode_id)
        if ep is None or ep.memory is not None:  # not a home episode, or warmed at its first frame
            return []
        ep.memory = []
        if not ep.warm_ids or em.maps is None:
            return []
        views = [kf for kf in (self.read_view(ep.home, v) for v in ep.warm_ids) if kf is not None]
        self._remembered[em.episode_id] = views
        now = self.clock()
        if frame.step == 0 and views:  # the first frame may already show a change
            self._check(ep, em, Keyframe.from_frame(frame, "", em.resolution, t=now,
                                                    max_depth=em.config.volume.max_depth), views)
        index = self.read_index(ep.home)
        weights = dict(zip([kf.view_id for kf in views], stale_weights(
            [kf.info(0) for kf in views], now, [*(index.changes if index else []), *ep.changes],
            self.settings.home_stale_age_s, self.settings.home_stale_weight), strict=True))
        blind = em.start.question.without_ground_truth()
        requests = []
        for kf in views:
            points = prompt_points(em.maps.free, em.origin, em.resolution, kf.depth, kf.intrinsics, kf.camera_pose,
                                   em.config.prompt)
            requests.append((kf, points, ScoreRequest(
                episode_id=em.episode_id, step=frame.step, question=blind, rgb=kf.rgb, prompt_points=points,
                instances=kf.instances, labels=kf.labels, depth=kf.depth, seed=memory_seed(em.start.seed, kf.view_id))))
        replies = self._ask_all(self.scorer(), [req for _, _, req in requests], em.episode_id,
                                [kf.view_id for kf, _, _ in requests])
        scored: list[tuple[Keyframe, Any, ScoreResult]] = []
        for (kf, points, _), result in zip(requests, replies, strict=True):
            if result is None:
                continue
            if isinstance(result, ErrorReply):
                log.warning("episode %s: remembered view %s left out: %s", em.episode_id, kf.view_id, result.reason)
                continue
            scored.append((kf, points, result))
        for kf, points, result in scored:  # every scored view's Eq. 3 values guide the exploration
            try:
                em.apply_scores(result.lsv, result.gsv, points=points)
            except ValueError as exc:
                log.warning("episode %s: values of remembered view %s not written: %s", em.episode_id, kf.view_id,
                            exc)
        def relevance(s: tuple[Keyframe, Any, ScoreResult]) -> float:  # stale evidence down-weighted
            return float(s[2].relevance) * weights[s[0].view_id]

        if 0 < self.settings.home_memory_steps < len(scored):
            # the stopper gets the most relevant views only: each memory step is one more term of Eq. 9's running
            # intersection (and of the calibration's min over steps), so views that do not bear on the question
            # would only make q_hat larger; a warm table is calibrated with the same rule
            scored = sorted(scored, key=lambda s: (-relevance(s), s[0].view_id))
            scored = scored[: self.settings.home_memory_steps]
        scored.sort(key=lambda s: (s[0].t, s[0].view_id))  # oldest first: the order they were seen in
        out = []
        for kf, _, result in scored:
            out.append(MemoryScore(answer_probs=list(result.answer_probs), relevance=relevance((kf, None, result)),
                                   view_step=kf.step, seen_at=kf.t))
        ep.memory = out
        log.info("episode %s: warm start from %d of %d remembered views (%d stale)", em.episode_id, len(out),
                 len(views), sum(1 for w in weights.values() if w < 1.0))
        return list(out)

    # ---- persistence within the episode -----------------------------------------------------------------
    def dump(self, episode_id: str) -> dict[str, Any] | None:
        ep = self.episodes.get(episode_id)
        return None if ep is None else ep.dump()

    def restore(self, episode_id: str, part: Any) -> None:
        """The home part of a restored episode; its candidate views' cells are read back from their keyframes."""
        if not isinstance(part, dict):
            return
        home = str(part["home"])
        views = []
        for v in part.get("pool", []):
            kf = self.read_view(home, str(v["view_id"]))
            if kf is not None:
                views.append(ViewInfo(kf.view_id, kf.t, int(v["nbytes"]), kf.cells, kf.episode_id, kf.step))
        memory = part.get("memory")
        self.episodes[episode_id] = EpisodeHome(
            home=home, base_version=int(part["base_version"]), pool=self._pool(views),
            reset=None if part.get("reset") is None else str(part["reset"]),
            warm_ids=[str(v) for v in part.get("warm_ids", [])], loaded_cells=int(part.get("loaded_cells", 0)),
            step_limit=None if part.get("step_limit") is None else int(part["step_limit"]),
            geometry_only=bool(part.get("geometry_only", False)), objects_base=bool(part.get("objects_base", False)),
            redetect_ids=[str(v) for v in part.get("redetect_ids", [])],
            redetect_without=[str(c) for c in part.get("redetect_without", [])],
            objects_warmed=bool(part.get("objects_warmed", False)),
            memory=None if memory is None else [MemoryScore.model_validate(m) for m in memory],
            changes=[ObservedChange.from_json(c) for c in part.get("changes", [])])

    # ---- the end: write the home back -------------------------------------------------------------------
    def commit(self, em: EpisodeMap, objects: ObjectMap | None = None) -> HomeIndex | None:
        """Commit the episode's map, views and (a task's) object layer ``objects`` to its home (see the module's
        doc); the new index."""
        ep = self.episodes.pop(em.episode_id, None)
        self._remembered.pop(em.episode_id, None)
        if ep is None:
            return None
        try:
            return self._finish(ep, em, objects)
        finally:
            if ep.objects_base:
                self.store.delete(objects_base_key(ep.home, em.episode_id))

    def _finish(self, ep: EpisodeHome, em: EpisodeMap, objects: ObjectMap | None) -> HomeIndex | None:
        if em.step < 0:  # no frame integrated: nothing new to remember
            self.store.delete_many([view_key(ep.home, v.view_id) for v in ep.pool.views])
            return None
        for attempt in range(COMMIT_ATTEMPTS):
            with homes.locked(self.store, ep.home, self.settings.instance, LOCK_WAIT_S) as taken:
                if not taken:
                    log.error("home %s: lock not obtained in %.0f s; episode %s not remembered", ep.home,
                              LOCK_WAIT_S, em.episode_id)
                    return None
                if homes.reset_mark(self.store, ep.home) != ep.reset:
                    # the user reset the home after this episode started: its memory must not come back
                    self.store.delete_many([view_key(ep.home, v.view_id) for v in ep.pool.views])
                    log.info("home %s: reset since episode %s started; the episode is not remembered", ep.home,
                             em.episode_id)
                    return None
                done = self._commit(ep, em, objects)
                if done is not None:
                    return done
            # the index changed under this commit: its lock expired (a commit slower than the lock's TTL) and
            # another writer committed or reset meanwhile; the next attempt reads what it wrote and merges
            log.warning("home %s: index changed during episode %s's commit (attempt %d); committing again", ep.home,
                        em.episode_id, attempt + 1)
        log.error("home %s: episode %s not remembered: the index changed during %d commits", ep.home, em.episode_id,
                  COMMIT_ATTEMPTS)
        return None

    def _commit_objects(self, ep: EpisodeHome, em: EpisodeMap, objects: ObjectMap | None, index: HomeIndex,
                        budget: int) -> HomeObjects | None:
        """The home's object layer after the episode, within ``budget`` bytes (written by the caller): a task's
        own evidence, measured against the layer it started from, added to the layer stored now
        (:func:`commit_layer`: another episode of the home may have committed meanwhile); a question, or the
        trusting agent (no 3D layer), leaves the stored layer as it is."""
        stored = self.read_objects(ep.home)
        if objects is None or em.start.task is None or objects.single_frame:
            out = stored
        else:
            base = self.read_objects(ep.home, objects_base_key(ep.home, em.episode_id)) if ep.objects_base else None
            if ep.objects_base and base is None:
                log.error("home %s: episode %s lost the object layer it started from; its own evidence is measured "
                          "against the layer stored now", ep.home, em.episode_id)
                base = stored
            if stored is not None and index.version != ep.base_version:
                log.info("home %s: episode %s's object evidence added to the layer committed meanwhile", ep.home,
                         em.episode_id)
            a = objects.home_arrays()
            out = commit_layer(base, a["uid"], a["means"], a["sigma"], a["opacity"], a["gamma"],
                               objects.task_classes, objects.layer.config.prior, em.episode_id, self.clock(),
                               floor_of(em.volume, float(em.resolution)), onto=stored)
        if out is None:
            return None
        out = out.bounded(self.settings.helios_max_gaussians)
        while len(out.to_bytes()) > budget and len(out):
            out = out.bounded(len(out) // 2)
        return out if len(out.to_bytes()) <= budget else None

    def _commit(self, ep: EpisodeHome, em: EpisodeMap, objects: ObjectMap | None = None) -> HomeIndex | None:
        """Write the episode into the home; None when the index changed since this commit read it (nothing is
        written then: the map, object layer and index go in one compare-and-set on the index's bytes)."""
        s = self.settings
        read_as = self.store.get(index_key(ep.home))  # the guard of the write below
        index = self.read_index(ep.home) or HomeIndex()
        mine = HomeMap.from_episode(em)
        if index.version != ep.base_version:
            stored = self.read_map(ep.home)
            if stored is not None:
                log.info("home %s: version %d since episode %s started at %d; maps merged", ep.home, index.version,
                         em.episode_id, ep.base_version)
                mine = stored.merge(mine)
        elif ep.geometry_only:  # what earlier episodes explored stays explored in the home
            stored = self.read_map(ep.home)
            if stored is not None:
                mine = mine.with_explored_of(stored)
        map_bytes = mine.to_bytes()
        budget = s.home_max_bytes - len(map_bytes)
        if budget < 0:
            log.warning("home %s: map of %d bytes exceeds EQA_HOME_MAX_BYTES=%d; the map is not stored",
                        ep.home, len(map_bytes), s.home_max_bytes)
            budget = s.home_max_bytes
        home_objects = self._commit_objects(ep, em, objects, index, budget)
        objects_bytes = b"" if home_objects is None else home_objects.to_bytes()
        budget -= len(objects_bytes)
        candidates = {v.view_id: v for v in [*index.views, *ep.pool.views]}
        chosen = select_views(list(candidates.values()), s.home_max_views, budget)
        chosen_ids = {v.view_id for v in chosen}
        ttl = s.home_ttl_s
        items: list[tuple[str, bytes]] = []
        drop: list[str] = []
        if len(map_bytes) <= s.home_max_bytes:
            items.append((map_key(ep.home), map_bytes))
        else:
            drop.append(map_key(ep.home))
        if objects_bytes:
            items.append((objects_key(ep.home), objects_bytes))
        else:
            drop.append(objects_key(ep.home))
        scene = em.start.question.scene
        # a change matters to views older than it: one older than every kept view is forgotten
        oldest = min((v.t for v in chosen), default=math.inf)
        changes = [c for c in [*index.changes, *ep.changes] if c.t > oldest][-MAX_CHANGES:]
        new = HomeIndex(version=index.version + 1, views=chosen, episodes=index.episodes + 1, changes=changes,
                        scenes=(index.scenes + ([scene] if scene not in index.scenes else []))[-64:],
                        map_bytes=len(map_bytes) if len(map_bytes) <= s.home_max_bytes else 0,
                        created_at=index.created_at, objects_bytes=len(objects_bytes),
                        gaussians=0 if home_objects is None else len(home_objects))
        if ep.objects_base:  # its own evidence is in the layer now: the copy it started from goes with the index
            drop.append(objects_base_key(ep.home, em.episode_id))
        items.append((index_key(ep.home), new.to_bytes()))
        if not self.store.set_many_if(index_key(ep.home), read_as, items, ttl_s=ttl, then_delete=drop):
            return None
        # every kept view's TTL runs from now; the views left out go
        for v in chosen:
            raw = self.store.get(view_key(ep.home, v.view_id))
            if raw is not None:
                self.store.set(view_key(ep.home, v.view_id), raw, ttl_s=ttl)
        gone = [view_key(ep.home, vid) for vid in candidates if vid not in chosen_ids]
        if gone:
            self.store.delete_many(gone)
        summary = homes.HomeSummary(home=ep.home, episodes=new.episodes, views=len(chosen),
                                    bytes=new.map_bytes + new.objects_bytes + new.view_bytes,
                                    gaussians=new.gaussians, created_at=new.created_at,
                                    updated_at=time.time(), scenes=new.scenes)
        homes.write_summary(self.store, summary, ttl_s=ttl)
        log.info("home %s: version %d after episode %s: %d views, %d bytes", ep.home, new.version, em.episode_id,
                 len(chosen), summary.bytes)
        return new
