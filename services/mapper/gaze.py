"""Gaze points for local search (HELIOS section 3.2, "Local search").

Around a candidate object (its 3D box: ``centre_xyz``, ``extent_xyz``, from the object layer's Gaussians) the
gaze point positions lie on a contour around the object's 2D ground projection: the footprint rectangle grown
by ``radius_m`` (a rounded rectangle), ``n`` points evenly spaced along it. Then, as in the paper:

1. gaze points in occupied cells of the 2D map are discarded (and those off the map), and those closer than
   ``clearance_m`` to an occupied cell (the robot standing there would touch it: the task layer passes the
   robot's mapped clearance, :func:`eqa.robot.mapped_clearance_m`);
2. gaze points with "an occupied region over a certain height in the way between the gaze point and the pick
   location" are discarded: the 2D segment from the gaze point towards the object's centre, up to where it
   enters the object's footprint (the object and its own receptacle are not in the way of themselves), must
   hold no occupied cell whose obstacle height exceeds ``max_obstacle_height_m`` (with no height map, every
   occupied cell on the segment counts as in the way);
3. the orientation looks at the object's centre in the ground plane (``yaw``) and at its highest point
   (``pitch``, from a camera ``camera_height_m`` above the floor; negative = down).

Pure function: numpy in, a list of :class:`GazeCandidate` out (in contour order; the planner orders them by
distance, the object layer scores them with Psi' Eq. 11 and the optimistic IG Eq. 12).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eqa import grid as gridm
from eqa.messages import GridSpec

MAX_GAZE_POINTS = 256
CAMERA_HEIGHT_M = 1.5  # the simulated robot's head camera (services/sim/camera.py)


@dataclass(frozen=True)
class GazeCandidate:
    x: float
    y: float
    yaw: float  # radians, towards the object's centre in the ground plane
    pitch: float  # radians, towards the object's highest point (negative = down)


def contour_points(centre_xy: tuple[float, float], half_xy: tuple[float, float], radius_m: float,
                   n: int) -> np.ndarray:
    """``(n, 2)`` points evenly spaced (by arc length) on the boundary of the rectangle of half-sizes
    ``half_xy`` grown by ``radius_m`` (straight sides and quarter circles at the corners), starting on the
    +x side's middle and running counter-clockwise."""
    cx, cy = centre_xy
    hx, hy = max(half_xy[0], 0.0), max(half_xy[1], 0.0)
    r = radius_m
    # pieces in order (counter-clockwise from (cx + hx + r, cy)): lengths
    side_y, side_x, arc = 2 * hy, 2 * hx, math.pi * r / 2
    pieces = [side_y / 2, arc, side_x, arc, side_y, arc, side_x, arc, side_y / 2]
    total = sum(pieces)
    s = (np.arange(n) + 0.0) * total / n
    out = np.empty((n, 2))
    for k, t in enumerate(s):
        acc = 0.0
        for p_idx, length in enumerate(pieces):
            if t <= acc + length or p_idx == len(pieces) - 1:
                u = t - acc
                out[k] = _piece_point(p_idx, u, cx, cy, hx, hy, r)
                break
            acc += length
    return out


def _piece_point(p: int, u: float, cx: float, cy: float, hx: float, hy: float, r: float) -> tuple[float, float]:
    if p == 0:  # right side, upward from the middle
        return cx + hx + r, cy + u
    if p in (1, 3, 5, 7):  # corner arcs: top-right, top-left, bottom-left, bottom-right
        corner = {1: (hx, hy, 0.0), 3: (-hx, hy, math.pi / 2), 5: (-hx, -hy, math.pi), 7: (hx, -hy, 1.5 * math.pi)}
        ox, oy, a0 = corner[p]
        a = a0 + (u / r if r > 0 else 0.0)
        return cx + ox + r * math.cos(a), cy + oy + r * math.sin(a)
    if p == 2:  # top side, leftward
        return cx + hx - u, cy + hy + r
    if p == 4:  # left side, downward
        return cx - hx - r, cy + hy - u
    if p == 6:  # bottom side, rightward
        return cx - hx + u, cy - hy - r
    return cx + hx + r, cy - hy + u  # p == 8: right side, upward to the middle


def _cell(grid: GridSpec, x: float, y: float) -> tuple[int, int] | None:
    i, j = gridm.cell_of_point(x, y, gridm.origin_of(grid), grid.resolution)
    return (i, j) if gridm.inside(i, j, (grid.rows, grid.cols)) else None


def _entry_t(p: np.ndarray, c: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Parameter ``t`` in [0, 1] where the segment ``p -> c`` (``c`` inside the box) enters the box."""
    d = c - p
    t_in = 0.0
    for k in range(2):
        if abs(d[k]) < 1e-12:
            continue
        t1, t2 = (lo[k] - p[k]) / d[k], (hi[k] - p[k]) / d[k]
        t_in = max(t_in, min(t1, t2))
    return float(min(max(t_in, 0.0), 1.0))


def occluded(occupancy: np.ndarray, heights: np.ndarray | None, grid: GridSpec, start_xy: np.ndarray,
             centre_xy: np.ndarray, half_xy: np.ndarray, max_obstacle_height_m: float) -> bool:
    """Whether an obstacle higher than ``max_obstacle_height_m`` lies on the segment from ``start_xy`` to the
    object's footprint (towards its centre; see the module doc)."""
    lo, hi = centre_xy - half_xy, centre_xy + half_xy
    t_end = _entry_t(start_xy, centre_xy, lo, hi)
    length = float(np.linalg.norm(centre_xy - start_xy)) * t_end
    if length <= 0:
        return False
    n = max(2, math.ceil(length / (grid.resolution / 2)) + 1)
    own = _cell(grid, float(start_xy[0]), float(start_xy[1]))
    for t in np.linspace(0.0, t_end, n)[:-1]:
        q = start_xy + t * (centre_xy - start_xy)
        cell = _cell(grid, float(q[0]), float(q[1]))
        if cell is None or cell == own:
            continue
        if not occupancy[cell]:
            continue
        if heights is None or float(heights[cell]) > max_obstacle_height_m:
            return True
    return False


def _too_close(occ: np.ndarray, grid: GridSpec, cell: tuple[int, int], clearance_m: float) -> bool:
    """Whether an occupied cell lies within ``clearance_m`` of ``cell`` (centre to centre)."""
    if clearance_m <= 0:
        return False
    r = math.ceil(clearance_m / grid.resolution)
    i, j = cell
    i0, j0 = max(0, i - r), max(0, j - r)
    win = occ[i0 : i + r + 1, j0 : j + r + 1]
    ii, jj = np.nonzero(win)
    if ii.size == 0:
        return False
    d2 = ((ii + i0 - i) ** 2 + (jj + j0 - j) ** 2) * grid.resolution**2
    return bool((d2 < clearance_m**2 - 1e-12).any())


def gaze_points(occupancy: np.ndarray, heights: np.ndarray | None, grid: GridSpec,
                centre_xyz: tuple[float, float, float], extent_xyz: tuple[float, float, float], radius_m: float,
                n: int, max_obstacle_height_m: float, camera_height_m: float = CAMERA_HEIGHT_M,
                clearance_m: float = 0.0) -> list[GazeCandidate]:
    """Gaze points around one object (module doc). ``occupancy`` (rows x cols bool) and ``heights`` (the
    obstacle height of each cell in metres, or None) are on ``grid``; ``clearance_m``: the distance a gaze
    point keeps from occupied cells (cell centre to cell centre). Raises ``ValueError`` on bad sizes."""
    occ = np.asarray(occupancy, bool)
    if occ.shape != (grid.rows, grid.cols):
        raise ValueError(f"occupancy is {occ.shape}, the grid is {(grid.rows, grid.cols)}")
    if heights is not None and np.shape(heights) != occ.shape:
        raise ValueError(f"heights is {np.shape(heights)}, the grid is {occ.shape}")
    if not 1 <= int(n) <= MAX_GAZE_POINTS:
        raise ValueError(f"n must be 1..{MAX_GAZE_POINTS}, got {n}")
    vals = [*centre_xyz, *extent_xyz, radius_m, max_obstacle_height_m, camera_height_m, clearance_m]
    if not all(math.isfinite(float(v)) for v in vals) or radius_m <= 0 or min(extent_xyz) < 0:
        raise ValueError("centre, extent, radius and heights must be finite; radius > 0, extent >= 0")
    centre = np.array(centre_xyz[:2], np.float64)
    half = np.array(extent_xyz[:2], np.float64) / 2
    top_z = float(centre_xyz[2]) + float(extent_xyz[2]) / 2
    out = []
    for x, y in contour_points((float(centre[0]), float(centre[1])), (float(half[0]), float(half[1])),
                               radius_m, int(n)):
        cell = _cell(grid, x, y)
        if cell is None or occ[cell] or _too_close(occ, grid, cell, clearance_m):
            continue
        p = np.array([x, y])
        if occluded(occ, heights, grid, p, centre, half, max_obstacle_height_m):
            continue
        dist = float(np.linalg.norm(centre - p))
        yaw = math.atan2(centre[1] - y, centre[0] - x)
        pitch = math.atan2(top_z - camera_height_m, max(dist, 1e-6))
        out.append(GazeCandidate(round(float(x), 4), round(float(y), 4), round(yaw, 6), round(pitch, 6)))
    return out
