"""Robot motion in a scene: which base poses are valid, and sampling start poses.

A pose is valid when it is finite, on the floor of the scene, and the robot's disc (radius
``clearance``) touches no wall or furniture below camera height, judged on the scene's ground-truth
navigable grid (:meth:`services.sim.scene.Scene.navigable_grid`). The sim teleports the robot to a valid
goal pose (the planner plans the path on its own map).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from eqa.grid import cell_of_point
from eqa.messages import Pose2D
from services.sim.scene import Scene

GRID_RES = 0.05
ROBOT_RADIUS = 0.2  # m, the collision radius of a goal pose
START_CLEARANCE = 0.5  # m, free space around a sampled start pose


def _disk(radius: float, res: float) -> np.ndarray:
    r = math.ceil(radius / res)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return (xx**2 + yy**2) * res**2 <= radius**2 + 1e-9


def clearance_map(scene: Scene, clearance: float, res: float = GRID_RES) -> tuple[np.ndarray, float, float]:
    """Cells where a disc of radius ``clearance`` centred there is all navigable floor."""
    key = ("clearance", float(clearance), float(res))
    if key in scene.cache:
        return scene.cache[key]  # type: ignore[return-value]
    grid, ox, oy = scene.navigable_grid(res)
    if clearance <= 0:
        return grid, ox, oy
    # distance (in cells) from each free cell centre to the nearest blocked cell centre
    dist = ndimage.distance_transform_edt(np.pad(grid, 1))[1:-1, 1:-1]
    out = (dist * res > clearance, ox, oy)
    scene.cache[key] = out
    return out


def pose_error(scene: Scene, pose: Pose2D | tuple[float, float, float], clearance: float = ROBOT_RADIUS) -> str | None:
    """``None`` if the robot may stand at ``pose``, else the reason (non-finite, off the floor, in collision)."""
    if isinstance(pose, Pose2D):
        x, y, yaw = pose.x, pose.y, pose.yaw
    else:
        try:
            x, y, yaw = (float(v) for v in pose)
        except (TypeError, ValueError):
            return f"pose {pose!r} is not three numbers x, y, yaw"
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        return f"pose ({x}, {y}, {yaw}) has a non-finite value"
    floor, ox, oy = scene.navigable_grid(GRID_RES, obstacles=False)
    i, j = cell_of_point(x, y, (ox, oy), GRID_RES)
    if not (0 <= i < floor.shape[0] and 0 <= j < floor.shape[1]) or not floor[i, j]:
        return f"pose ({x:.2f}, {y:.2f}) is off the floor of scene {scene.id}"
    free, _, _ = scene.navigable_grid(GRID_RES)
    r = math.ceil(clearance / GRID_RES)
    i0, i1, j0, j1 = i - r, i + r + 1, j - r, j + r + 1
    disk = _disk(clearance, GRID_RES)
    if i0 < 0 or j0 < 0 or i1 > free.shape[0] or j1 > free.shape[1]:
        return f"pose ({x:.2f}, {y:.2f}) is in collision with a wall (robot radius {clearance:.2f} m)"
    if not free[i0:i1, j0:j1][disk].all():
        return f"pose ({x:.2f}, {y:.2f}) is in collision with a wall or furniture (robot radius {clearance:.2f} m)"
    return None


def reachable_map(scene: Scene, start: Pose2D | None = None, clearance: float = ROBOT_RADIUS,
                  res: float = GRID_RES) -> tuple[np.ndarray, float, float]:
    """Cells the robot (radius ``clearance``) can reach from ``start``, or the largest connected region."""
    key = ("labels", float(clearance), float(res))
    if key not in scene.cache:
        ok, ox, oy = clearance_map(scene, clearance, res)
        scene.cache[key] = (ok, *ndimage.label(ok), ox, oy)
    ok, labels, n, ox, oy = scene.cache[key]  # type: ignore[misc]
    if n == 0:
        return ok, ox, oy
    if start is not None:
        i, j = int((start.y - oy) // res), int((start.x - ox) // res)
        if 0 <= i < ok.shape[0] and 0 <= j < ok.shape[1] and labels[i, j] > 0:
            return labels == labels[i, j], ox, oy
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(sizes.argmax()), ox, oy


def sample_start_pose(scene: Scene, rng: np.random.Generator, clearance: float = START_CLEARANCE) -> Pose2D:
    """A uniformly drawn valid pose with ``clearance`` metres of free space around it, in the largest
    connected free region (so the whole house is reachable), with a random heading."""
    ok, ox, oy = clearance_map(scene, clearance)
    reach, _, _ = reachable_map(scene, None, ROBOT_RADIUS)
    cells = np.argwhere(ok & reach)
    if len(cells) == 0:
        raise ValueError(f"scene {scene.id} has no free floor with {clearance} m clearance")
    i, j = cells[int(rng.integers(0, len(cells)))]
    return Pose2D(x=round(ox + (j + 0.5) * GRID_RES, 3), y=round(oy + (i + 0.5) * GRID_RES, 3),
                  yaw=round(float(rng.uniform(-math.pi, math.pi)), 4))
