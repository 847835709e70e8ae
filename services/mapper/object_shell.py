"""The mapper shell's part for the HELIOS object layer (task episodes only), as a mixin of
:class:`services.mapper.service.MapperService` so the service keeps one obvious home per idea.

Per task episode (``EpisodeStart.task`` set): an :class:`~services.mapper.object_map.ObjectMap` with the task's
classes, and one value layer per task class, ``helios:<class>`` (paper 3.1.2). Per frame, while the mapper
integrates and the question's scores are computed, one worker asks the scorer pool for the frame's detections
(:class:`~eqa.messages.DetectRequest`) and for the per-target value prompt "Seems like there is a (class)
ahead" (:class:`~eqa.messages.ValueRequest`); then the detections are fused, each value fused into its layer
over the frame's field-of-view cone by confidence (paper 3.1.2, as VLFM: :mod:`services.mapper.fov_values`;
the question layer keeps Explore-EQA's max-fused prompt points), and the map update carries the instances
(:attr:`~eqa.messages.MapUpdate.objects`). The phase follows the simulator's skill reports on the frames: once a
pick succeeded, the frontiers take their values from the goal receptacle's layer and the goal receptacle's
candidates get the gaze points (:func:`services.mapper.object_map.phase_classes`). The trusting agent
(``EpisodeStart.ablation``) has no 3D layer: its object map holds each frame's detections alone. A detection
that fails is reported on the mapper's error stream and the frame is not fused (no detection is not "nothing
detected"). The object layer goes into the episode's stored state with the map, so a restarted mapper
continues it. Question episodes are untouched: no request, no layer, the same state bytes as before.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np

from eqa.messages import (
    DetectRequest,
    DetectResult,
    EpisodeStart,
    ErrorReply,
    Frame,
    MapUpdate,
    ValueRequest,
    ValueResult,
)
from services.mapper import fov_values
from services.mapper.semantic_map import QUESTION_LAYER

if TYPE_CHECKING:
    from services.mapper.object_map import ObjectMap, ObjectMapConfig


TORCH_THREADS = 1  # torch intra-op threads of the mapper's object layer (see _object_map_module)


def _object_map_module() -> Any:
    """The object layer (torch) is imported on the first task episode, not when the mapper starts: question
    episodes never need it, and importing torch made every mapper (re)start several seconds slower -- longer than
    the sim's step resends wait for a restarted mapper.

    Torch then runs on :data:`TORCH_THREADS` thread: the mapper shares the cores with the other services, and
    torch's default (one thread per core, spinning while waiting) made the object layer 7-10x slower on the
    loaded 2-core machine (6 updates + 36 optimistic views: 1.3-1.4 s CPU with 1 thread, 10-12 s with 2; issue
    17), the same numbers either way."""
    import torch

    from services.mapper import object_map

    if torch.get_num_threads() != TORCH_THREADS:
        torch.set_num_threads(TORCH_THREADS)
    return object_map

log = logging.getLogger(__name__)

Detect = Callable[[DetectRequest], DetectResult]
Values = Callable[[ValueRequest], ValueResult]
LAYER_PREFIX = "helios:"
CONFIDENCE_PREFIX = "confidence/"  # the map plane with a task value layer's field-of-view confidence


def task_map_config(config: Any) -> Any:
    """The mapper's configuration for a task episode: ``config`` with the 2D obstacle band starting at the voxel
    layer that holds the robot's obstacle height (:data:`eqa.robot.OBSTACLE_MIN_Z_M`, where the sim's
    collisions start) instead of the question map's floor clearance. With the question map's 0.1 m, the voxel
    layer 0-0.1 m was left out and objects lower than about 0.15 m (shoes, 0.12 m) were never mapped: the task
    paths drove over them and the sim counted the collisions (14 of the first 25 collisions on the evaluation
    seeds were with shoes on the floor). Question episodes keep their map (their figures are made with it)."""
    import dataclasses

    from eqa import robot as body

    # the band takes the voxel layers whose centre is at or above floor_clearance: from the layer that reaches
    # above the obstacle height (a layer's centre lies half a voxel above its bottom)
    low = body.OBSTACLE_MIN_Z_M - config.volume.voxel_size / 2
    return dataclasses.replace(config, projection=dataclasses.replace(
        config.projection, floor_clearance=min(config.projection.floor_clearance, low)))


def value_layer(cls: str) -> str:
    return f"{LAYER_PREFIX}{cls}"


def frontier_class(task: Any, holding: bool) -> str:
    """The class whose value layer (paper 3.1.2: "one map layer for the pick location and one for the place
    location") values the frontiers: the pick location (start receptacle, else the object) until the object is
    held, then the place location (goal receptacle)."""
    if holding and task.goal_receptacle:
        return str(task.goal_receptacle)
    return str(task.start_receptacle or task.object)


def obstacle_heights(em: Any) -> np.ndarray | None:
    """Height (m) of the highest occupied voxel of each map cell up to the camera height, 0 where none: the
    heights the gaze-point occlusion test compares with ``EQA_HELIOS_GAZE_OBSTACLE_M`` (occupied = observed
    and within the occupied band behind a surface, as the 2D occupancy map)."""
    v, pc = em.volume, em.config.projection
    if v.tsdf.size == 0:
        return None
    z = v.z_centers
    sel = np.nonzero((z >= pc.floor_clearance) & (z <= pc.camera_height))[0]
    if sel.size == 0:
        return None
    t, w = v.tsdf[:, :, sel], v.weight[:, :, sel]
    occ = (w > 0) & (t <= 0) & (t >= -pc.occupied_band)
    top = occ.shape[2] - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    any_occ = occ.any(axis=2)
    traversed = v.planes.get("traversed")
    if traversed is not None:  # cells the robot stood on are free (as the occupancy map)
        any_occ &= ~traversed
    return np.where(any_occ, z[sel][top] + v.config.voxel_size / 2, 0.0).astype(np.float32)


class ObjectLayerShell:
    """Mixin: needs ``self.settings``, ``self.bus``, ``self.error(robot, episode_id, step, reason)`` and
    ``self.recorders`` of :class:`eqa.episode_service.EpisodeService`."""

    settings: Any
    bus: Any
    recorders: dict[str, Any]
    error: Callable[..., None]

    def objects_init(self, detector: Detect | None = None, values: Values | None = None) -> None:
        self._objects_config: ObjectMapConfig | None = None
        self.objects: dict[str, ObjectMap] = {}
        self.last_objects: dict[str, list] = {}
        self._detect, self._values = detector, values
        self._objects_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapper-objects")

    @property
    def objects_config(self) -> ObjectMapConfig:
        if self._objects_config is None:
            self._objects_config = _object_map_module().ObjectMapConfig.from_settings(self.settings)
        return self._objects_config

    def objects_close(self) -> None:
        self._objects_pool.shutdown(wait=True)

    def _pool_client(self) -> tuple[Detect, Values]:
        if self._detect is None or self._values is None:
            from eqa.scorer_client import ScorerClient

            client = ScorerClient(self.bus, self.settings)
            self._detect = self._detect or client.detect
            self._values = self._values or client.values
        return self._detect, self._values

    # ---- episode lifecycle ------------------------------------------------------------------------------
    def objects_layers(self, start: EpisodeStart) -> list[str] | None:
        """The value layers of a new episode (None: the default question layer only) and, for a task episode,
        its object map."""
        if start.task is None:
            return None
        om_mod = _object_map_module()
        self.objects[start.episode_id] = om_mod.ObjectMap.for_task(start.task, self.objects_config,
                                                                   single_frame=start.ablation == "trusting")
        classes, _ = om_mod.task_classes(start.task, self.objects_config)
        return [QUESTION_LAYER, *(value_layer(c) for c in classes)]

    def objects_finish(self, episode_id: str) -> None:
        self.objects.pop(episode_id, None)
        self.last_objects.pop(episode_id, None)

    def objects_dump(self, episode_id: str, map_state: bytes) -> Any:
        om = self.objects.get(episode_id)
        return map_state if om is None else {"map": map_state, "objects": om.snapshot()}

    def objects_load(self, episode_id: str, data: Any, start_of: Callable[[bytes], Any]) -> Any:
        """Restore: ``data`` is the map's bytes (question episodes, older states) or ``{"map", "objects"}``;
        ``start_of`` restores the map from its bytes. Returns the map."""
        if isinstance(data, dict):
            em = start_of(data["map"])
            em.config = task_map_config(em.config)
            self.objects[episode_id] = _object_map_module().ObjectMap.restore(data["objects"], self.objects_config)
            return em
        em = start_of(data)
        if em.start.task is not None:  # a task episode saved before its layer existed: start a fresh one
            em.config = task_map_config(em.config)
            self.objects[episode_id] = _object_map_module().ObjectMap.for_task(
                em.start.task, self.objects_config, single_frame=em.start.ablation == "trusting")
        return em

    # ---- per frame --------------------------------------------------------------------------------------
    def objects_submit(self, robot: str, em: Any, frame: Frame) -> Future | None:
        om = self.objects.get(em.episode_id)
        if om is None:
            return None
        return self._objects_pool.submit(self._objects_ask, om, em, frame)

    def _objects_ask(self, om: ObjectMap, em: Any, frame: Frame) -> tuple[Any, Any, float]:
        detect, values = self._pool_client()
        t0 = time.perf_counter()
        det, val = ask_objects(om, em, frame, detect, values)
        return det, val, (time.perf_counter() - t0) * 1000.0

    def objects_apply(self, robot: str, em: Any, frame: Frame, pending: Future | None,
                      timing: dict[str, float]) -> str | None:
        """Fuse the frame's detections and write its values (:func:`fuse_frame`); returns the layer the
        frontiers take their values from in a task episode, or None."""
        om = self.objects.get(em.episode_id)
        if pending is None or om is None:
            return None
        det, val, ask_ms = pending.result()
        timing["objects_ask"] = ask_ms
        layer, errors = fuse_frame(om, em, frame, det, val, timing)
        for reason in errors:
            self.error(robot, em.episode_id, frame.step, reason)
        return layer

    def objects_attach(self, em: Any, update: MapUpdate, frame: Frame | None, timing: dict[str, float]) -> None:
        """Put the episode's instances (with gaze points on this update's map) into ``update``."""
        om = self.objects.get(em.episode_id)
        if om is None:
            return
        attach_objects(om, em, update, frame, timing)
        self.last_objects[em.episode_id] = update.objects

    def objects_record(self, em: Any, frame: Frame) -> None:
        om = self.objects.get(em.episode_id)
        rec = self.recorders.get(em.episode_id)
        if om is None or rec is None or getattr(rec, "stream", None) is None:
            return
        try:
            rec.set_step(frame.step)
            _object_map_module().log_rerun(rec, om, self.last_objects.get(em.episode_id, []))
        except Exception:
            log.exception("episode %s: recording the object layer failed; going on", em.episode_id)


def ask_objects(om: ObjectMap, em: Any, frame: Frame, detect: Detect, values: Values) -> tuple[Any, Any]:
    """The frame's detections and per-target value prompts (HELIOS 3.1.2) from the scorer pool; each reply is
    the result, or the exception its request raised."""
    try:
        det: Any = detect(om.detect_request(frame, seed=em.start.seed))
    except Exception as exc:
        det = exc
    try:
        val: Any = values(ValueRequest(
            episode_id=em.episode_id, step=frame.step, rgb=frame.rgb, targets=om.task_classes,
            instances=frame.instances, labels=frame.labels, depth=frame.depth, seed=em.start.seed,
        ))
    except Exception as exc:
        val = exc
    return det, val


def fuse_frame(om: ObjectMap, em: Any, frame: Frame, det: Any, val: Any,
               timing: dict[str, float]) -> tuple[str, list[str]]:
    """One frame's object-layer step of a task episode (the mapper service's and the in-process runner's,
    :mod:`eqa.app.task_cores`): the phase from the frame's skill report, the detections fused into the 3D
    layer, each target's value fused into its layer over the field-of-view cone by confidence. ``det`` /
    ``val``: the scorer pool's replies (or the exception a request raised). Returns the layer the frontiers
    take their values from (:func:`frontier_class`) and the reasons of what was not fused (for the error
    stream)."""
    errors: list[str] = []
    skill = getattr(frame, "skill", None)
    if skill is not None and skill.skill == "pick" and skill.success:
        om.holding = True
    t0 = time.perf_counter()
    if isinstance(det, DetectResult):
        try:
            stats = om.integrate(frame, det)
            timing.update({f"objects_{k}": v for k, v in stats.timing_ms.items()})
        except Exception as exc:
            log.exception("episode %s: object layer update failed", em.episode_id)
            errors.append(f"object layer not updated: {type(exc).__name__}: {exc}")
    else:
        reason = det.reason if isinstance(det, ErrorReply) else f"{type(det).__name__}: {det}"
        errors.append(f"detector failed, frame not fused: {reason}")
    if isinstance(val, ValueResult) and len(val.values) == len(om.task_classes):
        rows, cols, conf = fov_values.fov_cells(frame.depth, frame.intrinsics, frame.camera_pose, em.origin,
                                                em.resolution, em.layer(value_layer(om.task_classes[0])).shape)
        for cls, v in zip(om.task_classes, val.values, strict=True):
            name = value_layer(cls)
            fov_values.fuse(em.layer(name), em.volume.add_plane(f"{CONFIDENCE_PREFIX}{name}", 0.0, np.float32),
                            rows, cols, conf, float(v))
    elif not isinstance(val, ValueResult):
        reason = val.reason if isinstance(val, ErrorReply) else f"{type(val).__name__}: {val}"
        errors.append(f"value prompt failed: {reason}")
    timing["objects_fuse"] = (time.perf_counter() - t0) * 1000.0
    return value_layer(frontier_class(em.start.task, om.holding)), errors


def attach_objects(om: ObjectMap, em: Any, update: MapUpdate, frame: Frame | None, timing: dict[str, float]) -> None:
    """Put the instances of ``om`` (with gaze points on this update's map, for the current phase's targets)
    into ``update``."""
    t0 = time.perf_counter()
    height = float(frame.camera_pose[2, 3]) if frame is not None else 1.5
    # the robot's head camera has a fixed tilt: gaze points are scored for the view it really gets there
    pitch = float(np.arcsin(np.clip(frame.camera_pose[2, 2], -1.0, 1.0))) if frame is not None else None
    targets = _object_map_module().phase_classes(em.start.task, om.holding) if em.start.task else None
    update.objects = om.summaries(update.grid, update.occupied, obstacle_heights(em), camera_height=height,
                                  camera_pitch=pitch, targets=targets)
    timing["objects_summary"] = (time.perf_counter() - t0) * 1000.0
    update.timing_ms.update(timing)
