"""Uncalibrated stopping rules that Explore-EQA compares against (section V and VII-F). Pure numpy.

* ``entropy``: stop when the entropy of the answer distribution ``H(f(x^t))`` (Eq. 4, nats) is below a
  threshold; answer ``argmax f(x^t)`` of that step.
* ``relevance``: stop when the question-image relevance ``Rel(x^t)`` (Eq. 5) is above a threshold; answer
  ``argmax f(x^t)`` of that step.
* ``max_steps``: never stop before the step limit (the answer is then the fallback of
  :func:`services.stopper.conformal.fallback_answer`).

Default thresholds (when ``StopConfig.threshold`` is None) are the ones of the paper's hardware experiments
(section VII-G): 0.1 nats for entropy and 0.4 for relevance, which roughly give 50 % success in its Fig. 9.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

DEFAULT_THRESHOLDS: dict[str, float] = {"entropy": 0.1, "relevance": 0.4}


def entropy(answer_probs: Sequence[float] | np.ndarray) -> float:
    """``H(f(x^t)) = -sum_y f_y log f_y`` in nats (Eq. 4); ``0 log 0 = 0``."""
    f = np.asarray(answer_probs, dtype=np.float64)
    nz = f[f > 0.0]
    return float(-(nz * np.log(nz)).sum())


def threshold_for(rule: str, threshold: float | None) -> float:
    """The threshold of a baseline rule: the configured one, or the documented default."""
    if rule not in DEFAULT_THRESHOLDS:
        raise ValueError(f"rule {rule!r} has no threshold")
    value = DEFAULT_THRESHOLDS[rule] if threshold is None else float(threshold)
    if not np.isfinite(value):
        raise ValueError(f"{rule} threshold must be a finite number, got {threshold!r}")
    if rule == "relevance" and not 0.0 <= value <= 1.0:
        raise ValueError(f"relevance threshold must be in [0, 1], got {value}")
    if rule == "entropy" and value < 0.0:
        raise ValueError(f"entropy threshold must be >= 0 nats, got {value}")
    return value


def entropy_stops(answer_probs: Sequence[float] | np.ndarray, threshold: float) -> tuple[bool, float]:
    """``(H(f(x^t)) < threshold, H)`` (Eq. 4)."""
    h = entropy(answer_probs)
    return h < threshold, h


def relevance_stops(relevance: float, threshold: float) -> tuple[bool, float]:
    """``(Rel(x^t) > threshold, Rel)`` (Eq. 5)."""
    rel = float(relevance)
    return rel > threshold, rel
