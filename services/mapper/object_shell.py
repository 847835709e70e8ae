"""The HELIOS object layer (task episodes only): a mapper extension (:mod:`services.mapper.extension`) of
:class:`services.mapper.service.MapperService`.

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
continues it. Question episodes are untouched: no request, no layer, no part in the stored state.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np

from eqa.messages import (
    DetectResult,
    EpisodeStart,
    Frame,
    MapUpdate,
    ObjectInstance,
    Task,
    ValueRequest,
    ValueResult,
)
from eqa.recording import EpisodeRecorder
from services.mapper import fov_values
from services.mapper.episode_map import EpisodeMap
from services.mapper.extension import (
    Detect,
    MapperContext,
    MapperExtension,
    StepOutputs,
    Values,
    call_pool,
    failure,
    object_map_module,
)

if TYPE_CHECKING:
    from services.mapper.object_map import ObjectMap


log = logging.getLogger(__name__)

LAYER_PREFIX = "helios:"
CONFIDENCE_PREFIX = "confidence/"  # the map plane with a task value layer's field-of-view confidence


def task_map_config(config: Any) -> Any:
    """The mapper's configuration for a task episode: ``config`` with the 2D obstacle band starting at the voxel
    layer that holds the robot's obstacle height (:data:`eqa.robot.OBSTACLE_MIN_Z_M`, where the sim's
    collisions start) instead of the question map's floor clearance: with the question map's 0.1 m, objects
    lower than about 0.15 m (shoes, 0.12 m) were never mapped, and task paths drove over them. Question episodes
    keep their map (their figures are made with it)."""
    import dataclasses

    from eqa import robot as body

    # the band takes the voxel layers whose centre is at or above floor_clearance: from the layer that reaches
    # above the obstacle height (a layer's centre lies half a voxel above its bottom)
    low = body.OBSTACLE_MIN_Z_M - config.volume.voxel_size / 2
    return dataclasses.replace(config, projection=dataclasses.replace(
        config.projection, floor_clearance=min(config.projection.floor_clearance, low)))


def value_layer(cls: str) -> str:
    return f"{LAYER_PREFIX}{cls}"


def frontier_class(task: Task, holding: bool) -> str:
    """The class whose value layer (paper 3.1.2: "one map layer for the pick location and one for the place
    location") values the frontiers: the pick location (start receptacle, else the object) until the object is
    held, then the place location (goal receptacle)."""
    if holding and task.goal_receptacle:
        return str(task.goal_receptacle)
    return str(task.start_receptacle or task.object)


def obstacle_heights(episode_map: EpisodeMap) -> np.ndarray | None:
    """Height (m) of the highest occupied voxel of each map cell up to the camera height, 0 where none: the
    heights the gaze-point occlusion test compares with ``EQA_HELIOS_GAZE_OBSTACLE_M`` (occupied = observed
    and within the occupied band behind a surface, as the 2D occupancy map)."""
    v, pc = episode_map.volume, episode_map.config.projection
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


class ObjectLayerExtension(MapperExtension):
    """The HELIOS object layer of task episodes as a mapper extension (module docstring): per episode its
    :class:`~services.mapper.object_map.ObjectMap` (``maps``) and the instances of its last map update."""

    state_key = "objects"

    def __init__(self, context: MapperContext) -> None:
        self.context = context
        self.maps: dict[str, ObjectMap] = {}
        self.last_objects: dict[str, list[ObjectInstance]] = {}
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapper-objects")

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    # ---- episode lifecycle ------------------------------------------------------------------------------
    def _new_map(self, start: EpisodeStart) -> ObjectMap:
        assert start.task is not None
        return object_map_module().ObjectMap.for_task(start.task, self.context.objects_config,
                                                      single_frame=start.ablation == "trusting")

    def begin(self, episode_map: EpisodeMap, part: Any | None, restored: bool) -> None:
        """A task episode: its object map (the stored one when taken up from the store), and one value layer per
        task class."""
        start = episode_map.start
        if part is not None:
            self.maps[start.episode_id] = object_map_module().ObjectMap.restore(part, self.context.objects_config)
        elif start.task is not None:
            self.maps[start.episode_id] = self._new_map(start)
        if start.task is not None and not restored:
            classes, _ = object_map_module().task_classes(start.task, self.context.objects_config)
            for c in classes:
                episode_map.add_layer(value_layer(c))

    def finish(self, episode_map: EpisodeMap) -> None:
        self.maps.pop(episode_map.episode_id, None)
        self.last_objects.pop(episode_map.episode_id, None)

    def dump(self, episode_id: str) -> bytes | None:
        objects = self.maps.get(episode_id)
        return None if objects is None else objects.snapshot()

    # ---- per frame --------------------------------------------------------------------------------------
    def submit(self, robot: str, episode_map: EpisodeMap, frame: Frame) -> Future[Any] | None:
        objects = self.maps.get(episode_map.episode_id)
        if objects is None:
            return None
        return self._pool.submit(self._ask, objects, episode_map, frame)

    def _ask(self, objects: ObjectMap, episode_map: EpisodeMap, frame: Frame) -> tuple[Any, Any, float]:
        detect, values = self.context.detect_and_values()
        t0 = time.perf_counter()
        det, val = ask_objects(objects, episode_map, frame, detect, values)
        return det, val, (time.perf_counter() - t0) * 1000.0

    def apply(self, robot: str, episode_map: EpisodeMap, frame: Frame, pending: Future[Any] | None, out: StepOutputs,
              timing: dict[str, float]) -> None:
        """Fuse the frame's detections and write its values (:func:`fuse_frame`); the frontiers of a task
        episode take their values from the current phase's search target (:func:`frontier_class`)."""
        objects = self.maps.get(episode_map.episode_id)
        if pending is None or objects is None:
            return
        det, val, ask_ms = pending.result()
        timing["objects_ask"] = ask_ms
        out.frontier_layer, errors = fuse_frame(objects, episode_map, frame, det, val, timing)
        for reason in errors:
            self.context.error(robot, episode_map.episode_id, frame.step, reason)

    def attach(self, episode_map: EpisodeMap, update: MapUpdate, frame: Frame) -> None:
        """Put the episode's instances (with gaze points on this update's map) into ``update``."""
        objects = self.maps.get(episode_map.episode_id)
        if objects is None:
            return
        attach_objects(objects, episode_map, update, frame)
        self.last_objects[episode_map.episode_id] = update.objects

    def record(self, episode_map: EpisodeMap, frame: Frame, recorder: EpisodeRecorder) -> None:
        objects = self.maps.get(episode_map.episode_id)
        if objects is None:
            return
        try:
            recorder.set_step(frame.step)
            object_map_module().log_rerun(recorder, objects, self.last_objects.get(episode_map.episode_id, []))
        except Exception:
            log.exception("episode %s: recording the object layer failed; going on", episode_map.episode_id)


def ask_objects(objects: ObjectMap, episode_map: EpisodeMap, frame: Frame, detect: Detect,
                values: Values) -> tuple[Any, Any]:
    """The frame's detections and per-target value prompts (HELIOS 3.1.2) from the scorer pool; each reply is
    the result, or the exception its request raised (:func:`call_pool`)."""
    start = episode_map.start
    det = call_pool(detect, objects.detect_request(frame, seed=start.seed, draws=start.draws))
    val = call_pool(values, ValueRequest(
        episode_id=episode_map.episode_id, step=frame.step, rgb=frame.rgb, targets=objects.task_classes,
        instances=frame.instances, labels=frame.labels, depth=frame.depth, seed=start.seed, draws=start.draws,
    ))
    return det, val


def fuse_frame(objects: ObjectMap, episode_map: EpisodeMap, frame: Frame, det: Any, val: Any,
               timing: dict[str, float]) -> tuple[str, list[str]]:
    """One frame's object-layer step of a task episode (the mapper's and the in-process runner's,
    :mod:`eqa_app.task_cores`): the phase from the frame's skill report, the detections fused into the 3D
    layer, each target's value fused into its layer over the field-of-view cone by confidence. ``det`` /
    ``val``: the scorer pool's replies (or the exception a request raised). Returns the layer the frontiers
    take their values from (:func:`frontier_class`) and the reasons of what was not fused (for the error
    stream)."""
    errors: list[str] = []
    skill = frame.skill
    if skill is not None and skill.skill == "pick" and skill.success:
        objects.holding = True
    t0 = time.perf_counter()
    if isinstance(det, DetectResult):
        try:
            stats = objects.integrate(frame, det)
            timing.update({f"objects_{k}": v for k, v in stats.timing_ms.items()})
        except Exception as exc:
            log.exception("episode %s: object layer update failed", episode_map.episode_id)
            errors.append(f"object layer not updated: {type(exc).__name__}: {exc}")
    else:
        errors.append(f"detector failed, frame not fused: {failure(det)}")
    if isinstance(val, ValueResult) and len(val.values) == len(objects.task_classes):
        shape = episode_map.layer(value_layer(objects.task_classes[0])).shape
        rows, cols, conf = fov_values.fov_cells(frame.depth, frame.intrinsics, frame.camera_pose, episode_map.origin,
                                                episode_map.resolution, shape)
        for cls, v in zip(objects.task_classes, val.values, strict=True):
            name = value_layer(cls)
            confidence = episode_map.volume.add_plane(f"{CONFIDENCE_PREFIX}{name}", 0.0, np.float32)
            fov_values.fuse(episode_map.layer(name), confidence, rows, cols, conf, float(v))
    elif not isinstance(val, ValueResult):
        errors.append(f"value prompt failed: {failure(val)}")
    timing["objects_fuse"] = (time.perf_counter() - t0) * 1000.0
    assert episode_map.start.task is not None  # an object map is kept for task episodes only
    return value_layer(frontier_class(episode_map.start.task, objects.holding)), errors


def attach_objects(objects: ObjectMap, episode_map: EpisodeMap, update: MapUpdate, frame: Frame,
                   timing: dict[str, float] | None = None) -> None:
    """Put the instances of ``objects`` (with gaze points on this update's map, for the current phase's
    targets) into ``update``; ``timing``: the step's timings so far, added to the update's."""
    t0 = time.perf_counter()
    height = float(frame.camera_pose[2, 3])
    # the robot's head camera has a fixed tilt: gaze points are scored for the view it really gets there
    pitch = float(np.arcsin(np.clip(frame.camera_pose[2, 2], -1.0, 1.0)))
    task = episode_map.start.task
    targets = object_map_module().phase_classes(task, objects.holding) if task else None
    update.objects = objects.summaries(update.grid, update.occupied, obstacle_heights(episode_map),
                                       camera_height=height, camera_pitch=pitch, targets=targets)
    if timing is not None:
        update.timing_ms.update(timing)
    update.timing_ms["objects_summary"] = (time.perf_counter() - t0) * 1000.0
