"""Multi-step conformal prediction for stopping exploration (Explore-EQA section V, Eq. 7-10, Claim 1).

Pure numpy, no I/O. Notation of the paper:

* ``f(x^t)`` — the VLM's answer distribution at step ``t`` over the ``K`` choices.
* ``Rel(x^t)`` — the question-image relevance score in ``[0, 1]`` (Eq. 5).
* ``rho_y^t = Rel(x^t) * (f_y(x^t) - 1)`` — relevance-weighted confidence (Eq. 8).
* ``rho_bar_y = min_t rho_y^t`` — episode-level confidence (Eq. 9).
* ``kappa_i = 1 - rho_bar_{y_i}`` — non-conformity score of calibration episode ``i``.
* ``q_hat`` — the ``ceil((N+1)(1-eps))/N`` empirical quantile of ``kappa_1..kappa_N``.
* ``C^t = {y : rho_y^t >= 1 - q_hat}`` — the causal prediction set of step ``t`` (Eq. 10); the robot keeps
  ``C^0 ∩ ... ∩ C^t`` and stops when one answer is left. Claim 1: that intersection over all steps equals
  the sequence-level set ``{y : rho_bar_y >= 1 - q_hat}``.

Ranges, and when the sets are non-trivial
-----------------------------------------
``rho_y^t`` lies in ``[-Rel(x^t), 0] ⊆ [-1, 0]``, so ``kappa`` lies in ``[1, 2]`` and so does ``q_hat``; the
threshold ``1 - q_hat`` lies in ``[-1, 0]``. Write ``m = q_hat - 1 ∈ [0, 1]``. Then
``y ∈ C^t  <=>  Rel(x^t) * (1 - f_y(x^t)) <= m``:

* ``q_hat = 2`` (``m = 1``): every label is in every set; the robot never stops early.
* ``q_hat = 1`` (``m = 0``): a label survives a step only if ``f_y = 1`` or ``Rel = 0``; any relevant,
  not fully certain view empties the set (then the fallback answer is given at once).
* A view with ``Rel(x^t) <= m`` keeps *every* label: irrelevant views never shrink the set, however
  confident the VLM is on them. This is why the rule does not stop on "confident biased answers on
  irrelevant views" the way the entropy rule (Eq. 4) does.
* A view shrinks the set to one label ``y`` only if ``Rel * (1 - f_y) <= m < Rel * (1 - f_z)`` for all
  ``z != y``; since at most one label has ``f > 1/2``, the useful regime is ``q_hat`` in ``(1, 2)`` with
  ``m`` clearly below the relevance of good views.

The quantile
------------
With ``k = ceil((N+1)(1-eps))`` the ``k/N`` empirical quantile is the ``k``-th smallest score (1-based),
i.e. ``numpy.quantile(kappas, k/N, method="inverted_cdf")``. (KnowNo's and the "gentle introduction"'s code
call ``method="higher"``, which for ``k < N`` returns the ``(k+1)``-th smallest: slightly more conservative;
we implement the formula of the paper.) ``k <= N`` requires ``N >= ceil(1/eps) - 1``; below that the
quantile is undefined (it would be ``+inf``: every set is all labels) and :func:`conformal_quantile` raises
:class:`CalibrationError` saying so. With continuous scores the coverage of the sequence-level set is in
``[1 - eps, 1 - eps + 1/(N+1))`` (Vovk; Angelopoulos & Bates, 2023, Thm. D.1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from eqa.messages import EPS_GT, EPS_LT, eps_in_bounds

PROB_SUM_TOL = 1e-3  # |sum(f) - 1| allowed for an answer distribution
# (N+1)(1-eps) is computed in floating point; an exact integer product must not round up to the next one.
_CEIL_TOL = 1e-9


class ScoreError(ValueError):
    """Step scores that are not a valid answer distribution / relevance (NaN, negative, not summing to 1)."""


class CalibrationError(ValueError):
    """Calibration impossible or undefined (bad eps, too few episodes, bad traces)."""


def check_eps(eps: float) -> float:
    """``eps`` as a float in the open interval (0, 1), else :class:`CalibrationError`."""
    try:
        value = float(eps)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"eps must be a number in (0, 1), got {eps!r}") from exc
    if not eps_in_bounds(value):
        raise CalibrationError(
            f"eps must be in the open interval ({EPS_GT:g}, {EPS_LT:g}) (1 - eps is the success wanted), got {eps!r}"
        )
    return value


def check_scores(answer_probs: Sequence[float], relevance: float, n_choices: int | None = None) -> np.ndarray:
    """Validate one step's ``f(x^t)`` and ``Rel(x^t)``; return ``f`` as a float64 array.

    Raises :class:`ScoreError` naming the problem: NaN/inf, negative or > 1 values, a sum not within
    ``PROB_SUM_TOL`` of 1, a wrong number of choices, a relevance outside ``[0, 1]``.
    """
    f = np.asarray(answer_probs, dtype=np.float64)
    if f.ndim != 1 or f.size < 1:
        raise ScoreError(f"answer_probs must be a non-empty list of numbers, got shape {f.shape}")
    if n_choices is not None and f.size != n_choices:
        raise ScoreError(f"answer_probs has {f.size} values but the question has {n_choices} choices")
    if not np.all(np.isfinite(f)):
        raise ScoreError(f"answer_probs contains NaN or inf: {f.tolist()}")
    if np.any(f < 0.0) or np.any(f > 1.0 + PROB_SUM_TOL):
        raise ScoreError(f"answer_probs must lie in [0, 1]: {f.tolist()}")
    if abs(float(f.sum()) - 1.0) > PROB_SUM_TOL:
        raise ScoreError(f"answer_probs must sum to 1 (got {float(f.sum()):.6f})")
    rel = float(relevance)
    if not math.isfinite(rel) or not 0.0 <= rel <= 1.0:
        raise ScoreError(f"relevance must be a number in [0, 1], got {relevance!r}")
    return f


def relevance_weighted_confidence(answer_probs: Sequence[float] | np.ndarray, relevance: float) -> np.ndarray:
    """``rho_y^t = Rel(x^t) * (f_y(x^t) - 1)`` for every label ``y`` (Eq. 8; Eq. 7 for one step).

    ``answer_probs`` may be ``(K,)`` for one step or ``(T, K)`` with ``relevance`` of shape ``(T,)``.
    Values lie in ``[-Rel, 0]``.
    """
    f = np.asarray(answer_probs, dtype=np.float64)
    rel = np.asarray(relevance, dtype=np.float64)
    if f.ndim == 2:
        rel = rel.reshape(-1, 1)
    return rel * (f - 1.0)


def episode_confidence(rhos: np.ndarray) -> np.ndarray:
    """``rho_bar_y = min_t rho_y^t`` over the steps of an episode (Eq. 9); ``rhos`` is ``(T, K)``."""
    r = np.asarray(rhos, dtype=np.float64)
    if r.ndim != 2 or r.shape[0] < 1:
        raise CalibrationError(f"an episode needs at least one step of scores, got shape {r.shape}")
    return r.min(axis=0)


def nonconformity(answer_probs: np.ndarray, relevance: np.ndarray, answer_index: int) -> float:
    """``kappa = 1 - min_t rho_{y}^t`` for the true answer ``y`` of one calibration episode (section V-B)."""
    rho_bar = episode_confidence(relevance_weighted_confidence(answer_probs, relevance))
    if not 0 <= answer_index < rho_bar.size:
        raise CalibrationError(f"answer index {answer_index} outside the {rho_bar.size} choices")
    return float(1.0 - rho_bar[answer_index])


def quantile_rank(n: int, eps: float) -> int:
    """``k = ceil((N+1)(1-eps))``: ``q_hat`` is the ``k``-th smallest score. Raises when ``k > N``."""
    eps = check_eps(eps)
    if n < 1:
        raise CalibrationError("the calibration set is empty: run `eqa calibrate` on some episodes first")
    k = max(1, math.ceil((n + 1) * (1.0 - eps) - _CEIL_TOL))
    if k > n:
        need = math.ceil(1.0 / eps - _CEIL_TOL) - 1
        raise CalibrationError(
            f"the conformal quantile is undefined for eps={eps:g} with N={n} calibration episodes: "
            f"ceil((N+1)(1-eps)) = {k} > N; at least ceil(1/eps) - 1 = {need} episodes are needed "
            f"(or ask for a larger eps)"
        )
    return k


def conformal_quantile(kappas: Sequence[float] | np.ndarray, eps: float) -> float:
    """``q_hat``: the ``ceil((N+1)(1-eps))/N`` empirical quantile of the non-conformity scores (V-A)."""
    scores = np.asarray(kappas, dtype=np.float64).ravel()
    if not np.all(np.isfinite(scores)):
        raise CalibrationError("non-conformity scores contain NaN or inf")
    k = quantile_rank(scores.size, eps)
    return float(np.partition(scores, k - 1)[k - 1])


def in_set(rho: np.ndarray | float, q_hat: float) -> np.ndarray:
    """Whether ``rho >= 1 - q_hat``, tested in the non-conformity form ``1 - rho <= q_hat``.

    ``q_hat`` is one of the calibration scores ``1 - rho_bar`` (computed by :func:`nonconformity` with the very
    same floating-point operations), so a test score equal to it compares equal here. The paper's form
    ``rho >= 1 - q_hat`` evaluates ``1 - (1 - rho)``, which is not ``rho`` in floating point: an exchangeable
    tie (coarse probabilities, a re-run question) would drop the true answer and break Eq. 6. ``1 - x`` is
    monotone under rounding, so ``max_t (1 - rho^t) = 1 - min_t rho^t`` exactly and Claim 1 still holds.
    """
    return 1.0 - np.asarray(rho, dtype=np.float64) <= float(q_hat)


def step_set(rho: np.ndarray, q_hat: float) -> np.ndarray:
    """Boolean mask of ``C^t = {y : rho_y^t >= 1 - q_hat}`` (Eq. 10; compared as in :func:`in_set`)."""
    return in_set(rho, q_hat)


def sequence_set(rhos: np.ndarray, q_hat: float) -> np.ndarray:
    """Boolean mask of the sequence-level set ``{y : min_t rho_y^t >= 1 - q_hat}`` (section V-B)."""
    return in_set(episode_confidence(rhos), q_hat)


def running_intersection(rhos: np.ndarray, q_hat: float) -> np.ndarray:
    """``(T, K)`` masks of ``C^0 ∩ ... ∩ C^t`` for every ``t`` (what the robot keeps; Claim 1, Prop. 1)."""
    return np.logical_and.accumulate(in_set(rhos, q_hat), axis=0)


def fallback_answer(answer_probs: Sequence[Sequence[float]], relevance: Sequence[float]) -> int:
    """Index of ``argmax_y f_y(x^t*)`` at ``t* = argmax_t Rel(x^t)`` (section V-B, last paragraph).

    Used when the step limit is reached with several answers left, the intersection is empty, or the
    planner has nothing left to explore. Ties go to the earliest step and the first label.
    """
    f = np.asarray(answer_probs, dtype=np.float64)
    rel = np.asarray(relevance, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 1 or rel.shape != (f.shape[0],):
        raise ValueError("fallback_answer needs at least one step of scores")
    t_star = int(np.argmax(rel))
    return int(np.argmax(f[t_star]))
