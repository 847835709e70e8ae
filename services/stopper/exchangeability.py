"""Is a calibration table still valid for the model that scores today? (beyond the paper.)

The coverage guarantee of conformal prediction (Explore-EQA Eq. 6, Prop. 1) assumes that a new episode's
non-conformity score ``kappa = 1 - min_t rho_y^t`` is exchangeable with the ``N`` calibration scores. That
fails silently when the scorer changes (a user points it at another model, a new prompt, other houses). Given
new *labelled, full-length* episodes, this module tests it two ways (pure, numpy/scipy):

* **rank test**: the Mann-Whitney U test of the new scores against the table's (two-sided): under
  exchangeability every ranking of the pooled scores is equally likely;
* **coverage test**: for each eps of the table, how many new episodes the sequence-level set would cover
  (``kappa <= q_hat``); CP promises at least ``1 - eps`` (in expectation over calibration sets), so a one-sided
  exact binomial test flags a shortfall.

The table is called *stale* when either test rejects at ``alpha`` (the coverage test after a Bonferroni
correction over the eps checked). A stale table is not proof of a bug; it means the guarantee printed beside
every CP decision is no longer backed by data: recalibrate on episodes of the current model
(``eqa calibrate --from-store`` after labelling, or ``eqa calibrate`` on the benchmark).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from services.stopper.calibration import CalibrationTable

CHECK_EPS: tuple[float, ...] = (0.1, 0.2, 0.3)
MIN_NEW = 5  # below this the tests have no power: say so instead of "fresh"


@dataclass
class CoverageCheck:
    eps: float
    q_hat: float
    covered: int
    n: int
    p_value: float  # one-sided: P(coverage this low | true coverage 1 - eps)

    @property
    def coverage(self) -> float:
        return self.covered / self.n if self.n else math.nan


@dataclass
class StalenessReport:
    n_table: int
    n_new: int
    rank_p: float
    median_table: float
    median_new: float
    coverage: list[CoverageCheck] = field(default_factory=list)
    alpha: float = 0.05
    stale: bool = False
    enough: bool = True
    message: str = ""


def check_exchangeable(table: CalibrationTable, new_kappas: Sequence[float], alpha: float = 0.05,
                       eps_list: Sequence[float] = CHECK_EPS) -> StalenessReport:
    """Test whether ``new_kappas`` (non-conformity scores of new labelled full-length episodes) look
    exchangeable with ``table.kappas`` (module docstring); the report says plainly what to do."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    new = np.asarray(new_kappas, dtype=np.float64)
    if new.ndim != 1 or not np.all(np.isfinite(new)):
        raise ValueError("new non-conformity scores must be a list of finite numbers")
    old = np.asarray(table.kappas, dtype=np.float64)
    med_new = float(np.median(new)) if new.size else math.nan
    rep = StalenessReport(n_table=old.size, n_new=new.size, rank_p=math.nan, alpha=alpha,
                          median_table=float(np.median(old)), median_new=med_new)
    if new.size == 0:
        rep.enough, rep.message = False, "no labelled full-length episodes to check: nothing can be said"
        return rep
    rep.rank_p = float(stats.mannwhitneyu(new, old, alternative="two-sided").pvalue)
    checks = [e for e in eps_list if table.lookup(e) is not None]
    for eps in checks:
        entry, _ = table.lookup(eps)  # type: ignore[misc]
        covered = int(np.sum(new <= entry.q_hat))  # the sequence-level set holds the truth (kappa form, as in_set)
        p = float(stats.binomtest(covered, new.size, 1.0 - entry.eps, alternative="less").pvalue)
        rep.coverage.append(CoverageCheck(entry.eps, entry.q_hat, covered, int(new.size), p))
    short = [c for c in rep.coverage if c.p_value < alpha / max(len(rep.coverage), 1)]
    rep.stale = rep.rank_p < alpha or bool(short)
    rep.enough = new.size >= MIN_NEW
    cov = ", ".join(f"eps {c.eps:g}: {c.coverage:.2f} (>= {1 - c.eps:.2f} promised, p {c.p_value:.2g})"
                    for c in rep.coverage)
    if rep.stale:
        why = []
        if rep.rank_p < alpha:
            why.append(f"their non-conformity scores rank differently from the table's (Mann-Whitney p "
                       f"{rep.rank_p:.2g}; median {rep.median_new:.3f} against {rep.median_table:.3f})")
        if short:
            why.append("the sets would cover the truth less often than promised (" + ", ".join(
                f"eps {c.eps:g}: {c.coverage:.2f} < {1 - c.eps:.2f}" for c in short) + ")")
        rep.message = (f"STALE: the calibration table ({rep.n_table} episodes) does not fit these {rep.n_new} "
                       f"labelled episodes: {'; '.join(why)}. The coverage guarantee no longer holds for this "
                       f"scorer (another model or other houses?): recalibrate with `eqa calibrate --from-store` or "
                       f"`eqa calibrate` using the current scorer.")
    elif not rep.enough:
        rep.message = (f"only {rep.n_new} labelled episodes (< {MIN_NEW}): no evidence against the table, but too "
                       f"few to say it still fits (rank p {rep.rank_p:.2g}; {cov})")
    else:
        rep.message = (f"ok: {rep.n_new} labelled episodes look exchangeable with the table's {rep.n_table} "
                       f"(Mann-Whitney p {rep.rank_p:.2g}; {cov})")
    return rep
