"""Shortest paths through the true house, from the simulator's ground-truth navigable grid.

:func:`geodesic_field` is the one geodesic-distance routine of the simulator side (8-connected grid, no corner
cutting, several sources with their own start costs). :func:`target_paths` uses it for the benchmark-only
``target_oracle`` yardstick: the distance from every cell of the house to the nearest ground-truth target of a
question (``Question.targets``), walked around walls and furniture, so that the yardstick heads for the frontier
whose path to the target is shortest rather than the one nearest the target in a straight line. The product never
calls it: only the benchmark runners attach its result to an :class:`eqa.messages.EpisodeStart`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from eqa import grid as gridm
from eqa.messages import GridSpec, TargetPaths
from services.sim.motion import ROBOT_RADIUS, clearance_map
from services.sim.scene import Scene

PATH_RES = 0.1  # m per cell of the target distance field (the message carries rows x cols float32)
SOURCE_RADIUS_M = 1.5  # a target counts as reached from a free cell within this distance, in its own room


def geodesic_field(reach: np.ndarray, resolution: float, sources: Sequence[tuple[int, int, float]]) -> np.ndarray:
    """Geodesic distance (m) to every cell of the boolean ``reach`` grid from the nearest of ``sources``
    ``(row, col, start cost in m)`` (8-connected, no corner cutting): ``min_s cost_s + path(s, cell)``;
    ``inf`` where no source reaches. Sources off the grid or on unreachable cells are ignored."""
    rows, cols = reach.shape
    idx = np.full(reach.shape, -1, np.int64)
    ii, jj = np.nonzero(reach)
    n = len(ii)
    idx[ii, jj] = np.arange(n)
    src, dst, w = [], [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        ni, nj = ii + di, jj + dj
        ok = (ni < rows) & (nj >= 0) & (nj < cols)
        ok[ok] = reach[ni[ok], nj[ok]]
        if di and dj:  # diagonal: both side cells free (no corner cutting)
            ok[ok] = reach[ni[ok], jj[ok]] & reach[ii[ok], nj[ok]]
        src.append(idx[ii[ok], jj[ok]])
        dst.append(idx[ni[ok], nj[ok]])
        w.append(np.full(int(ok.sum()), resolution * math.hypot(di, dj)))
    out = np.full(reach.shape, np.inf)
    starts = [(int(idx[i, j]), float(c)) for i, j, c in sources if gridm.inside(i, j, reach.shape) and idx[i, j] >= 0]
    if not starts:
        return out
    # one virtual node (index n) joined to every source by its start cost: a single Dijkstra run gives the
    # minimum over the sources (a start cost of 0 is kept as a tiny positive weight: csgraph drops zeros)
    s_virtual = np.full(len(starts), n, np.int64)
    d_virtual = np.array([k for k, _ in starts], np.int64)
    w_virtual = np.array([max(c, 1e-9) for _, c in starts])
    s = np.concatenate([*src, s_virtual])
    d = np.concatenate([*dst, d_virtual])
    ww = np.concatenate([*w, w_virtual])
    graph = csr_matrix((ww, (s, d)), shape=(n + 1, n + 1))
    dist = dijkstra(graph, directed=False, indices=n)
    out[reach] = dist[:n]
    return out


def target_sources(scene: Scene, reach: np.ndarray, origin: tuple[float, float], resolution: float,
                   targets: Sequence[tuple[float, float]], radius: float = SOURCE_RADIUS_M
                   ) -> list[tuple[int, int, float]]:
    """The reachable cells within ``radius`` of each target (in the target's own room when the scene has rooms,
    so a cell behind a wall does not count as near), with their straight-line distance to it as start cost."""
    rows, cols = reach.shape
    xs, _ = gridm.cell_center(0, np.arange(cols), origin, resolution)
    _, ys = gridm.cell_center(np.arange(rows), 0, origin, resolution)
    out: list[tuple[int, int, float]] = []
    for tx, ty in targets:
        d = np.hypot(ys[:, None] - ty, xs[None, :] - tx)
        near = reach & (d <= radius)
        room = scene.room_at(tx, ty) if scene.rooms else None
        if room is not None:
            x0, y0, x1, y1 = room.rect
            inside = ((xs[None, :] > x0) & (xs[None, :] < x1)) & ((ys[:, None] > y0) & (ys[:, None] < y1))
            near &= inside
        ii, jj = np.nonzero(near)
        out += [(int(i), int(j), float(d[i, j])) for i, j in zip(ii, jj, strict=True)]
    return out


def target_paths(scene: Scene, targets: Sequence[tuple[float, float]], resolution: float = PATH_RES,
                 clearance: float = ROBOT_RADIUS) -> TargetPaths:
    """Ground truth for the ``target_oracle`` yardstick: per cell of the house, the length (m) of the shortest
    path a robot of radius ``clearance`` can walk to within :data:`SOURCE_RADIUS_M` of a target (plus the
    straight line from there to the target); ``inf`` where no target can be reached."""
    reach, ox, oy = clearance_map(scene, clearance, resolution)
    field = geodesic_field(reach, resolution, target_sources(scene, reach, (ox, oy), resolution, targets))
    rows, cols = field.shape
    return TargetPaths(grid=GridSpec(origin_x=ox, origin_y=oy, resolution=resolution, rows=rows, cols=cols),
                       distance_m=field.astype(np.float32))
