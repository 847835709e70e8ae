"""The mapper's object layer of one task episode (HELIOS 3.1.3): detections in, ObjectInstance summaries out.

Glue between the bus messages and the pure torch core (:mod:`services.mapper.objects`): it builds the
frame's :class:`~eqa.messages.DetectRequest` for the task's classes with their per-class thresholds (object
od_g, start receptacle od_a, goal receptacle od_b; Table 3), fuses the :class:`~eqa.messages.DetectResult`,
and summarises every instance as an :class:`~eqa.messages.ObjectInstance` (class, S, U, Psi of Eq. 7 per task
class, centre, extent). Candidate instances (a task class with S >= ``cs_min``, at most ``max_gaze_instances``
of them, best first) also get gaze points (:func:`services.mapper.gaze.gaze_points`) scored with Psi' (Eq. 11)
and the optimistic IG (Eq. 12) of their believed task class. The mapper passes the obstacle height of each
cell, so only obstacles taller than ``gaze_obstacle_m`` occlude, and the gaze points keep the robot's mapped
clearance (:func:`eqa.robot.mapped_clearance_m`) from occupied cells.

A task episode's layer (:meth:`ObjectMap.for_task`) reads it per phase (:func:`phase_classes`): the candidates
that get gaze points are those believed to be a class the current phase looks for -- the object and the start
receptacle before the pick, the goal receptacle after it, the object in an object search -- so instances of a
finished phase do not crowd out the ones searched now. ``ig`` is Eq. 10's ``IG_a``: the information gain of
the whole pose set ``P`` of the local search (all gaze points, Eq. 12), not that of one gaze point. A miss is
evidence only within :attr:`ObjectMapConfig.miss_range_m`. The trusting agent (Table 1: no 3D layer) gets a
single-frame layer: each frame's detections alone, nothing fused over views.

A history of each instance's Psi over the steps is kept for monitoring (bounded).
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from eqa import robot as body
from eqa.messages import DetectRequest, DetectResult, Frame, GazePoint, GridSpec, ObjectInstance, Task
from eqa.recording import EpisodeRecorder
from eqa.settings import SettingsGroup
from services.mapper.gaze import gaze_points
from services.mapper.objects.config import OTHER, ObjectLayerConfig
from services.mapper.objects.layer import ObjectLayer, UpdateStats, camera_from_gaze, pixel_classes

MAX_HISTORY = 200  # Psi samples kept per instance
MAX_TRACKED = 256  # instances with a Psi history


@dataclass(frozen=True)
class ObjectMapConfig:
    layer: ObjectLayerConfig = field(default_factory=ObjectLayerConfig)
    device: str = "cpu"
    od_object: float = 0.25  # od_g
    od_start: float = 0.35  # od_a
    od_goal: float = 0.45  # od_b
    cs_min: float = 0.3  # cs_a / cs_g / cs_b: S for an instance to be a candidate (gets gaze points)
    gaze_radius_m: float = 0.9
    gaze_points: int = 12
    gaze_obstacle_m: float = 1.0
    max_gaze_instances: int = 4
    max_instances: int = 64
    # Task layers: a pixel no detection covers is evidence against the objects behind it only up to this depth.
    # The detector's documented recall (services/vlm_scorer/detector/oracle.py: recall 0.9 x a range factor, 1 up
    # to 2.5 m, linear to 0 at 7 m) is below one half past 2.5 + 4.5 x (1 - 0.5 / 0.9) = 4.5 m: beyond it an
    # object in view is more often missed than detected, so "not detected" there says little about it. DETIC's
    # recall (Zhou et al. 2022) likewise drops for small, far objects. Detections themselves count at any range.
    miss_range_m: float = 4.5

    @classmethod
    def from_settings(cls, s: SettingsGroup) -> ObjectMapConfig:
        """From the HELIOS and object layer settings (:class:`eqa.settings.HeliosSettings`,
        :class:`eqa.settings.ObjectLayerSettings`)."""
        layer = ObjectLayerConfig(
            alpha_cpa=s.helios_alpha_cpa, alpha_cs=s.helios_alpha_cs, render_scale=s.helios_render_scale,
            max_gaussians=s.helios_max_gaussians, max_new_per_frame=s.helios_max_new_per_frame,
            gaze_width=s.helios_gaze_width,
        )
        return cls(
            layer=layer, device=s.helios_device, od_object=s.helios_od_g, od_start=s.helios_od_a,
            od_goal=s.helios_od_b, cs_min=s.helios_cs_g, gaze_radius_m=s.helios_gaze_radius_m,
            gaze_points=s.helios_gaze_points, gaze_obstacle_m=s.helios_gaze_obstacle_m,
            max_instances=s.helios_max_instances,
        )


def task_classes(task: Task, config: ObjectMapConfig) -> tuple[list[str], list[float]]:
    """The detector's vocabulary of a task and its per-class thresholds (od_g, od_a, od_b)."""
    out: dict[str, float] = {}
    for name, th in ((task.object, config.od_object), (task.start_receptacle, config.od_start),
                     (task.goal_receptacle, config.od_goal)):
        if name is not None and name not in out:
            out[name] = th
    return list(out), list(out.values())


class ObjectMap:
    """One episode's object layer with the task's vocabulary (see the module docstring)."""

    def __init__(self, classes: list[str], thresholds: list[float], config: ObjectMapConfig | None = None) -> None:
        if len(thresholds) != len(classes):
            raise ValueError("one threshold per class")
        self.config = config or ObjectMapConfig()
        self.thresholds = list(thresholds)
        self.layer = ObjectLayer(classes, self.config.layer, self.config.device)
        self.history: OrderedDict[int, list[tuple[int, float]]] = OrderedDict()
        self.last_stats: UpdateStats | None = None
        self.single_frame = False  # the layer holds the last frame's detections only (trusting agent)
        self.holding = False  # a task's object was picked: the goal receptacle's phase (phase_classes)

    @classmethod
    def for_task(cls, task: Task, config: ObjectMapConfig | None = None, single_frame: bool = False) -> ObjectMap:
        """A task episode's layer (module doc); ``single_frame``: the trusting agent's (no fusion over views)."""
        config = config or ObjectMapConfig()
        config = replace(config, layer=replace(config.layer, other_max_depth_m=config.miss_range_m))
        classes, th = task_classes(task, config)
        objects = cls(classes, th, config)
        objects.single_frame = single_frame
        return objects

    @property
    def task_classes(self) -> list[str]:
        return self.layer.classes[:-1]

    def detect_request(self, frame: Frame, seed: int = 0, draws: str | None = None) -> DetectRequest:
        return DetectRequest(
            episode_id=frame.episode_id, step=frame.step, rgb=frame.rgb, classes=self.task_classes,
            thresholds=self.thresholds, instances=frame.instances, labels=frame.labels, depth=frame.depth, seed=seed,
            draws=draws,
        )

    def integrate(self, frame: Frame, result: DetectResult, without: frozenset[str] = frozenset()) -> UpdateStats:
        """Fuse one frame with its detections (a frame whose detection failed is not fused: "nothing
        detected" would count as evidence against every object in view). ``without``: classes whose detected
        pixels add nothing (:func:`~services.mapper.objects.layer.pixel_classes`)."""
        h, w = frame.depth.shape
        dets = [(d.cls, d.score, d.full_mask(h, w)) for d in result.detections]
        pc = pixel_classes(dets, self.layer.classes, (h, w), without)
        if self.single_frame:  # instance labels go on counting: a new frame's detection is a new instance
            self.layer.store = type(self.layer.store).empty(len(self.layer.classes), self.layer.device)
        self.last_stats = self.layer.update(frame.depth, pc, frame.camera_pose, frame.intrinsics, frame.step)
        for inst in self.layer.instances():
            if inst.cls == self.layer.other and inst.instance_id not in self.history:
                continue
            hist = self.history.setdefault(inst.instance_id, [])
            hist.append((frame.step, max(inst.psi[:-1])))
            del hist[:-MAX_HISTORY]
            self.history.move_to_end(inst.instance_id)
        while len(self.history) > MAX_TRACKED:
            self.history.popitem(last=False)
        return self.last_stats

    def summaries(
        self, grid: GridSpec | None = None, occupancy: np.ndarray | None = None, heights: np.ndarray | None = None,
        camera_height: float = 1.5, camera_pitch: float | None = None, targets: list[str] | None = None,
    ) -> list[ObjectInstance]:
        """Every instance (up to ``max_instances``, best task-class score first); gaze points for candidates
        when the 2D map is given. ``camera_pitch`` (radians, negative = down): the pitch of a head camera that
        cannot tilt (the simulated robot's is fixed at -30 deg); the gaze points then carry that pitch and Psi'
        (Eq. 11) is computed for the view the robot will really get there, not for the paper's pitch towards
        the object's top (which needs a tilting head). None: the paper's pitch. ``targets``: the classes whose
        candidates get gaze points (the phase's, :func:`phase_classes`; None: every task class). ``ig``: Eq. 12
        over all of an instance's gaze points together (the pose set ``P`` of Eq. 10), 0 without any."""
        c = self.config
        names = self.layer.classes
        insts = sorted(self.layer.instances(), key=lambda i: -max(i.S[:-1]))[: c.max_instances]
        wanted = None if targets is None else {names.index(t) for t in targets if t in names}
        out: list[ObjectInstance] = []
        gazed = 0
        for inst in insts:
            best = int(np.argmax(inst.S[:-1]))  # the believed task class
            gaze: list[GazePoint] = []
            ig = 0.0
            candidate = (inst.S[best] >= c.cs_min and gazed < c.max_gaze_instances and not self.single_frame
                         and (wanted is None or best in wanted))
            if grid is not None and occupancy is not None and candidate:
                gazed += 1
                gaze, ig = self._gaze(inst.instance_id, best, inst.centre, inst.extent, grid, occupancy, heights,
                                      camera_height, camera_pitch)
            out.append(ObjectInstance(
                instance_id=inst.instance_id, cls=names[inst.cls], S=inst.S[inst.cls], U=inst.U[inst.cls],
                psi=inst.psi[inst.cls],
                scores={names[k]: (inst.S[k], inst.U[k], inst.psi[k]) for k in range(len(names) - 1)},
                centre=_finite3(inst.centre), extent=_finite3(inst.extent), n_gaussians=inst.n_gaussians,
                ig=ig, gaze=gaze,
            ))
        return out

    def _gaze(self, instance_id: int, cls: int, centre, extent, grid: GridSpec, occupancy: np.ndarray,
              heights: np.ndarray | None, camera_height: float,
              camera_pitch: float | None = None) -> tuple[list[GazePoint], float]:
        """The gaze points with Psi' and IG of each alone, and the IG of all of them together (Eq. 10, 12)."""
        c = self.config
        cands = gaze_points(occupancy, heights, grid, tuple(centre), tuple(max(e, 0.0) for e in extent),
                            c.gaze_radius_m, c.gaze_points, c.gaze_obstacle_m, camera_height,
                            clearance_m=body.mapped_clearance_m())
        if camera_pitch is not None:
            cands = [replace(g, pitch=round(float(camera_pitch), 6)) for g in cands]
        if not cands:
            return [], 0.0
        poses = [camera_from_gaze(g.x, g.y, g.yaw, g.pitch, camera_height) for g in cands]
        opts = self.layer.optimistic_each(instance_id, cls, poses)  # each gaze point alone, one render
        ig_set = float(self.layer.optimistic(instance_id, cls, poses).ig)
        return [GazePoint(x=g.x, y=g.y, yaw=g.yaw, pitch=g.pitch, psi_prime=o.psi_prime, ig=o.ig)
                for g, o in zip(cands, opts, strict=True)], ig_set

    # ---- a home's layer (services.mapper.home_objects) ---------------------------------------------------
    def load_home(self, uid: np.ndarray, means: np.ndarray, sigma: np.ndarray, opacity: np.ndarray,
                  gamma: np.ndarray) -> None:
        """Start from a home's Gaussians (``gamma``: their concentrations over this layer's classes, by
        :meth:`services.mapper.home_objects.HomeObjects.gamma_for`), clustered into instances; they count as
        last updated before the episode's first step (the bound drops them before the episode's own)."""
        import torch

        from services.mapper.objects.gaussians import GaussianStore

        n = len(uid)
        if gamma.shape != (n, len(self.layer.classes)):
            raise ValueError(f"home layer concentrations {gamma.shape} for {n} Gaussians and {self.layer.classes}")
        dev = self.layer.device
        self.layer.store = GaussianStore(
            torch.as_tensor(np.array(means, np.float32)).reshape(n, 3).to(dev),
            torch.as_tensor(np.array(sigma, np.float32)).to(dev),
            torch.as_tensor(np.array(opacity, np.float32)).to(dev),
            torch.as_tensor(np.array(gamma, np.float32)).to(dev),
            torch.full((n,), -1, dtype=torch.long, device=dev),
            torch.full((n,), -1, dtype=torch.long, device=dev),
            torch.as_tensor(np.array(uid, np.int64)).to(dev),
        )
        self.layer.store.enforce_bound(self.layer.config.max_gaussians)
        self.layer.recluster(torch.ones(len(self.layer.store), dtype=torch.bool, device=dev))

    def home_arrays(self) -> dict[str, np.ndarray]:
        """The layer's Gaussians for the home's commit: ``uid`` (-1: made in this episode), ``means``,
        ``sigma``, ``opacity``, ``gamma`` (over :attr:`task_classes` then ``other``)."""
        st = self.layer.store.to_numpy()
        return {k: st[k] for k in ("uid", "means", "sigma", "opacity", "gamma")}

    # ---- persistence ------------------------------------------------------------------------------------
    def snapshot(self) -> bytes:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
            z.writestr("layer.npz", self.layer.snapshot())
            z.writestr("meta.json", json.dumps({
                "thresholds": self.thresholds,
                "history": [[k, v] for k, v in self.history.items()],
                **({"single_frame": True} if self.single_frame else {}),
                **({"holding": True} if self.holding else {}),
                **({"miss_range_m": m} if (m := self.layer.config.other_max_depth_m) is not None else {}),
            }))
        return buf.getvalue()

    @classmethod
    def restore(cls, data: bytes, config: ObjectMapConfig | None = None) -> ObjectMap:
        config = config or ObjectMapConfig()
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            layer = ObjectLayer.restore(z.read("layer.npz"), config.layer, config.device)
            meta = json.loads(z.read("meta.json"))
        if meta.get("miss_range_m") is not None:  # a task layer (for_task)
            config = replace(config, layer=replace(config.layer, other_max_depth_m=float(meta["miss_range_m"])))
            layer.config = config.layer
        objects = cls(layer.classes[:-1], meta["thresholds"], config)
        objects.layer = layer
        objects.history = OrderedDict((int(k), [(int(s), float(p)) for s, p in v]) for k, v in meta["history"])
        objects.single_frame = bool(meta.get("single_frame", False))
        objects.holding = bool(meta.get("holding", False))
        return objects


def phase_classes(task: Task, holding: bool) -> list[str]:
    """The classes a task's current phase looks for (module doc): ``find_object`` the object; ``pick_place``
    the object and the start receptacle until the object is held, then the goal receptacle."""
    if task.kind == "find_object" or task.goal_receptacle is None:
        return [task.object]
    if holding:
        return [task.goal_receptacle]
    return [c for c in (task.object, task.start_receptacle) if c is not None]


def _finite3(v) -> tuple[float, float, float]:
    a = [float(x) if math.isfinite(float(x)) else 0.0 for x in v]
    return (a[0], a[1], a[2])


__all__ = ["OTHER", "ObjectMap", "ObjectMapConfig", "phase_classes", "task_classes"]


# ---- monitoring ----------------------------------------------------------------------------------------------
PALETTE = np.array(
    [[230, 60, 60], [60, 120, 230], [60, 190, 90], [240, 180, 40], [170, 80, 200], [40, 200, 200]], np.uint8
)
OTHER_RGB = np.array([150, 150, 150], np.uint8)
MAX_LOGGED_GAUSSIANS = 20_000
GAUSSIANS_ENTITY = "world/objects/gaussians"  # rr.Ellipsoids3D: colour = most likely class, alpha = certainty
INSTANCES_ENTITY = "world/objects/instances"  # rr.Boxes3D per instance, labelled class and Psi
PSI_ENTITY = "objects/psi"  # rr.Scalars per instance, objects/psi/<instance id>: Psi of its best task class


def class_colours(n_task_classes: int) -> np.ndarray:
    """RGB per class: a palette colour per task class, grey for ``other``."""
    return np.vstack([PALETTE[np.arange(n_task_classes) % len(PALETTE)], OTHER_RGB[None]])


def log_rerun(recorder: EpisodeRecorder, objects_map: ObjectMap, objects: list[ObjectInstance]) -> None:
    """Log the layer into an :class:`eqa.recording.EpisodeRecorder` (its step already set): the Gaussians as
    ellipsoids (1-sigma, coloured by most likely class, opacity = certainty 1 - 2 sqrt(Var) of that class,
    at most ``MAX_LOGGED_GAUSSIANS``), each instance's box with its class and Psi, and each instance's Psi."""
    import rerun as rr
    import torch

    from services.mapper.objects import dirichlet

    st = objects_map.layer.store
    n = len(st)
    idx = torch.arange(n) if n <= MAX_LOGGED_GAUSSIANS else torch.linspace(0, n - 1, MAX_LOGGED_GAUSSIANS).long()
    gamma = st.gamma[idx].cpu()
    e = dirichlet.expectation(gamma)
    cls = e.argmax(1)
    sd = dirichlet.variance(gamma).sqrt().gather(1, cls[:, None])[:, 0]
    alpha = (255 * (1.0 - 2.0 * sd).clamp(0.05, 1.0)).to(torch.uint8).numpy()
    rgb = class_colours(len(objects_map.task_classes))[cls.numpy()]
    colours = np.concatenate([rgb, alpha[:, None]], axis=1)
    sigma = st.sigma[idx].cpu().numpy()
    recorder.log(GAUSSIANS_ENTITY, rr.Ellipsoids3D(  # type: ignore[attr-defined]
        centers=st.means[idx].cpu().numpy(), half_sizes=np.repeat(sigma[:, None], 3, axis=1), colors=colours,
        fill_mode="solid",
    ))
    if objects:
        recorder.log(INSTANCES_ENTITY, rr.Boxes3D(  # type: ignore[attr-defined]
            centers=[o.centre for o in objects], sizes=[o.extent for o in objects],
            labels=[f"{o.instance_id} {o.cls} psi {o.psi:.2f}" for o in objects],
        ))
    for o in objects:
        best = max(o.scores.values(), key=lambda s: s[0], default=(o.S, o.U, o.psi))
        recorder.log(f"{PSI_ENTITY}/{o.instance_id}", rr.Scalars(best[2]))  # type: ignore[attr-defined]
