"""One episode's object layer: a frame's update in the paper's order, summaries, optimistic views, snapshot.

Per frame (:meth:`ObjectLayer.update`), at ``render_scale`` of the frame's resolution:

1. render the layer's depth (Eq. 1) and create Gaussians where detected task-class pixels show a depth
   error (appendix "Gaussian creation", :mod:`.gaussians`);
2. render again (the new Gaussians included), take the re-observation mask (:mod:`.reobserve`) and update
   the concentrations of every Gaussian seen through it with Eq. 3, the class of each pixel being the
   detection covering it or ``other``;
3. drop Gaussians past the bound (:meth:`.gaussians.GaussianStore.enforce_bound`);
4. re-cluster the updated Gaussians and their instances (:mod:`.instances`).

Classes: the task classes given at the start of the episode, then ``other``.
"""

from __future__ import annotations

import io
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from eqa import npy
from services.mapper.objects import dirichlet, splat
from services.mapper.objects.config import OTHER, ObjectLayerConfig
from services.mapper.objects.gaussians import GaussianStore, create, spawn_pixels
from services.mapper.objects.info_gain import Optimistic, optimistic_each, optimistic_views
from services.mapper.objects.instances import relabel
from services.mapper.objects.reobserve import reobservation_mask
from services.mapper.objects.scores import InstanceScores, summarise

log = logging.getLogger(__name__)

SNAPSHOT_FORMAT = 1
MAX_CLASSES = 32
NO_EVIDENCE = -1  # a pixel_class entry whose pixel neither creates Gaussians nor updates any (Eq. 3 skips it)


@dataclass
class UpdateStats:
    step: int
    created: int = 0
    dropped: int = 0
    touched: int = 0
    gaussians: int = 0
    instances: int = 0
    timing_ms: dict[str, float] = field(default_factory=dict)


def scale_intrinsics(K: np.ndarray | torch.Tensor, s: float) -> torch.Tensor:
    """Intrinsics of the same camera at ``s`` times the resolution (pixel centres at integers)."""
    k = torch.as_tensor(np.array(K, dtype=np.float64))
    k[0, 0] *= s
    k[1, 1] *= s
    k[0, 2] = (k[0, 2] + 0.5) * s - 0.5
    k[1, 2] = (k[1, 2] + 0.5) * s - 0.5
    return k


def sample_grid(big_h: int, big_w: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of a nearest-pixel downsampling of (H, W) to (h, w): each output pixel takes the
    input pixel at its centre."""
    rows = np.minimum(((np.arange(h) + 0.5) * big_h / h).astype(np.int64), big_h - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * big_w / w).astype(np.int64), big_w - 1)
    return rows, cols


def pixel_classes(
    detections: list[tuple[str, float, np.ndarray]], classes: list[str], shape: tuple[int, int],
    without: frozenset[str] = frozenset(),
) -> np.ndarray:
    """The class index y_i of each pixel (Eq. 3's one-hot y) from detections ``(class, score, full mask)``:
    the highest-scoring detection covering a pixel names it; ``other`` (the last class) where none does.
    Detections of classes not in ``classes`` are ignored. Pixels a class of ``without`` names get
    :data:`NO_EVIDENCE` (they add nothing: a remembered view re-detected for new classes, whose pixels of a
    class asked before are already counted in the home's layer)."""
    other = len(classes) - 1
    out = np.full(shape, other, dtype=np.int64)
    best = np.zeros(shape, dtype=np.float64)
    for name, score, mask in detections:
        if name not in classes[:-1]:
            continue
        sel = np.asarray(mask, dtype=bool) & (score > best)
        out[sel] = NO_EVIDENCE if name in without else classes.index(name)
        best[sel] = score
    return out


def camera_from_gaze(x: float, y: float, yaw: float, pitch: float, height: float) -> torch.Tensor:
    """4x4 camera-to-world pose (OpenCV) of a camera at (x, y, height) looking along ``yaw`` pitched by
    ``pitch`` (radians, negative = down), as the simulator's head camera."""
    c, s = math.cos(yaw), math.sin(yaw)
    ct, st = math.cos(pitch), math.sin(pitch)
    forward = np.array([c * ct, s * ct, st])
    right = np.array([s, -c, 0.0])
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, forward, (x, y, height)
    return torch.as_tensor(T, dtype=torch.float32)


class ObjectLayer:
    """The sparse 3D Gaussian object layer of one episode (see the module docstring)."""

    def __init__(
        self, classes: list[str], config: ObjectLayerConfig | None = None, device: str | torch.device = "cpu"
    ) -> None:
        names = [c.strip() for c in classes]
        if not names or len(names) > MAX_CLASSES:
            raise ValueError(f"give 1..{MAX_CLASSES} task classes, got {len(names)}")
        if any(not c for c in names) or len(set(names)) != len(names) or OTHER in names:
            raise ValueError(f"task classes must be distinct, non-empty and not {OTHER!r}: {names}")
        self.config = config or ObjectLayerConfig()
        self.classes = [*names, OTHER]
        self.device = torch.device(device)
        self.store = GaussianStore.empty(len(self.classes), self.device)
        self.next_label = 0
        self.step = -1
        self.last_camera: tuple[np.ndarray, np.ndarray, int, int] | None = None  # pose, K, H, W

    @property
    def other(self) -> int:
        return len(self.classes) - 1

    def class_index(self, name: str) -> int:
        try:
            return self.classes.index(name)
        except ValueError:
            raise ValueError(f"{name!r} is not one of this layer's classes {self.classes}") from None

    # ---- the update -------------------------------------------------------------------------------------
    def _render(self, pose: torch.Tensor, K: torch.Tensor, h: int, w: int) -> splat.Splats:
        c = self.config
        st = self.store
        return splat.render(
            st.means, st.sigma, st.opacity, pose, K, h, w,
            max_radius_px=c.max_splat_radius_px, min_alpha=c.min_alpha, max_alpha=c.max_alpha,
            min_transmittance=c.min_transmittance, valid_acc=c.valid_acc,
        )

    def update(
        self, depth: np.ndarray, pixel_class: np.ndarray, camera_pose: np.ndarray, K: np.ndarray, step: int
    ) -> UpdateStats:
        """Fuse one frame: ``depth`` (H, W) metres (0/inf = none), ``pixel_class`` (H, W) class index per pixel
        (``other`` where no detection, :data:`NO_EVIDENCE` where the pixel adds nothing), camera-to-world
        ``camera_pose``, intrinsics ``K``."""
        c = self.config
        t0 = time.perf_counter()
        timing: dict[str, float] = {}

        def lap(name: str) -> None:
            nonlocal t0
            now = time.perf_counter()
            timing[name] = (now - t0) * 1000.0
            t0 = now

        big_h, big_w = depth.shape
        if pixel_class.shape != depth.shape:
            raise ValueError(f"pixel_class {pixel_class.shape} and depth {depth.shape} differ")
        h, w = max(1, round(big_h * c.render_scale)), max(1, round(big_w * c.render_scale))
        rows, cols = sample_grid(big_h, big_w, h, w)  # nearest-pixel downsampling before any conversion
        small = np.asarray(depth)[np.ix_(rows, cols)].astype(np.float32)
        d = torch.as_tensor(np.nan_to_num(small, nan=0.0, posinf=0.0, neginf=0.0)).to(self.device)
        d = torch.where((d > 0) & (d <= c.max_depth_m), d, torch.zeros_like(d))
        pc = torch.as_tensor(np.asarray(pixel_class)[np.ix_(rows, cols)].astype(np.int64)).to(self.device)
        if int(pc.min()) < NO_EVIDENCE or int(pc.max()) > self.other:
            raise ValueError(f"pixel_class must hold class indices 0..{self.other} or {NO_EVIDENCE}")
        Ks = scale_intrinsics(K, h / big_h)
        pose = torch.as_tensor(np.array(camera_pose, np.float64), dtype=torch.float32, device=self.device)
        self.last_camera = (np.asarray(camera_pose, np.float64), np.asarray(K, np.float64), big_h, big_w)
        self.step = step
        lap("prepare")
        # 1. creation from the depth error inside the (eroded) detection masks
        first = self._render(pose, Ks, h, w)
        px = spawn_pixels(
            pc, d, first.depth, self.other, c.spawn_stride_px, c.erosion_px,
            c.new_depth_error_m, c.new_empty_error_m, c.max_depth_m,
        )
        new = create(
            px, pc, d, pose, Ks, len(self.classes), c.prior, c.init_opacity, c.spawn_stride_px,
            c.scale_factor, step, c.max_new_per_frame,
        )
        self.store.append(new)
        lap("create")
        # 2. re-observation mask and the Dirichlet update (Eq. 3)
        r = self._render(pose, Ks, h, w) if len(new) else first  # nothing new: the first render is the same
        mask = reobservation_mask(d, r.depth, c.reobserve_depth_m, c.close_px)
        if c.other_max_depth_m is not None:  # a miss beyond the detector's range says nothing
            mask = mask & ~((pc == self.other) & (d > c.other_max_depth_m))
        mask = (mask & (pc >= 0)).reshape(-1)
        sel = mask[r.pixel]
        g, k, y = r.gauss[sel], r.kappa[sel], pc.reshape(-1)[r.pixel[sel]]
        self.store.gamma = dirichlet.update(self.store.gamma, g, k, y, c.alpha_cpa, c.pixel_weight)
        evidence = torch.zeros(len(self.store), device=self.device).index_add_(0, g, k * c.pixel_weight)
        touched = evidence >= c.touched_evidence
        self.store.last_step[touched] = step
        lap("update")
        # 3. the bound
        dropped = self.store.enforce_bound(c.max_gaussians)
        if dropped:
            log.info("object layer: dropped %d Gaussians past the bound of %d", dropped, c.max_gaussians)
        # 4. instances over the touched Gaussians and their instances
        self.recluster(self.store.last_step == step)
        lap("instances")
        return UpdateStats(
            step, created=len(new), dropped=dropped, touched=int(touched.sum()), gaussians=len(self.store),
            instances=int(torch.unique(self.store.instance[self.store.instance >= 0]).numel()), timing_ms=timing,
        )

    def recluster(self, touched: torch.Tensor) -> None:
        """Re-cluster the Gaussians ``touched`` (bool) and every Gaussian of their instances (:mod:`.instances`)."""
        inst = self.store.instance
        if not bool(touched.any()):
            return
        labels = torch.unique(inst[touched & (inst >= 0)])
        subset = touched | torch.isin(inst, labels)
        idx = torch.nonzero(subset).squeeze(1).cpu().numpy()
        cls = dirichlet.expectation(self.store.gamma).argmax(1).cpu().numpy()
        new, self.next_label = relabel(
            self.store.means.cpu().numpy(), cls, inst.cpu().numpy(), idx, self.next_label, self.config.voxel_m
        )
        inst[torch.as_tensor(idx, device=self.device)] = torch.as_tensor(new, device=self.device)

    # ---- reading it -------------------------------------------------------------------------------------
    def instances(self) -> list[InstanceScores]:
        st = self.store
        return summarise(st.means, st.sigma, st.gamma, st.instance, self.config.alpha_cs)

    def members(self, instance_id: int) -> torch.Tensor:
        return torch.nonzero(self.store.instance == instance_id).squeeze(1)

    def _gaze_camera(self, width: int | None) -> tuple[torch.Tensor, int, int, float]:
        """The last frame's camera model at ``width`` (default ``gaze_width``) pixels across: intrinsics, height,
        width, and Eq. 3's pixel weight at that resolution."""
        if self.last_camera is None:
            raise RuntimeError("the layer has seen no frame yet")
        _, K, big_h, big_w = self.last_camera
        w = int(width or self.config.gaze_width)
        s = w / big_w
        h = max(1, round(big_h * s))
        update_scale = round(big_w * self.config.render_scale) / big_w
        weight = self.config.pixel_weight * (update_scale / s) ** 2
        return scale_intrinsics(K, s), h, w, weight

    def optimistic(
        self, instance_id: int, cls: int, poses: list[torch.Tensor], width: int | None = None
    ) -> Optimistic:
        """Eq. 11/12 for ``instance_id`` seen as class ``cls`` from the camera poses ``poses``, rendered with
        the last frame's camera model at ``width`` (default ``gaze_width``) pixels across."""
        K, h, w, weight = self._gaze_camera(width)
        st = self.store
        return optimistic_views(
            st.means, st.sigma, st.opacity, st.gamma, self.members(instance_id), cls,
            [p.to(self.device) for p in poses], K, h, w, self.config, weight,
        )

    def optimistic_each(
        self, instance_id: int, cls: int, poses: list[torch.Tensor], width: int | None = None
    ) -> list[Optimistic]:
        """:meth:`optimistic` of each pose alone (one gaze point each), in one vectorised render."""
        K, h, w, weight = self._gaze_camera(width)
        st = self.store
        return optimistic_each(
            st.means, st.sigma, st.opacity, st.gamma, self.members(instance_id), cls,
            [p.to(self.device) for p in poses], K, h, w, self.config, weight,
        )

    def nbytes(self) -> int:
        return self.store.nbytes()

    # ---- persistence ------------------------------------------------------------------------------------
    def snapshot(self) -> bytes:
        """The whole layer as bytes (an uncompressed ``.npz``), for the mapper's store snapshot (saved every
        step: zlib cost ~50 ms per 8 000 Gaussians for a third less bytes; measured)."""
        buf = io.BytesIO()
        extra: dict[str, Any] = {}
        if self.last_camera is not None:
            pose, K, hh, ww = self.last_camera
            extra = {"cam_pose": pose, "cam_K": K, "cam_hw": np.array([hh, ww], np.int64)}
        np.savez(
            buf,
            format=np.array(SNAPSHOT_FORMAT),
            classes=np.array(self.classes),
            meta=np.array([self.next_label, self.step], np.int64),
            # home ids only when the layer has some (a task in a home): an episode without one stores what it did
            **{f"g_{k}": v for k, v in self.store.to_numpy().items() if k != "uid" or (v >= 0).any()},
            **extra,
        )
        return buf.getvalue()

    @classmethod
    def restore(
        cls, data: bytes, config: ObjectLayerConfig | None = None, device: str | torch.device = "cpu"
    ) -> ObjectLayer:
        z = npy.load_npz(data)
        if int(z["format"]) != SNAPSHOT_FORMAT:
            raise ValueError(f"object layer snapshot format {int(z['format'])}, expected {SNAPSHOT_FORMAT}")
        classes = [str(c) for c in z["classes"].tolist()]
        layer = cls(classes[:-1], config, device)
        layer.next_label, layer.step = (int(v) for v in z["meta"])
        layer.store = GaussianStore.from_numpy(
            {k[2:]: z[k] for k in z if k.startswith("g_")}, layer.device
        )
        if "cam_pose" in z:
            hh, ww = (int(v) for v in z["cam_hw"])
            layer.last_camera = (z["cam_pose"], z["cam_K"], hh, ww)
        return layer
