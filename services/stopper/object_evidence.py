"""Object evidence for questions: the HELIOS object layer's beliefs as an answer distribution.

Pure numpy, no I/O. The mapper's object layer (HELIOS 3.1.3, :mod:`services.mapper.objects`) keeps, per
instance of a tracked class, ``Psi = S * (1 - U)`` (HELIOS Eq. 7: semantic confidence discounted by its
uncertainty). For a question about objects, the mapper tracks the question's target class
(:mod:`services.mapper.question_objects`) and reports an :class:`ObjectEvidence` per step: the ``Psi`` of the
target-class instances in the asked region and the explored share of that region. This module turns it into a
distribution over the question's choices and pools it with the VLM's ``f(x^t)``:

* **counting** ("How many X are there in the Y?"): the instances with ``Psi >= psi_min`` are counted, each
  present with probability ``Psi_i`` (independent), so the seen count is Poisson-binomial; the unexplored
  share ``u = 1 - explored`` adds unseen instances: with probability ``u`` the count may be one more
  (a one-step shift, the simplest over-dispersion). Each numeric choice gets ``P(count = n_c)``; non-numeric
  choices get 0; the result is mixed with the uniform distribution by ``floor``.
* **existence** ("Is there an X in the Y?"): ``P(yes) = 1 - (1 - Psi_best) * (1 - u * prior)``: the best
  instance is there with ``Psi_best``; otherwise an X may hide in the unexplored share, with ``prior`` the
  prior probability of the object in the room. "Yes"/"No" choices get ``P(yes)``/``1 - P(yes)``, others 0.
* **identification** (the colour of an object) is *not* covered: the layer is class-level (HELIOS tracks
  classes, not attributes); those questions keep the VLM's answer.

Pooling (:func:`combine`): relevance-free log-linear pooling ``f ∝ f_vlm^(1-w) * f_obj^w`` — the layer and
the VLM read the same frames, so their errors are not independent and a product of experts (``w`` on both
= 1) would be over-confident. ``w`` is chosen on the tuning seed only. The stopper's conformal score uses the
combined ``f`` with the VLM's relevance (Eq. 8); calibration uses the same combination, so Eq. 6 holds for it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from eqa.messages import MAX_EVIDENCE_INSTANCES, ObjectEvidence

NUMBER_WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")
MAX_TRACKED = MAX_EVIDENCE_INSTANCES  # instances reported per step
CATEGORIES = ("counting", "existence")
__all__ = ["CATEGORIES", "MAX_TRACKED", "EvidenceParams", "ObjectEvidence", "budget_answer", "combine",
           "combined_steps", "layer_distribution", "poisson_binomial"]


@dataclass(frozen=True)
class EvidenceParams:
    psi_min: float = 0.3  # an instance counts only from this Psi on
    weight: float = 0.5  # w of the layer's distribution in the log-linear pool
    prior: float = 0.5  # existence: prior of the object in the unexplored share
    floor: float = 0.05  # mixing with the uniform distribution (never rule an answer out alone)

    def __post_init__(self) -> None:
        for name in ("psi_min", "weight", "prior", "floor"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"object evidence {name} must be in [0, 1], got {v!r}")


def choice_number(text: str) -> int | None:
    """The number a choice names ("Three", "3", "three chairs"), or None."""
    t = text.strip().lower()
    m = re.match(r"^(\d+)\b", t)
    if m:
        return int(m.group(1))
    for n, w in enumerate(NUMBER_WORDS):
        if re.match(rf"^{w}\b", t):
            return n
    return None


def yes_no(text: str) -> bool | None:
    t = text.strip().lower().rstrip(".!")
    return True if t == "yes" else False if t == "no" else None


def poisson_binomial(p: list[float] | np.ndarray) -> np.ndarray:
    """``P(sum of independent Bernoulli(p_i) = n)`` for ``n = 0..len(p)`` (dynamic programming)."""
    out = np.array([1.0])
    for pi in np.asarray(p, dtype=np.float64):
        out = np.append(out * (1.0 - pi), 0.0) + np.append(0.0, out * pi)
    return out


def layer_distribution(ev: ObjectEvidence, choices: list[str], params: EvidenceParams) -> np.ndarray | None:
    """The layer's distribution over ``choices`` (module docstring), or None when it has nothing to say
    (another category, or choices that are not numbers / yes-no)."""
    psi = [float(min(max(p, 0.0), 1.0)) for p in ev.psi if math.isfinite(p)]
    u = 1.0 - ev.explored
    if ev.category == "counting":
        nums = [choice_number(c) for c in choices]
        if not any(n is not None for n in nums):
            return None
        seen = poisson_binomial([p for p in psi if p >= params.psi_min])
        counts = np.append(seen * (1.0 - u), 0.0) + np.append(0.0, seen * u)  # maybe one unseen
        raw = np.array([counts[n] if n is not None and n < counts.size else 0.0 for n in nums])
    elif ev.category == "existence":
        yn = [yes_no(c) for c in choices]
        if not any(v is not None for v in yn):
            return None
        best = max((p for p in psi if p >= params.psi_min), default=0.0)
        p_yes = 1.0 - (1.0 - best) * (1.0 - u * params.prior)
        raw = np.array([p_yes if v is True else (1.0 - p_yes) if v is False else 0.0 for v in yn])
    else:
        return None
    total = raw.sum()
    dist = raw / total if total > 0 else np.full(len(choices), 1.0 / len(choices))
    return (1.0 - params.floor) * dist + params.floor / len(choices)


def combine(vlm: np.ndarray | list[float], layer: np.ndarray | None, weight: float) -> np.ndarray:
    """``f ∝ f_vlm^(1-w) * f_layer^w`` (log-linear pooling); the VLM's ``f`` when the layer has no opinion."""
    f = np.asarray(vlm, dtype=np.float64)
    if layer is None or weight <= 0.0:
        return f
    logp = (1.0 - weight) * np.log(np.maximum(f, 1e-12)) + weight * np.log(np.maximum(layer, 1e-12))
    out = np.exp(logp - logp.max())
    return out / out.sum()


def budget_answer(vlm_probs: np.ndarray | Sequence[Sequence[float]], relevance: np.ndarray | Sequence[float],
                  latest: ObjectEvidence | None, choices: list[str], params: EvidenceParams) -> int:
    """The answer at a budget with the layer pooled in: ``argmax`` of the VLM's ``f(x^t*)`` at the most relevant
    step ``t*`` (Explore-EQA V-B) pooled with the layer's distribution at the last step (``latest``: it has fused
    every view so far); the VLM's answer alone when the layer has nothing to say. Ties: the earliest step, the
    first label."""
    f = np.asarray(vlm_probs, dtype=np.float64)
    rel = np.asarray(relevance, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 1 or rel.shape != (f.shape[0],):
        raise ValueError("budget_answer needs at least one step of scores")
    t_star = int(np.argmax(rel))
    layer = layer_distribution(latest, choices, params) if latest is not None else None
    return int(np.argmax(combine(f[t_star], layer, params.weight)))


def combined_steps(probs: np.ndarray, evidence: list[ObjectEvidence | None], choices: list[str],
                   params: EvidenceParams) -> np.ndarray:
    """``(T, C)`` combined distributions of an episode's steps (the layer's belief at step ``t`` is cumulative:
    it has fused every frame up to ``t``, so the combination stays causal)."""
    f = np.asarray(probs, dtype=np.float64)
    out = f.copy()
    for t, ev in enumerate(evidence):
        if ev is not None:
            out[t] = combine(f[t], layer_distribution(ev, choices, params), params.weight)
    return out
