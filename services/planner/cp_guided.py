"""``cp_guided``: the conformal prediction set guides exploration (Explore-EQA section VIII, future work).

The paper suggests using the CP prediction set "not only as the stopping criterion, but also for guiding
exploration". The planner receives the stopper's :class:`eqa.messages.Decision` of every step before it plans;
this strategy reads its running prediction set ``C`` (Eq. 10, Claim 1) and re-tempers the Eq. A6 frontier
weights the mapper computed as for ``semantic``:

    w_p' = w_p ** (1 + gamma * s),    s = (K - |C|) / (K - 1)  in [0, 1]

(``K`` choices; ``s = 0`` while every answer is still possible, 1 when one is left). Equivalently both Eq. A6
temperatures (tau_SV, tau_SV,Normal; and through SV, tau_LSV and tau_GSV) are multiplied by ``1 + gamma s``.

Why this favours views likely to split the set: a set shrinks only on a view that is relevant to the question
(``Rel * (1 - f_y) > q_hat - 1`` for the answers it removes), i.e. where the semantic value map already
points. While nothing relevant has been seen (``|C| = K``) the robot explores as ``semantic`` does; once some
answers are ruled out, the evidence that split them lies in the high-value region, and the answers still in
the set are split by a closer or second view of it, so the robot concentrates there instead of wandering to
low-value frontiers (the paper's Fig. 7c finds higher temperatures help early and hurt late; here the
temperature rises only once the set says the evidence is near).

What it does not do (the issue's example): score every answer still in the set with its own LSV/GSV prompt.
That would need one scorer prompt per answer and a map layer per answer (the mapper keeps one question layer);
it is left for later. With a non-CP stopping rule (no prediction set) the strategy is ``semantic``.
"""

from __future__ import annotations

import math

import numpy as np

from eqa.messages import Decision, MapUpdate

DEFAULT_GAMMA = 2.0  # temperature gain when one answer is left (tau x 3); not tuned on any evaluation seed


def narrowing(decision: Decision | None) -> float:
    """``s = (K - |C|) / (K - 1)`` of the decision's running prediction set, 0 without a CP set."""
    if decision is None or decision.rule != "cp" or not decision.scores:
        return 0.0
    k = len(decision.scores)  # rho_y^t of every label
    if k < 2:
        return 0.0
    size = min(max(len(decision.prediction_set), 1), k)
    return (k - size) / (k - 1)


def reweight(weights: list[float], decision: Decision | None, gamma: float = DEFAULT_GAMMA) -> list[float]:
    """Eq. A6 weights raised to ``1 + gamma * s`` (module docstring), in log space (weights may be huge or
    tiny: ``exp(tau * SV)``), rescaled so the largest is 1. Non-finite or negative weights stay as they are
    (the sampler ignores them)."""
    if not math.isfinite(gamma) or gamma < 0:
        raise ValueError(f"gamma must be a finite number >= 0, got {gamma}")
    w = np.asarray(weights, dtype=np.float64)
    factor = 1.0 + gamma * narrowing(decision)
    ok = np.isfinite(w) & (w > 0)
    if factor == 1.0 or not ok.any():
        return [float(v) for v in w]
    logw = np.log(w[ok]) * factor
    out = w.copy()
    out[ok] = np.exp(logw - logw.max())
    return [float(v) for v in out]


def guided_map(update: MapUpdate, decision: Decision | None, gamma: float = DEFAULT_GAMMA) -> MapUpdate:
    """The map update with its frontier weights re-tempered by the prediction set (the planner samples from it
    as for ``semantic``)."""
    new = reweight([f.weight for f in update.frontiers], decision, gamma)
    frontiers = [f.model_copy(update={"weight": w}) for f, w in zip(update.frontiers, new, strict=True)]
    return update.model_copy(update={"frontiers": frontiers})
