"""The benchmarks' statistics (eqa_app/stats.py) against scipy, known values, and the closed forms the published
figures were computed with (so a figure recomputed from the same data prints the same digits)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from scipy import stats as sps

from eqa_app import stats


def test_wilson_is_scipys_and_the_closed_form() -> None:
    for k, n in ((0, 7), (5, 10), (7, 7), (57, 200), (1, 1)):
        ci = sps.binomtest(k, n).proportion_ci(0.95, method="wilson")
        z, p = 1.959963984540054, k / n
        den, mid = 1 + z * z / n, (p + z * z / (2 * n)) / (1 + z * z / n)
        half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
        got = stats.wilson_ci(k, n)
        assert got == pytest.approx((ci.low, ci.high), abs=1e-12)
        assert got == pytest.approx((max(0.0, mid - half), min(1.0, mid + half)), abs=1e-12)
    assert stats.wilson_ci(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert stats.wilson_ci(7, 7)[1] == 1.0 and all(math.isnan(v) for v in stats.wilson_ci(0, 0))


def test_exact_sign_test() -> None:
    assert stats.sign_test_p(0, 0) == 1.0 and stats.sign_test_p(3, 3) == 1.0
    assert stats.sign_test_p(5, 0) == pytest.approx(2 / 32)  # 5 heads of 5 fair coins, both tails
    assert stats.sign_test_p(1, 9) == pytest.approx(2 * (math.comb(10, 0) + math.comb(10, 1)) / 1024)
    assert stats.sign_test_p(13, 4) == pytest.approx(sps.binomtest(13, 17, 0.5).pvalue)
    assert stats.sign_test_of([0.1, 0.0, -0.2, 0.3, 0.4, 0.0]) == stats.sign_test_p(3, 1)
    assert pytest.approx(sps.norm.ppf(0.975), abs=1e-15) == stats.Z95


def test_paired_diff_wald_interval() -> None:
    d, lo, hi = stats.paired_diff_ci(10, 2, 100)
    se = math.sqrt(12 - 64 / 100) / 100
    assert (d, lo, hi) == pytest.approx((0.08, 0.08 - stats.Z95 * se, 0.08 + stats.Z95 * se))
    assert stats.paired_diff_ci(3, 3, 50)[0] == 0.0 and all(math.isnan(v) for v in stats.paired_diff_ci(0, 0, 0))


def test_bootstrap_is_scipys_and_resamples_as_the_published_figures_did() -> None:
    rng = np.random.default_rng(3)
    v, w = rng.normal(size=57), rng.normal(size=57)
    # the resampling the published figures used: one index matrix from the seed's generator, percentile CI
    idx = np.random.default_rng(0).integers(0, 57, size=(2000, 57))
    m = (v - w)[idx].mean(axis=1)
    assert stats.bootstrap_mean_ci(v - w) == pytest.approx((np.quantile(m, 0.025), np.quantile(m, 0.975)), abs=1e-12)
    ref = sps.bootstrap((v - w,), np.mean, n_resamples=2000, method="percentile", rng=np.random.default_rng(0))
    assert stats.bootstrap_mean_ci(v - w) == pytest.approx(tuple(ref.confidence_interval), abs=1e-12)
    ratio = v[idx].sum(axis=1) / w[idx].sum(axis=1)  # a statistic of two paired samples, resampled together
    got = stats.bootstrap_ci(lambda a, b, axis=-1: a.sum(axis=axis) / b.sum(axis=axis), [v, w])
    assert got == pytest.approx((np.quantile(ratio, 0.025), np.quantile(ratio, 0.975)), abs=1e-12)
    assert stats.bootstrap_mean_ci(np.full(20, 0.25)) == (0.25, 0.25)
    d = np.r_[np.ones(10), -np.ones(10)]  # no difference on average: the interval straddles 0
    lo, hi = stats.bootstrap_mean_ci(d, 500, seed=3)
    assert lo < 0 < hi and lo == pytest.approx(-hi, abs=0.1)
    assert all(math.isnan(x) for x in stats.bootstrap_mean_ci([])) and stats.bootstrap_mean_ci([0.5]) == (0.5, 0.5)
    with pytest.raises(ValueError):
        stats.bootstrap_ci(lambda a, b, axis=-1: a.mean(axis=axis), [v, w[:5]])


def test_percentile_interpolates_linearly() -> None:
    assert stats.percentile([1, 2, 3, 4], 50) == 2.5  # nearest-rank would give 2 or 3
    assert stats.percentile([10.0, 20.0, 30.0], 95) == pytest.approx(29.0)
    x = np.random.default_rng(1).exponential(size=101)
    assert stats.percentile(x, 95) == np.percentile(x, 95) and math.isnan(stats.percentile([], 50))


@dataclass(frozen=True)
class _Out:
    correct: bool
    norm_steps: float


def test_paired_outcomes_sees_a_real_difference_and_not_a_fake_one() -> None:
    a = [_Out(True, 0.5)] * 25 + [_Out(False, 0.5)] * 5
    b = [_Out(False, 0.7)] * 15 + [_Out(True, 0.7)] * 15
    r = stats.paired_outcomes(a, b)
    assert r["n"] == 30 and (r["a_only"], r["b_only"]) == (15, 5) and r["p"] == stats.sign_test_p(15, 5)
    assert r["diff"] == pytest.approx(1 / 3) and r["ci_low"] > 0 and r["steps_diff"] == pytest.approx(-0.2)
    assert r["steps_ci_high"] < 0 and r["steps_sign_p"] < 1e-6
    same = stats.paired_outcomes(a, a)
    assert same["diff"] == 0 and same["p"] == 1.0 and same["steps_sign_p"] == 1.0
    with pytest.raises(ValueError):
        stats.paired_outcomes(a, b[:3])
