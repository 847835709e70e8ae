"""Frontiers (Explore-EQA section IV-B) and their sampling weights (section IV-D, appendix B, Eq. A6).

A frontier cell is a reachable free cell that has been explored and touches (8-neighbourhood) a cell that is
neither explored nor occupied, or the edge of the grid. Frontier cells are grouped into 8-connected
clusters; a cluster longer than ``max_cluster_cells`` is split with k-means so each candidate covers one
stretch of boundary. Each cluster gives one candidate: its cell nearest the cluster centroid, with the unit
outward normal = the normalised sum of the unit vectors from the cluster's cells to their unexplored
neighbours (it points into unknown space).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from eqa import grid
from eqa.messages import Frontier, TargetPaths

_EIGHT = np.ones((3, 3), dtype=bool)
_OFFSETS = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]


@dataclass(frozen=True)
class FrontierConfig:
    min_cluster_cells: int = 3
    max_cluster_cells: int = 30
    d_sv: float = 3.0  # appendix B: SV_p,normal averages the value up to 3 m along the normal
    # SV_p,normal averages only the scored cells along the normal (the reference implementation keeps the
    # non-zero values only), so unscored unknown space does not dilute a value seen beyond it
    normal_scored_only: bool = False
    # the value an unscored cell counts with in Eq. A6 (0: below every scored value, SV >= 1)
    unscored_sv: float = 0.0


def frontier_cells(
    free: np.ndarray, explored: np.ndarray, occupied: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(frontier mask, unknown mask). ``unknown`` = neither explored nor occupied."""
    unknown = ~explored & ~occupied
    padded = np.pad(unknown, 1, constant_values=True)  # outside the grid is unknown
    touches = ndimage.binary_dilation(padded, structure=_EIGHT)[1:-1, 1:-1]
    return free & explored & touches, unknown


def _split(cells: np.ndarray, k: int, iters: int = 8) -> np.ndarray:
    """Deterministic k-means of cell coordinates (farthest-point initialisation). Returns labels."""
    pts = cells.astype(np.float64)
    centers = [pts[0]]
    for _ in range(1, k):
        d = np.min([np.sum((pts - c) ** 2, axis=1) for c in centers], axis=0)
        centers.append(pts[int(np.argmax(d))])
    C = np.array(centers)
    labels = np.zeros(len(pts), dtype=np.int64)
    for _ in range(iters):
        labels = np.argmin(((pts[:, None, :] - C[None]) ** 2).sum(-1), axis=1)
        # Cluster means of integer cell coordinates: the sums are exact in float64 in any order, so the
        # bincount sums equal the per-cluster ``mean`` of the straightforward loop bit for bit.
        count = np.bincount(labels, minlength=k)
        has = count > 0
        sx = np.bincount(labels, weights=pts[:, 0], minlength=k)
        sy = np.bincount(labels, weights=pts[:, 1], minlength=k)
        C[has, 0] = sx[has] / count[has]
        C[has, 1] = sy[has] / count[has]
    return labels


def find_frontiers(
    free: np.ndarray,
    explored: np.ndarray,
    occupied: np.ndarray,
    origin: tuple[float, float],
    resolution: float,
    robot_xy: tuple[float, float],
    config: FrontierConfig | None = None,
) -> list[Frontier]:
    """Frontier candidates (weight 1; see :func:`weigh_frontiers`), sorted by position for determinism."""
    config = config or FrontierConfig()
    mask, unknown = frontier_cells(free, explored, occupied)
    labels, n = ndimage.label(mask, structure=_EIGHT)
    if n == 0:
        return []
    ny, nx = mask.shape
    unknown_p = np.pad(unknown, 1, constant_values=True)
    # per frontier cell: sum of unit vectors towards unknown neighbours
    normal = np.zeros((ny, nx, 2), dtype=np.float64)
    for dr, dc in _OFFSETS:
        nb = unknown_p[1 + dr : 1 + dr + ny, 1 + dc : 1 + dc + nx]
        inv = 1.0 / math.hypot(dr, dc)
        normal[..., 0] += nb * (dc * inv)  # x = columns
        normal[..., 1] += nb * (dr * inv)  # y = rows
    out: list[Frontier] = []
    objects = ndimage.find_objects(labels)
    for lab, sl in enumerate(objects, start=1):
        if sl is None:
            continue
        rr, cc = np.nonzero(labels[sl] == lab)
        rr = rr + sl[0].start
        cc = cc + sl[1].start
        if rr.size < config.min_cluster_cells:
            continue
        cells = np.stack([rr, cc], axis=1)
        k = math.ceil(rr.size / config.max_cluster_cells)
        parts = _split(cells, k) if k > 1 else np.zeros(rr.size, dtype=np.int64)
        for j in range(k):
            sel = parts == j
            if sel.sum() < config.min_cluster_cells:
                continue
            pr, pc = rr[sel], cc[sel]
            cr, cc_ = pr.mean(), pc.mean()
            best = int(np.argmin((pr - cr) ** 2 + (pc - cc_) ** 2))
            r, c = int(pr[best]), int(pc[best])
            x, y = grid.cell_center(r, c, origin, resolution)
            n_vec = normal[pr, pc].sum(axis=0)
            norm = float(np.hypot(*n_vec))
            if norm < 1e-9:  # symmetric boundary: face away from the robot
                n_vec = np.array([x - robot_xy[0], y - robot_xy[1]])
                norm = float(np.hypot(*n_vec)) or 1.0
                if norm == 1.0 and not n_vec.any():
                    n_vec = np.array([1.0, 0.0])
            out.append(
                Frontier(x=x, y=y, nx=float(n_vec[0] / norm), ny=float(n_vec[1] / norm), size=int(sel.sum()))
            )
    out.sort(key=lambda f: (round(f.y, 3), round(f.x, 3)))
    return out


def value_at(
    layer: np.ndarray, origin: tuple[float, float], resolution: float, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """Nearest-cell lookup of a value layer; 0 outside the grid (never scored)."""
    row, col = grid.cell_of(x, y, origin, resolution)
    inside = grid.inside(row, col, layer.shape)
    out = np.zeros(np.shape(col), dtype=np.float64)
    out[inside] = layer[row[inside], col[inside]]
    return out


def sv_normal(
    layer: np.ndarray, origin: tuple[float, float], resolution: float, f: Frontier, d_sv: float
) -> float:
    """SV_p,normal (section IV-D): mean semantic value of the points at distances ``resolution, 2 resolution,
    ..., d_sv`` from the frontier ``p`` along its normal."""
    s = np.arange(1, round(d_sv / resolution) + 1) * resolution
    return float(value_at(layer, origin, resolution, f.x + s * f.nx, f.y + s * f.ny).mean())


def path_distances(paths: TargetPaths, x: np.ndarray, y: np.ndarray, radius: float = 0.3) -> np.ndarray:
    """Walked distance (m) from world points to the nearest target (:class:`eqa.messages.TargetPaths`): the
    smallest ``distance + offset`` over the true grid's cells within ``radius`` of each point, since a frontier
    of the robot's own map may lie on a cell the true grid blocks (next to furniture); ``inf`` where none
    reaches."""
    g = paths.grid
    origin = (g.origin_x, g.origin_y)
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    row, col = grid.cell_of(x, y, origin, g.resolution)
    r = max(0, math.ceil(radius / g.resolution))
    best = np.full(np.shape(x), np.inf)
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            ii, jj = row + di, col + dj
            cx, cy = grid.cell_center(ii, jj, origin, g.resolution)
            off = np.hypot(cx - x, cy - y)
            near = grid.inside(ii, jj, (g.rows, g.cols)) & (off <= radius + g.resolution)
            val = np.full(np.shape(x), np.inf)
            val[near] = paths.distance_m[ii[near], jj[near]] + off[near]
            best = np.minimum(best, val)
    return best


def target_weights(frontiers: list[Frontier], targets: list[tuple[float, float]],
                   paths: TargetPaths | None = None) -> list[Frontier]:
    """The ``target_oracle`` yardstick (benchmark-only upper bound): ``weight = 1 / (1 + d)`` with ``d`` the
    distance (m) from the frontier to the nearest ground-truth target (``sv`` holds ``-d``). With ``paths`` (the
    true house's walked distances, :class:`eqa.messages.TargetPaths`) ``d`` is the walk around walls and
    furniture; a frontier from which the true house reaches no target, or any frontier without ``paths``, gets
    the straight-line distance. The planner goes for the smallest robot-to-frontier plus frontier-to-target
    distance (:func:`services.planner.sampling.choose`). Without targets every frontier weighs 1."""
    if not targets:
        return [f.model_copy(update={"sv": 0.0, "sv_normal": 0.0, "weight": 1.0}) for f in frontiers]
    if not frontiers:
        return []
    t = np.asarray(targets, dtype=np.float64)
    fx = np.array([f.x for f in frontiers])
    fy = np.array([f.y for f in frontiers])
    d = np.sqrt(((t[None, :, :] - np.stack([fx, fy], -1)[:, None, :]) ** 2).sum(-1)).min(axis=1)
    if paths is not None:
        walked = path_distances(paths, fx, fy)
        d = np.where(np.isfinite(walked), np.maximum(walked, d), d)
    return [f.model_copy(update={"sv": -float(di), "sv_normal": 0.0, "weight": 1.0 / (1.0 + float(di))})
            for f, di in zip(frontiers, d, strict=True)]


MAX_LOG_WEIGHT = 700.0  # exp(709.8) overflows a float64


def frontier_weight(sv_p: float, sv_p_normal: float, tau_sv: float, tau_sv_normal: float) -> float:
    """Eq. A6: ``w_p = exp(tau_SV * SV_p + tau_SV,Normal * SV_p,normal)``."""
    return float(math.exp(tau_sv * sv_p + tau_sv_normal * sv_p_normal))


def weigh_frontiers(
    frontiers: list[Frontier],
    layer: np.ndarray | None,
    origin: tuple[float, float],
    resolution: float,
    tau_sv: float,
    tau_sv_normal: float,
    d_sv: float = 3.0,
    normal_scored_only: bool = False,
    unscored_sv: float = 0.0,
) -> list[Frontier]:
    """Fill ``sv``, ``sv_normal`` and ``weight`` (Eq. A6) of each frontier from a semantic value layer.
    ``layer=None`` (strategies without semantic values: fbe, nearest) gives every frontier weight 1.
    ``normal_scored_only``: SV_p,normal is the mean of the scored (non-zero) cells along the normal;
    ``unscored_sv``: the value unscored cells count with (:class:`FrontierConfig`)."""
    if layer is None:
        return [f.model_copy(update={"sv": 0.0, "sv_normal": 0.0, "weight": 1.0}) for f in frontiers]
    if not frontiers:
        return []
    # All frontiers at once; the same element-wise arithmetic as :func:`value_at` / :func:`sv_normal` per
    # frontier, and each SV_p,normal is the mean of its own row, so the values are identical.
    fx = np.array([f.x for f in frontiers])
    fy = np.array([f.y for f in frontiers])
    fnx = np.array([f.nx for f in frontiers])
    fny = np.array([f.ny for f in frontiers])
    s = np.arange(1, round(d_sv / resolution) + 1) * resolution
    sv_p = value_at(layer, origin, resolution, fx, fy)
    along = value_at(layer, origin, resolution, fx[:, None] + s[None, :] * fnx[:, None],
                     fy[:, None] + s[None, :] * fny[:, None])
    scored = along > 0
    if normal_scored_only:
        count = scored.sum(axis=1)
        sv_n = np.where(count > 0, np.where(scored, along, 0.0).sum(axis=1) / np.maximum(count, 1), unscored_sv)
    else:
        along = np.where(scored, along, unscored_sv)
        sv_n = np.array([float(row.mean()) for row in along])  # row by row, as :func:`sv_normal`
    sv_p = np.where(sv_p > 0, sv_p, unscored_sv)
    log_w = tau_sv * sv_p + tau_sv_normal * sv_n
    # Eq. A6 as is while exp() is finite; beyond (SV = exp(tau_LSV LSV + tau_GSV GSV) reaches e^10 at the
    # paper's tau = 5, Fig. 7c) every weight is divided by the largest: sampling, proportional to the
    # weights, is unchanged, and no weight overflows. Ratios below e^-700 are clamped there rather than
    # underflowing to 0, so when the best frontier is unreachable the planner still samples among the rest.
    shift = float(log_w.max()) if float(log_w.max()) > MAX_LOG_WEIGHT else 0.0
    out = []
    for i, f in enumerate(frontiers):
        if shift == 0.0:
            w = frontier_weight(float(sv_p[i]), float(sv_n[i]), tau_sv, tau_sv_normal)
        else:
            w = math.exp(max(float(log_w[i]) - shift, -MAX_LOG_WEIGHT))
        out.append(f.model_copy(update={"sv": float(sv_p[i]), "sv_normal": float(sv_n[i]), "weight": w}))
    return out
