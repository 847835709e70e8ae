"""World <-> cell conversion of the 2D floor grids, in one place.

A grid is an ``origin = (origin_x, origin_y)`` (metres, world frame: ``z`` up) and a cell side ``resolution``;
cell ``(row, col)`` covers ``x in [origin_x + col*res, +res)``, ``y in [origin_y + row*res, +res)``
(:class:`eqa.messages.GridSpec` carries the same numbers over the bus, with ``rows x cols``).

Every function works on Python scalars and on numpy arrays alike, with the same floating-point operations in
the same order everywhere (``floor((v - o) / res)`` one way, ``o + (idx + 0.5) * res`` the other), so a map,
a frontier or a path computed through here is bit-for-bit what each module computed by hand before.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from eqa.messages import GridSpec

Origin = tuple[float, float]


def origin_of(spec: GridSpec) -> Origin:
    return (spec.origin_x, spec.origin_y)


def fractional_cell(x: Any, y: Any, origin: Origin, resolution: float) -> tuple[Any, Any]:
    """``(row, col)`` of world points as real numbers (cell ``(r, c)`` spans ``[r, r+1) x [c, c+1)``)."""
    return (y - origin[1]) / resolution, (x - origin[0]) / resolution


def cell_of(x: Any, y: Any, origin: Origin, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """``(row, col)`` int64 arrays of the cells holding world points (may lie outside the grid: see
    :func:`inside`)."""
    col = np.floor((np.asarray(x) - origin[0]) / resolution).astype(np.int64)
    row = np.floor((np.asarray(y) - origin[1]) / resolution).astype(np.int64)
    return row, col


def cell_of_point(x: float, y: float, origin: Origin, resolution: float) -> tuple[int, int]:
    """``(row, col)`` of one world point, as Python ints (may lie outside the grid)."""
    return math.floor((y - origin[1]) / resolution), math.floor((x - origin[0]) / resolution)


def cell_center(row: Any, col: Any, origin: Origin, resolution: float) -> tuple[Any, Any]:
    """World ``(x, y)`` of cell centres; ``row`` and ``col`` may be arrays of different shapes (the ``y`` of the
    rows and the ``x`` of the columns are computed independently)."""
    return origin[0] + (col + 0.5) * resolution, origin[1] + (row + 0.5) * resolution


def world_of(row: Any, col: Any, origin: Origin, resolution: float) -> tuple[Any, Any]:
    """World ``(x, y)`` of fractional cell coordinates (the inverse of :func:`fractional_cell`)."""
    return origin[0] + col * resolution, origin[1] + row * resolution


def inside(row: Any, col: Any, shape: tuple[int, ...]) -> Any:
    """Whether cells lie in a ``(rows, cols)`` grid (element-wise for arrays)."""
    return (row >= 0) & (row < shape[0]) & (col >= 0) & (col < shape[1])


def bounds(spec: GridSpec) -> tuple[float, float, float, float]:
    """``(x0, y0, x1, y1)``: the grid covers ``[x0, x1) x [y0, y1)``."""
    return (spec.origin_x, spec.origin_y, spec.origin_x + spec.cols * spec.resolution,
            spec.origin_y + spec.rows * spec.resolution)


def contains(spec: GridSpec, x: float, y: float) -> bool:
    """Whether world point ``(x, y)`` lies in the grid."""
    x0, y0, x1, y1 = bounds(spec)
    return x0 <= x < x1 and y0 <= y < y1
