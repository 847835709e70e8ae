"""Prompt points for visual prompting (Explore-EQA section IV-C).

"We first identify the free space seen in I_c^t by (a) projecting it onto M, (b) keeping only the free
points, and (c) sampling a set of points P using farthest point sampling ... |P| = 3 ... Then, we
de-project the sampled points back onto I_c^t and annotate them with letters A, B, C."

Candidates are cells of the reachable free map whose floor point (cell centre at z = 0) projects inside the
image and is not hidden behind a closer surface (its camera depth is at most the depth image there plus a
tolerance), at a horizontal distance of 2 to 10 m from the camera. Farthest-point sampling starts at the
candidate farthest from the camera and stops early when the next point would be closer than 1 m to one
already chosen (the points are merged).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eqa import grid
from eqa.messages import LETTERS, PromptPoint


@dataclass(frozen=True)
class PromptConfig:
    count: int = 3
    min_dist: float = 2.0
    max_dist: float = 10.0
    merge_dist: float = 1.0
    visibility_tol: float = 0.3  # metres a floor point may lie behind the measured depth


def visible_free_points(
    free: np.ndarray,
    origin: tuple[float, float],
    resolution: float,
    depth: np.ndarray,
    intrinsics: np.ndarray,
    cam_pose: np.ndarray,
    config: PromptConfig | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """World (x, y) of the free cells seen in this image and their pixel (u, v), both (n, 2)."""
    config = config or PromptConfig()
    h, w = depth.shape
    rr, cc = np.nonzero(free)
    xs, ys = grid.cell_center(rr, cc, origin, resolution)
    t = cam_pose[:3, 3]
    dist = np.hypot(xs - t[0], ys - t[1])
    near = (dist >= config.min_dist) & (dist <= config.max_dist)
    xs, ys = xs[near], ys[near]
    pw = np.stack([xs - t[0], ys - t[1], np.full_like(xs, -t[2])], axis=1)
    pc = pw @ cam_pose[:3, :3]  # R^T (p - t)
    z = pc[:, 2]
    front = z > 0.1
    zs = np.where(front, z, 1.0)
    u = intrinsics[0, 0] * pc[:, 0] / zs + intrinsics[0, 2]
    v = intrinsics[1, 1] * pc[:, 1] / zs + intrinsics[1, 2]
    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    inside = front & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    d = np.zeros_like(z)
    d[inside] = depth[vi[inside], ui[inside]]
    seen = inside & np.isfinite(d) & (d > 0) & (z <= d + config.visibility_tol)
    return np.stack([xs[seen], ys[seen]], axis=1), np.stack([u[seen], v[seen]], axis=1)


def farthest_point_sampling(points: np.ndarray, start: int, count: int, merge_dist: float) -> list[int]:
    """Indices of up to ``count`` points by farthest-point sampling from ``start``; stops when the farthest
    remaining point is closer than ``merge_dist`` to the chosen set."""
    if len(points) == 0:
        return []
    chosen = [start]
    dmin = np.linalg.norm(points - points[start], axis=1)
    while len(chosen) < count:
        k = int(np.argmax(dmin))
        if dmin[k] < merge_dist:
            break
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(points - points[k], axis=1))
    return chosen


def prompt_points(
    free: np.ndarray,
    origin: tuple[float, float],
    resolution: float,
    depth: np.ndarray,
    intrinsics: np.ndarray,
    cam_pose: np.ndarray,
    config: PromptConfig | None = None,
) -> list[PromptPoint]:
    """The labelled prompt points ``A``, ``B``, ``C`` of one frame (fewer when the free view is small)."""
    config = config or PromptConfig()
    xy, uv = visible_free_points(free, origin, resolution, depth, intrinsics, cam_pose, config)
    if len(xy) == 0:
        return []
    t = cam_pose[:3, 3]
    start = int(np.argmax(np.hypot(xy[:, 0] - t[0], xy[:, 1] - t[1])))
    idx = farthest_point_sampling(xy, start, config.count, config.merge_dist)
    return [
        PromptPoint(
            label=LETTERS[i], x=float(xy[k, 0]), y=float(xy[k, 1]), u=float(uv[k, 0]), v=float(uv[k, 1])
        )
        for i, k in enumerate(idx)
    ]
