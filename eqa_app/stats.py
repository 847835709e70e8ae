"""The statistics every benchmark and evaluation prints, on scipy (one home; tests/kernel/test_stats.py checks
them against scipy and known values).

* :func:`wilson_ci` — Wilson score interval of a success rate (``scipy.stats.binomtest(...).proportion_ci``).
* :func:`sign_test_p` — exact two-sided sign test over the discordant pairs (``binomtest(k, n, 0.5)``);
  :func:`sign_test_of` the same over the signs of paired differences (zeros dropped).
* :func:`paired_diff_ci` — difference of two paired success rates with the Wald interval for matched pairs.
* :func:`bootstrap_ci` / :func:`bootstrap_mean_ci` — percentile bootstrap intervals of paired items
  (``scipy.stats.bootstrap``, resampling whole items so paired samples stay paired), seeded.
* :func:`percentile` — a latency percentile, linearly interpolated between order statistics (numpy's default).
* :func:`paired_outcomes` — two rules or strategies on the same episodes: success rates and their difference
  (bootstrap interval, exact sign test), normalised steps and theirs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
Z95 = float(stats.norm.ppf(0.5 + CONFIDENCE / 2))  # 1.95996...: the normal quantile of a 95 % interval
N_BOOT = 2000


def wilson_ci(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of a success rate ``k / n`` ((nan, nan) for ``n = 0``)."""
    if n == 0:
        return math.nan, math.nan
    ci = stats.binomtest(int(k), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def sign_test_p(a_only: int, b_only: int) -> float:
    """Exact two-sided sign test: P(a split at least this uneven | each discordant pair a fair coin); 1 without
    discordant pairs."""
    n = int(a_only) + int(b_only)
    if n == 0:
        return 1.0
    return float(stats.binomtest(int(a_only), n, 0.5).pvalue)


def sign_test_of(differences: Sequence[float] | np.ndarray) -> float:
    """:func:`sign_test_p` over the signs of paired differences ``a - b`` (ties, zeros, are dropped)."""
    d = np.asarray(differences, dtype=np.float64)
    return sign_test_p(int((d > 0).sum()), int((d < 0).sum()))


def paired_diff_ci(a_only: int, b_only: int, n: int, z: float = Z95) -> tuple[float, float, float]:
    """Difference of two paired success rates, (a_only - b_only) / n, and its 95 % Wald interval for matched
    pairs (se = sqrt(a_only + b_only - (a_only - b_only)^2 / n) / n)."""
    if n == 0:
        return math.nan, math.nan, math.nan
    d = (a_only - b_only) / n
    se = math.sqrt(max(a_only + b_only - (a_only - b_only) ** 2 / n, 0.0)) / n
    return d, d - z * se, d + z * se


def bootstrap_ci(statistic: Callable[..., Any], samples: Sequence[np.ndarray], n_boot: int = N_BOOT, seed: int = 0,
                 confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic(*samples, axis=-1)`` (vectorised over resamples), the items
    of the equally long ``samples`` resampled together (paired) from the generator of ``seed``;
    (nan, nan) without items, the statistic itself for one item."""
    arrays = [np.asarray(s, dtype=np.float64) for s in samples]
    n = arrays[0].size
    if any(a.shape != (n,) for a in arrays):
        raise ValueError(f"bootstrap samples must be 1-D and equally long, got {[a.shape for a in arrays]}")
    if n == 0:
        return math.nan, math.nan
    if n == 1:
        v = float(statistic(*arrays, axis=-1))
        return v, v
    res = stats.bootstrap(tuple(arrays), statistic, n_resamples=n_boot, confidence_level=confidence,
                          method="percentile", paired=True, vectorized=True, rng=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def _mean(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(x, axis=axis)


def bootstrap_mean_ci(values: Sequence[float] | np.ndarray, n_boot: int = N_BOOT, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap 95 % interval of the mean of ``values`` (e.g. per-item paired differences)."""
    return bootstrap_ci(_mean, [np.asarray(values, dtype=np.float64)], n_boot, seed)


def percentile(values: Sequence[float] | np.ndarray, q: float) -> float:
    """The ``q``-th percentile (0..100) of ``values``, linearly interpolated; nan for no values."""
    v = np.asarray(values, dtype=np.float64)
    return float(np.percentile(v, q)) if v.size else math.nan


class Outcome(Protocol):
    """One episode's result under one rule: answered right or not, normalised steps used."""

    @property
    def correct(self) -> bool: ...

    @property
    def norm_steps(self) -> float: ...


def paired_outcomes(a: Sequence[Outcome], b: Sequence[Outcome], seed: int = 0,
                    n_boot: int = N_BOOT) -> dict[str, float]:
    """``a`` against ``b`` on the same episodes (item ``i`` of each is one episode): success rates, their
    difference ``a - b`` with a paired bootstrap interval and the exact sign test over the episodes only one
    gets right; mean normalised steps, their difference with its bootstrap interval and the sign test of the
    per-episode step differences. Both bootstraps draw the same resamples (one seed)."""
    if len(a) != len(b):
        raise ValueError(f"paired outcomes need the same episodes, got {len(a)} and {len(b)}")
    ca = np.array([x.correct for x in a], dtype=np.float64)
    cb = np.array([x.correct for x in b], dtype=np.float64)
    sa = np.array([x.norm_steps for x in a], dtype=np.float64)
    sb = np.array([x.norm_steps for x in b], dtype=np.float64)
    d, ds = ca - cb, sa - sb
    lo, hi = bootstrap_mean_ci(d, n_boot, seed)
    s_lo, s_hi = bootstrap_mean_ci(ds, n_boot, seed)
    a_only, b_only = int(((ca == 1) & (cb == 0)).sum()), int(((cb == 1) & (ca == 0)).sum())
    nan = math.nan
    return {"n": int(ca.size), "success_a": float(ca.mean()) if ca.size else nan,
            "success_b": float(cb.mean()) if cb.size else nan, "diff": float(d.mean()) if d.size else nan,
            "ci_low": lo, "ci_high": hi, "a_only": a_only, "b_only": b_only, "p": sign_test_p(a_only, b_only),
            "steps_a": float(sa.mean()) if sa.size else nan, "steps_b": float(sb.mean()) if sb.size else nan,
            "steps_diff": float(ds.mean()) if ds.size else nan, "steps_ci_low": s_lo, "steps_ci_high": s_hi,
            "steps_sign_p": sign_test_of(ds)}
