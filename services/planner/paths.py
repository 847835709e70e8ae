"""Collision-free paths on the 2D map with clearance (the planner pi of Explore-EQA section III).

The mapper's 2D map has fine cells (0.1 m in the reference settings). Searching 4 M fine cells every step
in Python is far too slow, so the search runs on a *coarse planning grid* whose blocks are ``k x k`` fine
cells (``k = round(coarse_m / resolution)``, 2 by default, larger only when the known area is huge):

1. Crop the map to the bounding box of the free cells (plus a margin); the rest is unknown anyway.
2. ``blocked`` = not free (occupied *or* unknown). A block is *traversable* when no blocked fine cell lies
   closer than the clearance to any fine cell of the block. This is computed exactly at block level: a
   block is dilated over the blocks whose nearest fine cells are closer than the clearance
   (:func:`block_footprint`), with one compiled ``scipy.ndimage`` dilation of the block-level "any blocked"
   mask. So every fine cell of a traversable block is free and has Euclidean clearance >= ``clearance``
   (cell centre to blocked cell centre).
3. One Dijkstra (``scipy.sparse.csgraph``, compiled) from the robot's block over the 8-connected graph of
   traversable blocks (diagonal moves only when both side blocks are traversable: no corner cutting) gives
   the geodesic distance to every reachable block and the predecessors to read paths from.
4. Paths are block centres, shortened by string pulling with a conservative segment test
   (:meth:`PlanningGrid.segment_clear`), so every point of every segment lies inside traversable blocks.

The only leg exempt from the clearance rule is the first one, from the robot's own position to the nearest
traversable block when the robot's block itself is not traversable (the robot stands there: its footprint
is often unseen at step 0); that leg must not cross occupied cells and is at most ``snap_radius_m`` long.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from eqa import grid as gridm
from eqa.messages import GridSpec

log = logging.getLogger(__name__)

_SQRT2 = math.sqrt(2.0)


class MapError(ValueError):
    """A map the planner cannot use (wrong shapes, robot outside the map, ...)."""


def block_footprint(clearance_cells: float, k: int) -> np.ndarray:
    """Block offsets ``(di, dj)`` whose fine cells can lie closer than ``clearance_cells`` to some fine cell
    of the centre block. The nearest fine cells of two blocks ``d`` blocks apart are
    ``max(0, |d| k - (k - 1))`` fine cells apart along that axis."""
    c = float(clearance_cells)
    reach = max(0, math.ceil(c + k) // k + 1)
    offs = np.arange(-reach, reach + 1)
    gap = np.maximum(0, np.abs(offs) * k - (k - 1)).astype(np.float64)
    d2 = gap[:, None] ** 2 + gap[None, :] ** 2
    fp = d2 < c * c - 1e-9
    fp[reach, reach] = True  # the block itself: a blocked fine cell inside it always counts
    rows = np.flatnonzero(fp.any(axis=1))
    cols = np.flatnonzero(fp.any(axis=0))
    return fp[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]


@dataclass
class PlanningGrid:
    """Traversable coarse blocks of one map at one clearance, and the distance field from a start."""

    grid: GridSpec
    clearance_m: float
    k: int  # fine cells per block side
    i0: int  # fine row of block row 0
    j0: int  # fine column of block column 0
    traversable: np.ndarray  # (R, C) bool
    occupied: np.ndarray  # fine occupied mask (full map), for the exempt first leg
    dist: np.ndarray | None = None  # (R, C) geodesic metres from the start block, inf if unreachable
    pred: np.ndarray | None = None  # (R, C) flat index of the predecessor block, -1 for none
    start_block: tuple[int, int] | None = None
    start_xy: tuple[float, float] | None = None  # the robot position the paths begin with
    timing_ms: dict[str, float] = field(default_factory=dict)

    @property
    def block_m(self) -> float:
        return self.k * self.grid.resolution

    # ---- coordinates ---------------------------------------------------------------------------------------
    def block_of(self, x: float, y: float) -> tuple[int, int]:
        """Block (row, column) containing world point ``(x, y)`` (may be outside the block grid)."""
        r, c = gridm.fractional_cell(x, y, gridm.origin_of(self.grid), self.grid.resolution)
        return math.floor((r - self.i0) / self.k), math.floor((c - self.j0) / self.k)

    def block_centre(self, bi: np.ndarray | int, bj: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        return gridm.world_of(self.i0 + (np.asarray(bi) + 0.5) * self.k, self.j0 + (np.asarray(bj) + 0.5) * self.k,
                              gridm.origin_of(self.grid), self.grid.resolution)

    def is_traversable(self, x: float, y: float) -> bool:
        bi, bj = self.block_of(x, y)
        R, C = self.traversable.shape
        return 0 <= bi < R and 0 <= bj < C and bool(self.traversable[bi, bj])

    # ---- segment test --------------------------------------------------------------------------------------
    def segment_clear(self, a: tuple[float, float], b: tuple[float, float]) -> bool:
        """True when every point of segment ``a``-``b`` lies in a traversable block.

        Samples every 0.2 block and tests, for each sample, every block within 0.11 block of it, which is
        conservative: a segment that clips a corner of a blocked block between two samples passes within
        half a sample step of that block."""
        origin, res = gridm.origin_of(self.grid), self.grid.resolution
        (ra, ca), (rb, cb) = gridm.fractional_cell(*a, origin, res), gridm.fractional_cell(*b, origin, res)
        u0, v0 = (ca - self.j0) / self.k, (ra - self.i0) / self.k
        u1, v1 = (cb - self.j0) / self.k, (rb - self.i0) / self.k
        n = max(2, math.ceil(math.hypot(u1 - u0, v1 - v0) / 0.2) + 1)
        t = np.linspace(0.0, 1.0, n)
        u = u0 + (u1 - u0) * t
        v = v0 + (v1 - v0) * t
        e = 0.11
        R, C = self.traversable.shape
        for du in (-e, e):
            for dv in (-e, e):
                bj = np.floor(u + du).astype(np.int64)
                bi = np.floor(v + dv).astype(np.int64)
                if not gridm.inside(bi, bj, (R, C)).all():
                    return False
                if not self.traversable[bi, bj].all():
                    return False
        return True

    def leg_hits_occupied(self, a: tuple[float, float], b: tuple[float, float]) -> bool:
        """True when the straight leg ``a``-``b`` touches an occupied fine cell (the exempt first leg)."""
        g = self.grid
        n = max(2, math.ceil(math.hypot(b[0] - a[0], b[1] - a[1]) / (0.25 * g.resolution)) + 1)
        t = np.linspace(0.0, 1.0, n)
        x = a[0] + (b[0] - a[0]) * t
        y = a[1] + (b[1] - a[1]) * t
        i, j = gridm.cell_of(x, y, gridm.origin_of(g), g.resolution)
        inside = gridm.inside(i, j, (g.rows, g.cols))
        return bool(self.occupied[i[inside], j[inside]].any())

    # ---- search --------------------------------------------------------------------------------------------
    def snap_start(self, x: float, y: float, radius_m: float) -> tuple[int, int] | None:
        """The robot's block if traversable, else the nearest traversable block within ``radius_m`` whose
        straight leg from the robot does not touch an occupied cell."""
        bi, bj = self.block_of(x, y)
        R, C = self.traversable.shape
        if 0 <= bi < R and 0 <= bj < C and self.traversable[bi, bj]:
            return bi, bj
        rad = math.ceil(radius_m / self.block_m) + 1
        r0, r1 = max(0, bi - rad), min(R, bi + rad + 1)
        c0, c1 = max(0, bj - rad), min(C, bj + rad + 1)
        if r0 >= r1 or c0 >= c1:
            return None
        ii, jj = np.nonzero(self.traversable[r0:r1, c0:c1])
        if ii.size == 0:
            return None
        ii = ii + r0
        jj = jj + c0
        cx, cy = self.block_centre(ii, jj)
        d = np.hypot(cx - x, cy - y)
        for n in np.argsort(d, kind="stable")[:64]:
            if d[n] > radius_m:
                break
            if not self.leg_hits_occupied((x, y), (float(cx[n]), float(cy[n]))):
                return int(ii[n]), int(jj[n])
        return None

    def search_from(self, x: float, y: float, snap_radius_m: float) -> bool:
        """Run Dijkstra from the robot at ``(x, y)``. False when no traversable start block exists."""
        self.start_xy = (float(x), float(y))
        start = self.snap_start(x, y, snap_radius_m)
        self.start_block = start
        R, C = self.traversable.shape
        self.dist = np.full((R, C), np.inf)
        self.pred = np.full((R, C), -1, dtype=np.int64)
        if start is None:
            return False
        t0 = _now_ms()
        graph, ids = grid_graph(self.traversable)
        src = int(ids[start])
        d, p = dijkstra(graph, directed=False, indices=src, return_predecessors=True)
        nodes = np.flatnonzero(self.traversable.ravel())
        self.dist.ravel()[nodes] = d * self.block_m
        p = np.asarray(p, dtype=np.int64)
        ok = p >= 0
        flat_pred = np.full(p.shape, -1, dtype=np.int64)
        flat_pred[ok] = nodes[p[ok]]
        self.pred.ravel()[nodes] = flat_pred
        self.timing_ms["dijkstra"] = _now_ms() - t0
        return True

    def reached_near(self, x: float, y: float, radius_m: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The blocks :meth:`search_from` reached in the square of half-side ``radius_m`` (and one block more)
        around ``(x, y)``: their rows, columns, centres (x, y) and geodesic metres; empty arrays when none."""
        if self.dist is None:
            raise RuntimeError("search_from() first")
        R, C = self.dist.shape
        bi, bj = self.block_of(x, y)
        rad = math.ceil(radius_m / self.block_m) + 1
        r0, r1, c0, c1 = max(0, bi - rad), min(R, bi + rad + 1), max(0, bj - rad), min(C, bj + rad + 1)
        if r0 >= r1 or c0 >= c1:
            none = np.zeros(0, np.int64)
            return none, none, np.zeros(0), np.zeros(0), np.zeros(0)
        ii, jj = np.nonzero(np.isfinite(self.dist[r0:r1, c0:c1]))
        ii, jj = ii + r0, jj + c0
        cx, cy = self.block_centre(ii, jj)
        return ii, jj, np.asarray(cx, float), np.asarray(cy, float), self.dist[ii, jj]

    def block_path(self, target: tuple[int, int]) -> list[tuple[int, int]]:
        """Blocks from the start block to ``target`` (inclusive); empty when unreachable."""
        if self.dist is None or self.pred is None or self.start_block is None:
            raise RuntimeError("search_from() first")
        if not np.isfinite(self.dist[target]):
            return []
        C = self.traversable.shape[1]
        out = [target]
        flat = target[0] * C + target[1]
        start_flat = self.start_block[0] * C + self.start_block[1]
        guard = self.traversable.size
        while flat != start_flat:
            flat = int(self.pred.ravel()[flat])
            if flat < 0 or guard <= 0:
                return []
            out.append((flat // C, flat % C))
            guard -= 1
        out.reverse()
        return out

    def world_path(
        self, target: tuple[int, int], horizon_m: float | None = None
    ) -> tuple[list[tuple[float, float]], bool, list[tuple[float, float]]]:
        """World path from the robot position to the centre of block ``target``.

        Returns ``(path, complete, raw)``: ``path`` is string-pulled, covering at least ``horizon_m`` metres
        of it (or all of it, then ``complete``); ``raw`` is the whole unshortened path of block centres (for
        display). Pulling only a prefix keeps a step fast when the target is hundreds of metres away."""
        blocks = self.block_path(target)
        if not blocks or self.start_xy is None:
            return [], False, []
        bi = np.array([b[0] for b in blocks])
        bj = np.array([b[1] for b in blocks])
        cx, cy = self.block_centre(bi, bj)
        pts = [(float(a), float(b)) for a, b in zip(cx, cy, strict=True)]
        robot = self.start_xy
        head: list[tuple[float, float]] = []
        if self.is_traversable(*robot):
            pts[0] = robot  # the robot stands inside the start block: begin exactly there
        else:
            head = [robot]  # exempt first leg: robot -> centre of the snapped start block
        raw = head + _corners(pts)
        if horizon_m is None:
            return head + self._pull(pts), True, raw
        seg = np.hypot(np.diff(cx), np.diff(cy))
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        want = max(0.0, horizon_m - path_length(head))
        reach = 1.5 * want + 2 * self.block_m
        while True:
            cut = int(np.searchsorted(cum, reach, side="right"))
            complete = cut >= len(pts)
            pulled = self._pull(pts[: max(cut, 1) + (0 if complete else 1)])
            if complete or path_length(pulled) >= want:
                return head + pulled, complete, raw
            reach *= 2

    def _pull(self, pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
        """String pulling: from each anchor, jump to the farthest point in sight (first failure stops)."""
        if len(pts) <= 2:
            return pts
        out = [pts[0]]
        i = 0
        n = len(pts)
        while i < n - 1:
            j = i + 1
            while j + 1 < n and self.segment_clear(pts[i], pts[j + 1]):
                j += 1
            out.append(pts[j])
            i = j
        return out


def _corners(pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points of a polyline where its direction changes (plus both ends)."""
    if len(pts) <= 2:
        return pts
    a = np.asarray(pts)
    d = np.diff(a, axis=0)
    turn = np.abs(d[1:, 0] * d[:-1, 1] - d[1:, 1] * d[:-1, 0]) > 1e-9
    keep = np.concatenate([[True], turn, [True]])
    return [pts[i] for i in np.flatnonzero(keep)]


def grid_graph(mask: np.ndarray) -> tuple[csr_matrix, np.ndarray]:
    """Undirected 8-connected graph of the True cells of ``mask`` (edge weights 1 and sqrt 2 in cells;
    diagonal edges only when both side cells are True). Returns the graph and the node id of each cell
    (-1 for False cells)."""
    H, W = mask.shape
    ids = np.full(mask.shape, -1, dtype=np.int64)
    n = int(mask.sum())
    ids[mask] = np.arange(n)
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    wts: list[np.ndarray] = []

    Sl = tuple[slice, slice]

    def add(a: Sl, b: Sl, w: float, extra: np.ndarray | None = None) -> None:
        m = mask[a] & mask[b]
        if extra is not None:
            m &= extra
        rows.append(ids[a][m])
        cols.append(ids[b][m])
        wts.append(np.full(int(m.sum()), w))

    s, e = slice(None), slice(None)
    add((s, slice(0, W - 1)), (e, slice(1, W)), 1.0)
    add((slice(0, H - 1), s), (slice(1, H), e), 1.0)
    # diagonals without corner cutting: both orthogonal neighbours must be traversable
    add(
        (slice(0, H - 1), slice(0, W - 1)),
        (slice(1, H), slice(1, W)),
        _SQRT2,
        mask[0 : H - 1, 1:W] & mask[1:H, 0 : W - 1],
    )
    add(
        (slice(0, H - 1), slice(1, W)),
        (slice(1, H), slice(0, W - 1)),
        _SQRT2,
        mask[0 : H - 1, 0 : W - 1] & mask[1:H, 1:W],
    )
    r = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    c = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    w = np.concatenate(wts) if wts else np.zeros(0)
    return csr_matrix((w, (r, c)), shape=(n, n)), ids


def _now_ms() -> float:
    import time

    return time.perf_counter() * 1e3


def check_map(grid: GridSpec, free: np.ndarray, occupied: np.ndarray) -> None:
    """Raise :class:`MapError` when the layers do not match the grid."""
    shape = (grid.rows, grid.cols)
    for name, arr in (("free", free), ("occupied", occupied)):
        if not isinstance(arr, np.ndarray) or arr.shape != shape:
            got = getattr(arr, "shape", type(arr).__name__)
            raise MapError(f"map layer {name!r} has shape {got}, the grid says {shape}")


def planning_grid(
    grid: GridSpec,
    free: np.ndarray,
    occupied: np.ndarray,
    clearance_m: float,
    coarse_m: float = 0.2,
    max_blocks: int = 400_000,
    extra_blocked: np.ndarray | None = None,
) -> PlanningGrid:
    """Traversable coarse blocks of a map (steps 1 and 2 of the module doc).

    ``free``/``occupied`` are the mapper's layers (rows x cols); ``extra_blocked`` (same shape, optional)
    marks fine cells to avoid as well (e.g. around poses the simulator refused)."""
    t0 = _now_ms()
    check_map(grid, free, occupied)
    free = free.astype(bool, copy=False)
    occupied = occupied.astype(bool, copy=False)
    res = grid.resolution
    clear_cells = round(clearance_m / res, 6)
    k = max(1, round(coarse_m / res))
    rows_any = np.flatnonzero(free.any(axis=1))
    if rows_any.size == 0:
        empty = np.zeros((1, 1), dtype=bool)
        return PlanningGrid(grid, clearance_m, k, 0, 0, empty, occupied, timing_ms={"traversable": 0.0})
    cols_any = np.flatnonzero(free.any(axis=0))
    i0, i1 = int(rows_any[0]), int(rows_any[-1]) + 1
    j0, j1 = int(cols_any[0]), int(cols_any[-1]) + 1
    while (i1 - i0) * (j1 - j0) / (k * k) > max_blocks:
        k += 1
    margin = k
    i0, j0 = i0 - margin, j0 - margin
    nb_r = math.ceil((i1 + margin - i0) / k)
    nb_c = math.ceil((j1 + margin - j0) / k)
    # fine blocked mask of the crop, padded with "blocked" where the crop leaves the map
    blocked = np.ones((nb_r * k, nb_c * k), dtype=bool)
    si0, sj0 = max(0, i0), max(0, j0)
    si1, sj1 = min(grid.rows, i0 + nb_r * k), min(grid.cols, j0 + nb_c * k)
    sub = ~free[si0:si1, sj0:sj1]
    if extra_blocked is not None:
        sub = sub | extra_blocked[si0:si1, sj0:sj1]
    blocked[si0 - i0 : si1 - i0, sj0 - j0 : sj1 - j0] = sub
    any_blocked = blocked.reshape(nb_r, k, nb_c, k).any(axis=(1, 3))
    fp = block_footprint(clear_cells, k)
    dilated = ndimage.binary_dilation(any_blocked, structure=fp, border_value=1)
    pg = PlanningGrid(grid, clearance_m, k, i0, j0, ~dilated, occupied)
    pg.timing_ms["traversable"] = _now_ms() - t0
    return pg


def truncate(path: list[tuple[float, float]], max_len: float) -> tuple[list[tuple[float, float]], bool]:
    """The first ``max_len`` metres of ``path`` and whether the whole path fits (Explore-EQA: at most 3 m
    between consecutive poses)."""
    if not path:
        return [], True
    out = [path[0]]
    left = max_len
    for a, b in itertools.pairwise(path):
        seg = math.hypot(b[0] - a[0], b[1] - a[1])
        if seg <= left + 1e-9:
            out.append(b)
            left -= seg
            continue
        f = max(0.0, left) / seg if seg > 0 else 0.0
        out.append((a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f))
        return out, False
    return out, True


def path_length(path: list[tuple[float, float]]) -> float:
    return float(sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in itertools.pairwise(path)))
