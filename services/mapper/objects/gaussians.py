"""The Gaussian store of the object layer and Gaussian creation (HELIOS appendix 6.1, "Gaussian creation").

A Gaussian holds a mean (world, m), an isotropic sigma (m), an opacity, its Dirichlet concentrations over the
episode's classes, its instance label (-1 before clustering) and the step it last got evidence. Nothing is
trained: means come from the measured depth and the camera pose, sigma from the spawn block's footprint.

Creation: inside the pixels detected as a task class (each class mask eroded by ``erosion_px`` first, so the
bleeding edges of a detector's masks make no Gaussians), with a measured depth > 0, take the depth error
|measured - rendered| against the layer's own rendered depth; where the layer renders nothing, an error above
``new_empty_error_m`` (0.001 m: any measured surface) is new; where it renders something, an error above
``new_depth_error_m`` (1 m) is. One Gaussian is made per ``spawn_stride_px`` block of such pixels (the
paper makes one per pixel; blocks keep the count proportional to the object's image area / stride^2).

The bound (a client-controlled count: the scene and the detector decide how much is detected): at most
``max_new_per_frame`` creations per frame (the nearest kept first: near views are the better ones) and at
most ``max_gaussians`` in the store; past that the Gaussians that got evidence longest ago are dropped first
(ties: the least total evidence first). Dropping is logged by the caller with the count.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import torch

from services.mapper.objects.reobserve import bbox, erode


@dataclass
class GaussianStore:
    means: torch.Tensor  # (N, 3) float32 world
    sigma: torch.Tensor  # (N,) float32 m
    opacity: torch.Tensor  # (N,) float32
    gamma: torch.Tensor  # (N, C) float32 concentrations
    instance: torch.Tensor  # (N,) int64, -1 = none yet
    last_step: torch.Tensor  # (N,) int64 step of the last evidence
    # (N,) int64 id in the episode's home (services.mapper.home_objects), -1 for one made in this episode
    uid: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))

    def __post_init__(self) -> None:
        if self.uid.shape[0] != self.means.shape[0]:  # made without home ids: none has one
            self.uid = torch.full((self.means.shape[0],), -1, dtype=torch.long, device=self.means.device)

    @classmethod
    def empty(cls, n_classes: int, device: torch.device | str = "cpu") -> GaussianStore:
        dev = torch.device(device)
        return cls(
            torch.zeros(0, 3, device=dev),
            torch.zeros(0, device=dev),
            torch.zeros(0, device=dev),
            torch.zeros(0, n_classes, device=dev),
            torch.zeros(0, dtype=torch.long, device=dev),
            torch.zeros(0, dtype=torch.long, device=dev),
        )

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        return self.means.device

    def append(self, other: GaussianStore) -> None:
        for f in fields(self):
            setattr(self, f.name, torch.cat([getattr(self, f.name), getattr(other, f.name)]))

    def select(self, keep: torch.Tensor) -> None:
        """Keep the Gaussians at index/boolean ``keep`` (in place)."""
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name)[keep])

    def nbytes(self) -> int:
        return sum(int(getattr(self, f.name).element_size() * getattr(self, f.name).numel()) for f in fields(self))

    def enforce_bound(self, max_gaussians: int) -> int:
        """Drop Gaussians past ``max_gaussians``: oldest evidence first, then least evidence. Returns how many."""
        n = len(self)
        if n <= max_gaussians:
            return 0
        evidence = self.gamma.sum(1).double()
        # lexicographic (last_step desc, evidence desc): keep the first max_gaussians
        key = self.last_step.double() * (evidence.max() + 1.0) + evidence
        keep = torch.argsort(key, descending=True)[:max_gaussians]
        self.select(torch.sort(keep).values)
        return n - max_gaussians

    def to_numpy(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name).cpu().numpy() for f in fields(self)}

    @classmethod
    def from_numpy(cls, data: dict[str, Any], device: torch.device | str = "cpu") -> GaussianStore:
        return cls(**{f.name: torch.as_tensor(np.asarray(data[f.name])).to(device) for f in fields(cls)
                      if f.name in data})


def spawn_pixels(
    pixel_class: torch.Tensor,
    measured: torch.Tensor,
    rendered: torch.Tensor,
    other: int,
    stride: int,
    erosion_px: int,
    new_depth_error_m: float,
    new_empty_error_m: float,
    max_depth_m: float,
) -> torch.Tensor:
    """(K, 2) int64 (row, col) of the pixels that make new Gaussians (see the module docstring)."""
    h, w = pixel_class.shape
    new = torch.zeros(h, w, dtype=torch.bool, device=pixel_class.device)
    y0, y1, x0, x1 = bbox(pixel_class != other, erosion_px + 1)  # erode only around the detections
    crop = pixel_class[y0:y1, x0:x1]
    for c in range(other):
        m = crop == c
        if bool(m.any()):
            new[y0:y1, x0:x1] |= erode(m, erosion_px)
    err = (measured - rendered).abs()
    new &= (measured > 0) & (measured <= max_depth_m)
    new &= torch.where(rendered > 0, err > new_depth_error_m, err > new_empty_error_m)
    # one pixel per stride block: the block's first new pixel in raster order, at the block grid
    grid = torch.zeros_like(new)
    off = stride // 2
    grid[off::stride, off::stride] = True
    return torch.nonzero(new & grid)


def create(
    rows_cols: torch.Tensor,
    pixel_class: torch.Tensor,
    measured: torch.Tensor,
    camera_pose: torch.Tensor,
    K: torch.Tensor,
    n_classes: int,
    prior: float,
    opacity: float,
    stride: int,
    scale_factor: float,
    step: int,
    max_new: int,
) -> GaussianStore:
    """New Gaussians at the pixels ``rows_cols``: means back-projected from the measured depth with the camera
    pose, sigma = ``scale_factor`` x the metric size of a ``stride``-pixel block at that depth, concentrations
    at ``prior`` (the frame's own evidence comes from the Eq. 3 update that follows). The nearest ``max_new``
    are kept."""
    dev = measured.device
    if rows_cols.numel() == 0 or max_new <= 0:
        return GaussianStore.empty(n_classes, dev)
    r, c = rows_cols[:, 0], rows_cols[:, 1]
    d = measured[r, c].float()
    if d.numel() > max_new:
        near = torch.argsort(d)[:max_new]
        r, c, d = r[near], c[near], d[near]
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    xc = torch.stack([(c.float() - cx) / fx * d, (r.float() - cy) / fy * d, d], 1)
    T = camera_pose.to(dev, torch.float32)
    means = xc @ T[:3, :3].T + T[:3, 3]
    sigma = scale_factor * stride * d / (0.5 * (fx + fy))
    n = means.shape[0]
    return GaussianStore(
        means,
        sigma,
        torch.full((n,), float(opacity), device=dev),
        torch.full((n, n_classes), float(prior), device=dev),
        torch.full((n,), -1, dtype=torch.long, device=dev),
        torch.full((n,), int(step), dtype=torch.long, device=dev),
    )
