"""Deterministic frontier rules that go beyond Eq. A6 sampling: ``vlfm``, ``gain`` and ``topo``.

All three read the same per-frontier semantic value the mapper writes for ``semantic`` (``Frontier.sv``,
``Frontier.sv_normal``: Eq. 3 values at the frontier and along its normal) and nothing of the ground truth.

* Value. ``v_p = ln max(1, (SV_p + SV_p,normal) / 2)``: Eq. 3 is ``SV = exp(tau_LSV LSV + tau_GSV GSV)``, so
  ``v_p`` is back on the scale of the scores themselves (0 for a frontier nothing was seen near, at most
  ``tau_LSV + tau_GSV``), the scale on which a cost per metre is comparable from house to house.
* ``vlfm`` (VLFM's rule, value maximisation with a distance cost): the robot goes to the reachable frontier of
  highest ``s_p = v_p - lambda d_p`` (``d_p``: geodesic distance). Subtracting ``lambda d`` from the log value is
  the same ranking as ``SV exp(-lambda d)`` on Eq. 3's scale, so the two forms VLFM-style planners use agree
  here; the additive form keeps ``lambda`` in value units per metre.
* ``gain`` (HELIOS's frontier objective, Eq. 10, with an exploration term): ``s_p = v_p + beta g_p - lambda d_p``
  with ``g_p`` the share of the disk of radius ``gain_radius_m`` around the frontier that is unknown (neither
  explored nor occupied; outside the map counts as unknown, as for the frontiers themselves): the area a visit
  is expected to reveal, in [0, 1].
* ``topo`` (steering through the explored map's topology): ``s_p = v_p - lambda d_p - mu h_p`` where ``h_p`` is the
  number of doorways between the robot's room and the frontier's on the region graph of the free space
  (:func:`regions`: rooms are the connected parts of the free space farther than ``topo_core_m`` from any
  obstacle or unknown cell, grown back over the free space; two rooms are linked where their cells touch,
  which is a doorway or an opening). The frontier's cost is then counted along the graph of rooms, not in
  straight-line or path metres only: a room is finished before the robot crosses into the next.

Perfect-value yardsticks (benchmark-only, :data:`eqa.messages.PERFECT_VALUE_RULE`): ``perfect_vlfm`` and
``perfect_gain`` are ``vlfm`` and ``gain`` unchanged, on the values the mapper computed from the ground-truth
target positions instead of the scorer's (:func:`rule_of` names the rule a strategy runs).

Commitment (all three): the frontier chosen earlier (``Memory.target``, which carries its value when chosen)
is kept while a candidate lies within ``commit_radius_m`` of it, its value has not dropped by more than
``commit_margin`` since it was chosen, and its score is within ``commit_margin`` of the best score of the step
(the value map changed so that another frontier is now clearly better: re-plan). Ties go to the shorter
geodesic distance, then to the lower index, so a step is a pure function of the map.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from eqa import grid as gridm
from eqa.messages import PERFECT_VALUE_RULE, Frontier, GridSpec

RULES: frozenset[str] = frozenset({"vlfm", "gain", "topo"})
_EIGHT = np.ones((3, 3), dtype=bool)


def rule_of(strategy: str) -> str | None:
    """The rule (one of :data:`RULES`) a strategy chooses its frontier by, None for a strategy that samples or
    has a rule of its own: a rule's own name, or the rule a perfect-value yardstick runs."""
    rule = PERFECT_VALUE_RULE.get(strategy, strategy)
    return rule if rule in RULES else None


def frontier_value(f: Frontier) -> float:
    """``v_p = ln max(1, (SV_p + SV_p,normal) / 2)`` (module doc); 0 for a non-finite value."""
    mean = 0.5 * (float(f.sv) + float(f.sv_normal))
    if not math.isfinite(mean) or mean <= 1.0:
        return 0.0
    return math.log(mean)


@dataclass(frozen=True)
class RuleParams:
    """The knobs of the rules (``PlannerParams`` holds them; see its comments for how they were chosen)."""

    cost_per_m: float
    commit_margin: float
    gain_weight: float
    gain_radius_m: float
    topo_core_m: float
    topo_hop_cost: float


def unknown_share(frontiers: list[Frontier], grid: GridSpec, explored: np.ndarray, occupied: np.ndarray,
                  radius_m: float) -> np.ndarray:
    """Per frontier: the share of the disk of ``radius_m`` around it whose cells are unknown (neither explored
    nor occupied; cells beyond the map count as unknown)."""
    out = np.zeros(len(frontiers))
    if not frontiers or radius_m <= 0:
        return out
    r = max(1, math.ceil(radius_m / grid.resolution))
    unknown = np.pad(~explored.astype(bool) & ~occupied.astype(bool), r, constant_values=True)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = (yy * yy + xx * xx) * grid.resolution**2 <= radius_m * radius_m
    area = float(disk.sum())
    origin = gridm.origin_of(grid)
    for n, f in enumerate(frontiers):
        i, j = gridm.cell_of_point(f.x, f.y, origin, grid.resolution)
        i = min(max(int(i), 0), grid.rows - 1) + r
        j = min(max(int(j), 0), grid.cols - 1) + r
        out[n] = float(unknown[i - r : i + r + 1, j - r : j + r + 1][disk].sum()) / area
    return out


def regions(free: np.ndarray, resolution: float, core_m: float) -> tuple[np.ndarray, int]:
    """Rooms of the free space: labels (0 = no room) and their count. Cores are the 8-connected parts of the
    free cells farther than ``core_m`` from any non-free cell (a doorway is narrower than ``2 core_m``, so it
    separates two cores); every other free cell joins the core it is grown into first, one cell per pass
    (ties: the larger label, deterministic)."""
    free = free.astype(bool)
    dist = ndimage.distance_transform_edt(np.pad(free, 1, constant_values=False))[1:-1, 1:-1] * resolution
    labels, n = ndimage.label(free & (dist > core_m), structure=_EIGHT)
    if n == 0:
        return labels, 0
    for _ in range(free.shape[0] + free.shape[1]):
        grown = ndimage.grey_dilation(labels, footprint=_EIGHT)
        todo = free & (labels == 0) & (grown > 0)
        if not todo.any():
            break
        labels[todo] = grown[todo]
    return labels, int(n)


def region_hops(labels: np.ndarray, n: int, start: int) -> np.ndarray:
    """Doorways (graph hops) from room ``start`` to every room (index = label; -1: not connected / no room);
    rooms are linked where a cell of one touches (4-neighbourhood) a cell of the other."""
    hops = np.full(n + 1, -1, dtype=np.int64)
    if start <= 0 or start > n:
        return hops
    adj: list[set[int]] = [set() for _ in range(n + 1)]
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1, :], labels[1:, :])):
        touch = (a != b) & (a > 0) & (b > 0)
        for u, v in set(zip(a[touch].tolist(), b[touch].tolist(), strict=True)):
            adj[u].add(v)
            adj[v].add(u)
    hops[start] = 0
    queue = deque([start])
    while queue:
        u = queue.popleft()
        for v in sorted(adj[u]):
            if hops[v] < 0:
                hops[v] = hops[u] + 1
                queue.append(v)
    return hops


def room_of(labels: np.ndarray, grid: GridSpec, x: float, y: float) -> int:
    """The room label at ``(x, y)``, else of the nearest labelled cell within 1 m, else 0."""
    i, j = gridm.cell_of_point(x, y, gridm.origin_of(grid), grid.resolution)
    i, j = int(i), int(j)
    if not (0 <= i < grid.rows and 0 <= j < grid.cols):
        return 0
    if labels[i, j] > 0:
        return int(labels[i, j])
    r = max(1, math.ceil(1.0 / grid.resolution))
    i0, j0 = max(0, i - r), max(0, j - r)
    win = labels[i0 : i + r + 1, j0 : j + r + 1]
    ii, jj = np.nonzero(win > 0)
    if ii.size == 0:
        return 0
    k = int(np.argmin((ii + i0 - i) ** 2 + (jj + j0 - j) ** 2))
    return int(win[ii[k], jj[k]])


def doorways(frontiers: list[Frontier], grid: GridSpec, free: np.ndarray, robot_xy: tuple[float, float],
             core_m: float) -> np.ndarray:
    """Per frontier: doorways between the robot's room and the frontier's (0 when either has no room or the
    two are not connected on the explored map: nothing is known of the way there)."""
    labels, n = regions(free, grid.resolution, core_m)
    out = np.zeros(len(frontiers))
    if n == 0:
        return out
    hops = region_hops(labels, n, room_of(labels, grid, *robot_xy))
    for k, f in enumerate(frontiers):
        h = int(hops[room_of(labels, grid, f.x, f.y)])
        out[k] = max(h, 0)
    return out


def scores(strategy: str, frontiers: list[Frontier], candidates: np.ndarray, geodesic_m: np.ndarray,
           grid: GridSpec, free: np.ndarray, occupied: np.ndarray, explored: np.ndarray | None,
           robot_xy: tuple[float, float], p: RuleParams) -> tuple[np.ndarray, np.ndarray]:
    """(score per frontier, -inf for non-candidates; value ``v_p`` per frontier) of a rule (module doc);
    ``strategy``: a rule or a yardstick that runs one (:func:`rule_of`)."""
    rule = rule_of(strategy)
    if rule is None:
        raise ValueError(f"{strategy!r} is not a frontier rule ({', '.join(sorted(RULES))})")
    v = np.array([frontier_value(f) for f in frontiers], dtype=np.float64)
    d = np.asarray(geodesic_m, dtype=np.float64)
    s = v - p.cost_per_m * np.where(np.isfinite(d), d, 0.0)
    if rule == "gain":
        # without the explored plane (a map from before the planner read it) free space is the explored part
        seen = explored if explored is not None else free
        s = s + p.gain_weight * unknown_share(frontiers, grid, seen, occupied, p.gain_radius_m)
    elif rule == "topo":
        s = s - p.topo_hop_cost * doorways(frontiers, grid, free, robot_xy, p.topo_core_m)
    ok = np.asarray(candidates, dtype=bool) & np.isfinite(d) & np.isfinite(s)
    return np.where(ok, s, -np.inf), v


def best(score: np.ndarray, geodesic_m: np.ndarray) -> int | None:
    """Index of the highest score; ties (within 1e-9) to the shorter geodesic distance, then the lower index."""
    if score.size == 0 or not np.isfinite(score.max()):
        return None
    tied = np.flatnonzero(score >= score.max() - 1e-9)
    d = np.asarray(geodesic_m, dtype=np.float64)[tied]
    return int(tied[int(np.argmin(d))])


def choose(strategy: str, frontiers: list[Frontier], candidates: np.ndarray, geodesic_m: np.ndarray,
           grid: GridSpec, free: np.ndarray, occupied: np.ndarray, explored: np.ndarray | None,
           robot_xy: tuple[float, float], p: RuleParams, committed: Frontier | None,
           commit_radius_m: float) -> tuple[int | None, np.ndarray, str, bool]:
    """The rule's frontier: (index or None without a candidate, one-hot probabilities, a note, whether it is a
    new choice rather than the kept commitment). ``committed``: the target chosen earlier, None for none."""
    score, v = scores(strategy, frontiers, candidates, geodesic_m, grid, free, occupied, explored, robot_xy, p)
    probs = np.zeros(len(frontiers))
    i = best(score, geodesic_m)
    if i is None:
        return None, probs, "no candidate frontier", True
    if committed is not None:
        near = np.array([math.hypot(f.x - committed.x, f.y - committed.y) if np.isfinite(score[k]) else np.inf
                         for k, f in enumerate(frontiers)])
        k = int(np.argmin(near))
        kept_value = v[k] >= frontier_value(committed) - p.commit_margin
        if near[k] <= commit_radius_m and kept_value and score[k] >= score[i] - p.commit_margin:
            probs[k] = 1.0
            return k, probs, (f"{strategy}: kept the committed target (score {score[k]:.3f}, "
                              f"best {score[i]:.3f})"), False
    probs[i] = 1.0
    return i, probs, (f"{strategy}: highest score {score[i]:.3f} (value {v[i]:.3f}, "
                      f"{float(geodesic_m[i]):.1f} m)"), True
