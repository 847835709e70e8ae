"""The stop rules of :func:`services.stopper.state.decide` over a whole recorded episode at once, on arrays.

Offline studies (stop-rule sweeps, answer rules, object evidence) replay thousands of recorded episodes under
many thresholds; stepping the service's :func:`~services.stopper.state.decide` through pydantic records for each
would cost minutes. :func:`replay_arrays` computes the same decision from the ``(T, K)`` answer distributions
``f(x^t)`` and the ``(T,)`` relevances ``Rel(x^t)`` of a cold episode (no memory steps) in one pass:

* ``cp`` (``parameter`` = ``q_hat``): the running intersection ``C^0 ∩ ... ∩ C^t`` of the causal sets of Eq. 10
  on ``rho_y^t = Rel~^t (f~_y^t - 1)`` (Eq. 8, the answer rule's pooled scores); stop at the first step with at
  most one answer left, answer that one, or the fallback when the set is empty;
* ``entropy`` / ``relevance`` (``parameter`` = threshold, None = the documented default): the first step with
  ``H(f(x^t)) < threshold`` (Eq. 4) / ``Rel(x^t) > threshold`` (Eq. 5), answering ``argmax f(x^t)``;
* ``max_steps``: never before the limit.

A rule that has not fired by the step limit ``max_steps - 1`` (or by the last recorded step, when the run ended
before it) answers with the answer rule's fallback (:func:`services.stopper.answer_memory.memory_answer`).
``tests/stopper/test_replay.py`` checks on random episodes that every rule decides exactly as ``decide`` does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.stopper import baselines
from services.stopper.answer_memory import AnswerRule, memory_answer, transform
from services.stopper.conformal import in_set, relevance_weighted_confidence

REPLAY_RULES = ("cp", "entropy", "relevance", "max_steps")


@dataclass(frozen=True)
class ReplayStop:
    """Where and how one recorded episode stops under one rule."""

    step: int  # the step the episode stops at (0-based; ``step + 1`` steps used)
    answer: int  # the answer's index into the choices
    prediction_set: tuple[int, ...] = ()  # cp: the running set at the stop step (empty for the other rules)
    # cp: the sequence-level set over every recorded step (Claim 1: the intersection of all causal sets),
    # whose coverage of the truth Eq. 6 bounds; None for the other rules
    sequence_set: tuple[int, ...] | None = None

    def covers(self, truth: int) -> bool | None:
        """Whether the sequence-level set holds the true answer (None for a rule without one)."""
        return None if self.sequence_set is None else truth in self.sequence_set


def replay_arrays(f: np.ndarray, relevance: np.ndarray, max_steps: int, rule: str, parameter: float | None = None,
                  answer_rule: AnswerRule = AnswerRule()) -> ReplayStop:
    """What ``decide`` answers, and at which step, for the recorded scores ``f`` ``(T, K)`` and ``relevance``
    ``(T,)`` of an episode with budget ``max_steps`` (module docstring). Pure; raises ``ValueError`` for
    arrays of the wrong shape, an unknown rule or a cp replay without ``q_hat``."""
    f = np.asarray(f, dtype=np.float64)
    rel = np.asarray(relevance, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 1 or f.shape[1] < 1 or rel.shape != (f.shape[0],):
        raise ValueError(f"replay needs (T, K) answer distributions and (T,) relevances, got {f.shape}, {rel.shape}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if rule not in REPLAY_RULES:
        raise ValueError(f"unknown stop rule {rule!r}; choose from {', '.join(REPLAY_RULES)}")
    t_end = min(f.shape[0], max_steps) - 1  # the step limit, or the last step of a run that ended before it

    def fallback(t: int) -> int:
        return memory_answer(f[: t + 1], rel[: t + 1], answer_rule)

    if rule == "cp":
        if parameter is None:
            raise ValueError("a cp replay needs q_hat")
        pf, pr = transform(f, rel, answer_rule)
        running = np.logical_and.accumulate(in_set(relevance_weighted_confidence(pf, pr), parameter), axis=0)
        seq = tuple(int(i) for i in np.flatnonzero(running[-1]))
        sizes = running.sum(axis=1)
        hit = np.flatnonzero(sizes[: t_end + 1] <= 1)
        t = int(hit[0]) if hit.size else t_end
        left = tuple(int(i) for i in np.flatnonzero(running[t]))
        return ReplayStop(t, left[0] if len(left) == 1 else fallback(t), left, seq)
    if rule in ("entropy", "relevance"):
        thr = baselines.threshold_for(rule, parameter)
        if rule == "entropy":
            fired = np.array([baselines.entropy_stops(f[t], thr)[0] for t in range(t_end + 1)])
        else:
            fired = np.array([baselines.relevance_stops(rel[t], thr)[0] for t in range(t_end + 1)])
        hit = np.flatnonzero(fired)
        if hit.size:
            t = int(hit[0])
            return ReplayStop(t, int(np.argmax(f[t])))
    return ReplayStop(t_end, fallback(t_end))
