"""Semantic value map (Explore-EQA section IV-C, Eq. 3; HELIOS section 3.1.2: one layer per search target).

Each prompt point ``p`` gets ``SV_p = exp(tau_LSV * LSV_p + tau_GSV * GSV_p)`` (Eq. 3). "We apply Gaussian
smoothing such that each value creates a Gaussian distribution around the point": a step writes
``S_t(x) = max_p SV_p * exp(-|x - p|^2 / (2 sigma^2))`` (cut at 3 sigma).

Fusion over steps: per-cell maximum, ``V_t = max(V_{t-1}, S_t)``. A region once judged worth exploring
keeps its value until it is explored (frontiers there disappear), overlapping Gaussians of one or several
steps do not pile up into values no single observation supported, and the result does not depend on the
order in which the robot happened to look at a region. Never-scored cells hold 0, below every written value
(``SV >= 1`` whenever the temperatures are non-negative).

Strategies (``EpisodeStart.strategy``): ``semantic`` uses both terms, ``no_lsv`` treats ``tau_LSV`` as 0,
``no_gsv`` treats ``tau_GSV`` as 0, ``fbe`` / ``nearest`` write nothing (every frontier weighs 1); ``vlfm``,
``gain`` and ``topo`` use both terms (the planner ranks the frontiers by value instead of sampling Eq. A6).
The perfect-value yardsticks (benchmark-only; ``perfect_sv`` for Eq. A6, ``perfect_vlfm`` / ``perfect_gain`` for
those rules: :data:`eqa.messages.PERFECT_VALUE_RULE`) use both terms with LSV / GSV from the ground truth
(:func:`ground_truth_scores`) instead of the scorer's.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from eqa import grid
from eqa.messages import PERFECT_VALUE_RULE

# vlfm / gain / topo (services/planner/frontier_rules.py) read the same values as semantic, by other rules
SEMANTIC_STRATEGIES = ("semantic", "no_lsv", "no_gsv", "cp_guided", "vlfm", "gain", "topo", *PERFECT_VALUE_RULE)
QUESTION_LAYER = "question"


def temperatures(strategy: str, tau_lsv: float, tau_gsv: float) -> tuple[float, float] | None:
    """(tau_LSV, tau_GSV) of a strategy, or None when the strategy uses no semantic values."""
    strategy = PERFECT_VALUE_RULE.get(strategy, strategy)  # a perfect-value yardstick: its rule's temperatures
    if strategy in ("semantic", "cp_guided", "vlfm", "gain", "topo"):  # cp_guided: the planner re-tempers
        return tau_lsv, tau_gsv
    if strategy == "no_lsv":
        return 0.0, tau_gsv
    if strategy == "no_gsv":
        return tau_lsv, 0.0
    return None


GT_LSV_SCALE_M = 1.0  # perfect LSV: softmax of -distance / 1 m over the prompt points


def ground_truth_scores(
    points: list[tuple[float, float]], targets: list[tuple[float, float]], camera_xy: tuple[float, float]
) -> tuple[list[float], float]:
    """LSV (Eq. 1) and GSV (Eq. 2) a perfect model would give, from the ground-truth target positions (the
    perfect-value yardsticks, upper bounds, never product behaviour): LSV is the softmax over the prompt
    points of ``-d_p / 1 m`` (``d_p``: straight-line distance from point ``p`` to the nearest target), so the
    point nearest a target takes most of the mass; GSV = 1 when some prompt point is nearer a target than the
    camera ("a direction worth exploring is in view"), else 0."""
    if not points:
        return [], 0.0
    if not targets:
        return [1.0 / len(points)] * len(points), 0.0
    t = np.asarray(targets, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    d = np.sqrt(((p[:, None, :] - t[None, :, :]) ** 2).sum(-1)).min(axis=1)
    z = -d / GT_LSV_SCALE_M
    e = np.exp(z - z.max())
    cam = float(np.sqrt(((t - np.asarray(camera_xy, dtype=np.float64)) ** 2).sum(-1)).min())
    return (e / e.sum()).tolist(), 1.0 if float(d.min()) < cam else 0.0


def semantic_value(lsv: float, gsv: float, tau_lsv: float, tau_gsv: float) -> float:
    """Eq. 3: ``SV_p = exp(tau_LSV * LSV_p + tau_GSV * GSV_p)``."""
    return float(math.exp(tau_lsv * lsv + tau_gsv * gsv))


def write_values(
    layer: np.ndarray,
    origin: tuple[float, float],
    resolution: float,
    points: list[tuple[float, float]],
    values: list[float],
    sigma: float = 1.0,
) -> None:
    """Max-fuse one Gaussian per point (peak ``value`` at the point, std ``sigma`` metres) into ``layer``
    in place."""
    for (_, _, value), (r0, r1, c0, c1), g in _gaussian_windows(layer.shape, origin, resolution, points, values,
                                                                 sigma):
        win = layer[r0:r1, c0:c1]
        np.maximum(win, (value * g).astype(layer.dtype), out=win)


def _gaussian_windows(
    shape: tuple[int, ...],
    origin: tuple[float, float],
    resolution: float,
    points: list[tuple[float, float]],
    values: list[float],
    sigma: float,
) -> Iterator[tuple[tuple[float, float, float], tuple[int, int, int, int], np.ndarray]]:
    """Per point inside the grid: ``((x, y, value), (r0, r1, c0, c1), g)`` with ``g`` the unit Gaussian (std
    ``sigma`` metres, cut at 3 sigma) over the window ``[r0:r1, c0:c1]`` of a ``shape`` grid."""
    ny, nx = shape[:2]
    radius = math.ceil(3 * sigma / resolution)
    for (x, y), value in zip(points, values, strict=True):
        r, c = grid.cell_of_point(x, y, origin, resolution)
        r0, r1 = max(r - radius, 0), min(r + radius + 1, ny)
        c0, c1 = max(c - radius, 0), min(c + radius + 1, nx)
        if r0 >= r1 or c0 >= c1:
            continue
        xs, ys = grid.cell_center(np.arange(r0, r1), np.arange(c0, c1), origin, resolution)
        d2 = (ys[:, None] - y) ** 2 + (xs[None, :] - x) ** 2
        g = np.exp(-d2 / (2 * sigma * sigma))
        g[d2 > (3 * sigma) ** 2] = 0
        yield (x, y, value), (r0, r1, c0, c1), g


# ---- view orientation (Explore-EQA appendix C, "Improving semantic exploration by considering view orientation";
# item 3) ----------------------------------------------------------------------------------------------
#
# With ``view_bins = B > 0`` a value layer ``V`` keeps, next to itself, the best value per viewing-direction bin
# ``V_b(x) = max over the steps that judged x from direction bin b of S_t(x)`` (b: the bin of the bearing from
# the camera to the prompt point whose Gaussian covers x, B equal sectors of 2 pi starting at +x: the direction
# the VLM looked at that region from) and the *neutral* value ``N(x)``: the Gaussian
# of ``SV_neutral = exp(tau_LSV / |P| + tau_GSV * GSV)`` (Eq. 3 with the uniform LSV 1/|P|, a view that prefers
# no prompt point) around the same points, max-fused. LSV is a softmax over the points of one view, so a point
# below 1/|P| was judged *worse than the rest of that view*: what a view from a poor angle (the sofa seen from
# behind) says. What the consumers (Eq. A6 frontier weights, the map update) read is the combined value
#
#     V(x) = max_b V_b(x)                      where at least ``agree`` bins have seen x  (explained)
#     V(x) = max(max_b V_b(x), N(x))           where fewer have                           (not explained yet)
#
# so a value below neutral is believed only once ``agree`` directions agree on it (every seen bin is below N
# then, else the max would be above it); a value above neutral is kept as without bins (max over bins = the
# max over all steps). ``agree = 1`` gives exactly the layer without bins. Memory: (B + 1) extra float32
# planes per value layer, B <= MAX_VIEW_BINS.

MAX_VIEW_BINS = 16


def view_plane_names(layer: str, bins: int) -> list[str]:
    """Names of the volume planes of a layer's direction bins, then its neutral plane (empty when bins = 0)."""
    if bins <= 0:
        return []
    return [f"value/{layer}/view{b}" for b in range(bins)] + [f"value/{layer}/neutral"]


def neutral_value(n_points: int, gsv: float, tau_lsv: float, tau_gsv: float) -> float:
    """Eq. 3 at the uniform LSV ``1 / |P|``: the value of a prompt point the model prefers to none other."""
    return semantic_value(1.0 / max(n_points, 1), gsv, tau_lsv, tau_gsv)


def view_bin(dx: np.ndarray, dy: np.ndarray, bins: int) -> np.ndarray:
    """Direction bin (0 .. bins - 1) of the bearing ``atan2(dy, dx)`` from the camera to a cell."""
    a = np.mod(np.arctan2(dy, dx), 2 * math.pi)
    return np.minimum((a * (bins / (2 * math.pi))).astype(np.int64), bins - 1)


def write_values_binned(
    bin_layers: list[np.ndarray],
    neutral_layer: np.ndarray,
    origin: tuple[float, float],
    resolution: float,
    points: list[tuple[float, float]],
    values: list[float],
    neutral: float,
    camera_xy: tuple[float, float],
    sigma: float = 1.0,
) -> None:
    """:func:`write_values` per direction bin: a point's Gaussian goes into the bin of the point's bearing from
    ``camera_xy`` only; the neutral value's Gaussian (same points, same sigma) into ``neutral_layer``."""
    bins = len(bin_layers)
    for (x, y, value), (r0, r1, c0, c1), g in _gaussian_windows(neutral_layer.shape, origin, resolution, points,
                                                                 values, sigma):
        b = int(view_bin(np.array([x - camera_xy[0]]), np.array([y - camera_xy[1]]), bins)[0])
        win = bin_layers[b][r0:r1, c0:c1]
        np.maximum(win, (value * g).astype(win.dtype), out=win)
        win = neutral_layer[r0:r1, c0:c1]
        np.maximum(win, (neutral * g).astype(win.dtype), out=win)


def combine_view_bins(bin_layers: list[np.ndarray], neutral_layer: np.ndarray, agree: int) -> np.ndarray:
    """The combined value (see above): ``max_b V_b`` where at least ``agree`` bins saw the cell, else
    ``max(max_b V_b, N)``."""
    stack = np.stack(bin_layers)
    best = stack.max(axis=0)
    seen = (stack > 0).sum(axis=0)
    return np.where(seen >= min(agree, len(bin_layers)), best, np.maximum(best, neutral_layer)).astype(
        neutral_layer.dtype
    )
