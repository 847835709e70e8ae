"""Answer memory: answer from the K most relevant views of an episode, not from one.

Explore-EQA answers at the end with ``argmax_y f_y(x^{t*})`` at ``t* = argmax_t Rel(x^t)`` (section V-B, last
paragraph): one view. This module keeps the ``K`` most relevant views seen so far and pools their answer
distributions. It is pure numpy, causal (step ``t`` uses only steps ``<= t``) and bounded (``K <= MAX_K``).

The rule (:class:`AnswerRule`)
------------------------------
With ``M_t`` the ``K`` steps of highest ``Rel`` among ``0..t`` (ties: earlier step first) and weights
``w_k = Rel(x^k) / sum_{j in M_t} Rel(x^j)``:

* ``fusion = "loglinear"`` (default): ``f~_y^t ∝ prod_{k in M_t} f_y(x^k)^{w_k}`` — relevance-weighted
  log-linear (geometric) pooling. Weights sum to 1, so ``K`` agreeing views do *not* multiply their confidence
  as a product of independent experts would: views of one object by one VLM share its errors (the simulated
  perception model draws right/wrong once per (question, object), ``services/vlm_scorer/backends/oracle.py``),
  and a naive Bayes product would be over-confident. A view that gives an answer ~0 acts as a veto, which
  is the wanted behaviour when a relevant view rules an answer out.
* ``fusion = "linear"``: ``f~^t = sum_k w_k f(x^k)`` (linear opinion pool): no veto, averages.

The relevance attached to the pooled distribution is ``Rel~^t = max_{k in M_t} Rel(x^k)`` (the best view's),
so the conformal score of a step (Eq. 8) becomes ``rho~_y^t = Rel~^t (f~_y^t - 1)``.

Conformal guarantee. ``(f~^t, Rel~^t)_t`` is a deterministic, causal function of the episode's scores, so the
pooled sequence of a calibration episode is exchangeable with a test episode's exactly when the raw ones are.
Calibrating ``kappa = 1 - min_t rho~_{y}^t`` on the *same* rule (:func:`transform` applied to the
calibration traces, :func:`services.stopper.calibration.calibrate` with ``answer_rule``) keeps Eq. 6 and
Claim 1 (the running intersection of the causal sets of the pooled scores equals the sequence-level set).
A table calibrated on another rule gives no guarantee; the stopper warns (:func:`rule_mismatch`).

``k = 0`` is the paper's single-view rule (no memory): :func:`transform` returns the scores unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

MAX_K = 16  # views kept at most (bounds memory and the multi-image prompt)
FUSIONS = ("loglinear", "linear")
Fusion = Literal["loglinear", "linear"]
_LOG_FLOOR = 1e-12  # log-linear pooling: a probability 0 counts as 1e-12 (a strong veto, not -inf)


@dataclass(frozen=True)
class AnswerRule:
    """How the answer of an episode is read from its steps: ``k = 0`` single view (paper), ``k >= 1`` pooled
    over the ``k`` most relevant views with ``fusion``."""

    k: int = 0
    fusion: Fusion = "loglinear"

    def __post_init__(self) -> None:
        if not isinstance(self.k, int) or not 0 <= self.k <= MAX_K:
            raise ValueError(f"answer memory K must be an integer in 0..{MAX_K} (0 = off), got {self.k!r}")
        if self.fusion not in FUSIONS:
            raise ValueError(f"answer memory fusion must be one of {FUSIONS}, got {self.fusion!r}")

    @property
    def on(self) -> bool:
        return self.k > 0

    @property
    def name(self) -> str:
        """A stable label for tables and reports: ``single`` or ``memory-K-fusion``."""
        return f"memory-{self.k}-{self.fusion}" if self.on else "single"

    @classmethod
    def from_name(cls, name: str | None) -> AnswerRule:
        """Inverse of :attr:`name` (``None`` / ``single`` = off)."""
        if not name or name == "single":
            return cls()
        parts = name.split("-")
        if len(parts) != 3 or parts[0] != "memory" or not parts[1].isdigit():
            raise ValueError(f"not an answer rule name: {name!r} (single or memory-K-fusion)")
        return cls(int(parts[1]), parts[2])  # type: ignore[arg-type]


def top_k(relevance: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` largest relevances (ties: earlier step first), in step order."""
    rel = np.asarray(relevance, dtype=np.float64)
    order = np.lexsort((np.arange(rel.size), -rel))  # by -rel, then by index
    return np.sort(order[:k])


def pool(probs: np.ndarray, relevance: np.ndarray, fusion: Fusion = "loglinear") -> np.ndarray:
    """Pool ``(n, C)`` answer distributions with weights ``Rel / sum Rel`` (uniform when all ``Rel`` are 0)."""
    f = np.asarray(probs, dtype=np.float64)
    rel = np.asarray(relevance, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 1 or rel.shape != (f.shape[0],):
        raise ValueError(f"pool needs (n, C) distributions and (n,) relevances, got {f.shape} and {rel.shape}")
    total = float(rel.sum())
    w = rel / total if total > 0 else np.full(rel.size, 1.0 / rel.size)
    if fusion == "linear":
        out = w @ f
    elif fusion == "loglinear":
        logp = w @ np.log(np.maximum(f, _LOG_FLOOR))
        out = np.exp(logp - logp.max())
    else:
        raise ValueError(f"unknown fusion {fusion!r}")
    return out / out.sum()


def transform(probs: np.ndarray, relevance: np.ndarray, rule: AnswerRule) -> tuple[np.ndarray, np.ndarray]:
    """``(f~, Rel~)`` of every step (``(T, C)``, ``(T,)``) under ``rule`` (module docstring); causal."""
    f = np.asarray(probs, dtype=np.float64)
    rel = np.asarray(relevance, dtype=np.float64)
    if not rule.on:
        return f, rel
    out_f = np.empty_like(f)
    out_r = np.empty_like(rel)
    kept: list[int] = []  # the K most relevant steps so far (same choice as top_k: ties keep the earlier step)
    logf = np.log(np.maximum(f, _LOG_FLOOR)) if rule.fusion == "loglinear" else f
    for t in range(f.shape[0]):
        if len(kept) < rule.k:
            kept.append(t)
        else:
            worst = min(kept, key=lambda i: (rel[i], -i))
            if rel[t] > rel[worst]:
                kept.remove(worst)
                kept.append(t)
        idx = np.array(kept)
        r = rel[idx]
        total = float(r.sum())
        w = r / total if total > 0 else np.full(r.size, 1.0 / r.size)
        if rule.fusion == "loglinear":
            lp = w @ logf[idx]
            p = np.exp(lp - lp.max())
        else:
            p = w @ f[idx]
        out_f[t] = p / p.sum()
        out_r[t] = r.max()
    return out_f, out_r


def memory_answer(probs: np.ndarray, relevance: np.ndarray, rule: AnswerRule) -> int:
    """The answer index at the end of the steps given: ``argmax f~^T`` (pooled), or the paper's fallback
    ``argmax f(x^{t*})`` at the most relevant step when the memory is off (ties: first label)."""
    f = np.asarray(probs, dtype=np.float64)
    rel = np.asarray(relevance, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 1:
        raise ValueError("memory_answer needs at least one step of scores")
    if not rule.on:
        return int(np.argmax(f[int(np.argmax(rel))]))
    idx = top_k(rel, rule.k)
    return int(np.argmax(pool(f[idx], rel[idx], rule.fusion)))


def rule_mismatch(table_rule: str | None, episode_rule: AnswerRule) -> str:
    """A warning when the calibration table was computed for another answer rule than the episode uses
    (absent provenance = the single-view rule of tables made before answer rules were recorded)."""
    have = table_rule or "single"
    if have == episode_rule.name:
        return ""
    return (f"table calibrated for answer rule {have}, this episode answers with {episode_rule.name}: "
            f"run `eqa calibrate --answer-memory {episode_rule.k}` for the guarantee")
