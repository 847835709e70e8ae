"""Choosing the next frontier (Explore-EQA section IV-D and appendix B).

* ``semantic``, ``no_lsv``, ``no_gsv``: sample a frontier with probability proportional to its weight
  ``w_p = exp(tau_SV SV_p + tau_SV,Normal SV_p,normal)`` (Eq. A6). The mapper computes ``Frontier.weight``
  for the episode's strategy (without LSV / GSV for the ablations); this module only samples.
* ``fbe``: frontier-based exploration without semantic value: uniform over the reachable frontiers.
* ``nearest``: deterministic, the reachable frontier with the shortest geodesic distance.
* ``perfect_sv`` (benchmark-only yardstick, an upper bound): sampled by Eq. A6 like ``semantic``, but the
  mapper wrote LSV / GSV computed from the ground-truth target positions instead of the scorer's.
* ``target_oracle`` (benchmark-only yardstick, an upper bound): deterministic, the reachable frontier on the
  shortest way to a ground-truth target: geodesic distance robot -> frontier on the robot's map plus the
  frontier's distance ``d`` to the nearest target, which the mapper walks through the true house when the
  benchmark gave it the house's paths (:class:`eqa.messages.TargetPaths`) and encodes as the weight
  ``1 / (1 + d)``; ties go to the shorter geodesic distance.

The sampled strategies multiply the probabilities by a distance decay ``exp(-d / decay_m)`` of the geodesic
distance (:func:`distance_decay`), the same for all of them, so with equal semantic values ``semantic``
still samples like ``fbe``.

Sampling is seeded per (episode seed, step, attempt), so a run is reproducible and a retry after a refused
goal draws again.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from eqa.messages import Strategy

# cp_guided (services/planner/cp_guided.py): Eq. A6 weights re-tempered by the CP prediction set
WEIGHTED: frozenset[str] = frozenset({"semantic", "no_lsv", "no_gsv", "perfect_sv", "cp_guided"})


def step_rng(seed: int, step: int, attempt: int = 0) -> np.random.Generator:
    """The random generator of one planning attempt: a pure function of (seed, step, attempt)."""
    return np.random.default_rng([int(seed) % (2**63), int(step), int(attempt)])


def valid_weights(weights: Sequence[float]) -> np.ndarray:
    """Mask of weights usable for sampling: finite and non-negative."""
    w = np.asarray(weights, dtype=np.float64)
    return np.isfinite(w) & (w >= 0.0)


def probabilities(strategy: Strategy, weights: Sequence[float], candidates: Sequence[bool]) -> tuple[np.ndarray, str]:
    """Sampling probabilities over all frontiers (0 for non-candidates) and a note on what was done.

    ``fbe`` gives equal probability to every candidate. The weighted strategies use Eq. A6 weights; a
    candidate whose weight is NaN, infinite or negative gets probability 0; when no candidate has a usable
    weight (or they sum to 0) the candidates are sampled uniformly and the note says so."""
    cand = np.asarray(candidates, dtype=bool)
    n = cand.size
    p = np.zeros(n)
    if not cand.any():
        return p, "no candidate frontier"
    if strategy in WEIGHTED:
        w = np.asarray(weights, dtype=np.float64)
        ok = valid_weights(w) & cand
        bad = int((cand & ~valid_weights(w)).sum())
        with np.errstate(over="ignore"):
            total = float(w[ok].sum()) if ok.any() else 0.0
        if ok.any() and math.isfinite(total) and total > 0.0:
            p[ok] = w[ok] / total
            note = f"{strategy}: weighted by Eq. A6"
            if bad:
                note += f" ({bad} frontier(s) with invalid weight ignored)"
            return p, note
        if ok.any() and not math.isfinite(total):  # finite weights whose sum overflows: scale first
            ws = w[ok] / w[ok].max()
            p[ok] = ws / ws.sum()
            return p, f"{strategy}: weighted by Eq. A6 (rescaled)"
        p[cand] = 1.0 / cand.sum()
        return p, f"{strategy}: no usable weight ({bad} invalid), sampled uniformly"
    p[cand] = 1.0 / cand.sum()
    return p, f"{strategy}: uniform over reachable frontiers"


def distance_decay(probs: np.ndarray, geodesic_m: Sequence[float], decay_m: float | None) -> np.ndarray:
    """Multiply sampling probabilities by ``exp(-d / decay_m)`` of each frontier's geodesic distance ``d`` and
    renormalise (the reference implementation's distance factor of the frontier weight, its ``dist_T``):
    without it, uniform sampling sends the robot back and forth across the house. ``None`` or 0: off."""
    if not decay_m or not probs.any():
        return probs
    d = np.asarray(geodesic_m, dtype=np.float64)
    d = np.where(np.isfinite(d), d, np.inf)
    q = probs * np.exp(-(d - d[probs > 0].min()) / decay_m)
    total = float(q.sum())
    return q / total if total > 0 and math.isfinite(total) else probs


def choose(
    strategy: Strategy,
    weights: Sequence[float],
    candidates: Sequence[bool],
    geodesic_m: Sequence[float],
    rng: np.random.Generator,
    decay_m: float | None = None,
) -> tuple[int | None, np.ndarray, str]:
    """Index of the chosen frontier (None when there is no candidate), the probabilities, and a note.
    ``decay_m``: :func:`distance_decay` for the sampled strategies."""
    cand = np.asarray(candidates, dtype=bool)
    if strategy == "target_oracle":
        p = np.zeros(cand.size)
        if not cand.any():
            return None, p, "no candidate frontier"
        w = np.asarray(weights, dtype=np.float64)
        ok = cand & valid_weights(w) & (w > 0)
        d = np.asarray(geodesic_m, dtype=np.float64)
        with np.errstate(divide="ignore"):
            to_target = np.where(ok, 1.0 / np.where(ok, w, 1.0) - 1.0, np.inf)
        total = np.where(cand, d + to_target, np.inf)
        best = np.flatnonzero(total == total.min()) if np.isfinite(total.min()) else np.flatnonzero(cand)
        i = int(best[np.argmin(d[best])])
        p[i] = 1.0
        return i, p, (f"target_oracle (bound, ground truth): shortest way to the target, {d[i]:.1f} m to the "
                      f"frontier + {to_target[i]:.1f} m on")
    if strategy == "nearest":
        p = np.zeros(cand.size)
        if not cand.any():
            return None, p, "no candidate frontier"
        d = np.where(cand, np.asarray(geodesic_m, dtype=np.float64), np.inf)
        i = int(np.argmin(d))
        p[i] = 1.0
        return i, p, f"nearest reachable frontier ({d[i]:.1f} m)"
    p, note = probabilities(strategy, weights, cand)
    if not cand.any():
        return None, p, note
    if decay_m:
        p = distance_decay(p, geodesic_m, decay_m)
        note += f", distance decay {decay_m:g} m"
    i = int(rng.choice(p.size, p=p / p.sum()))
    return i, p, note
