"""Synthetic exchangeable EQA episodes, for checking the stopping rules' statistics (tests, ``eqa_app/benches/``).

Not used by the service. Each episode draws a true answer, a step limit, and per step a view that is either
relevant (the VLM is right with probability ``accuracy``, relevance runs low as in Explore-EQA Fig. A5) or
irrelevant (low relevance, but a *confident, biased* answer distribution: the failure mode that makes the
entropy rule stop too early, paper section VII-F). Episodes are i.i.d. given the seed, hence exchangeable,
which is all conformal prediction assumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.stopper.calibration import Trace, TraceStep
from services.stopper.conformal import relevance_weighted_confidence


@dataclass(frozen=True)
class SyntheticConfig:
    n_choices: int = 4
    min_steps: int = 8
    max_steps: int = 20
    p_relevant: float = 0.3
    accuracy: float = 0.75
    relevant_rel: tuple[float, float] = (4.0, 3.0)  # Beta parameters of Rel on relevant views
    irrelevant_rel: tuple[float, float] = (1.0, 12.0)  # ... and on irrelevant ones
    concentration: float = 6.0  # Dirichlet mass on the favoured label


@dataclass(frozen=True)
class SyntheticEpisode:
    answer: int
    probs: np.ndarray  # (T, K)
    relevance: np.ndarray  # (T,)

    def rhos(self) -> np.ndarray:
        """``(T, K)`` relevance-weighted confidences (Eq. 8)."""
        return relevance_weighted_confidence(self.probs, self.relevance)


def episode(rng: np.random.Generator, cfg: SyntheticConfig = SyntheticConfig()) -> SyntheticEpisode:
    k = cfg.n_choices
    y = int(rng.integers(k))
    bias = int(rng.integers(k))  # the label the VLM favours on irrelevant views
    t_max = int(rng.integers(cfg.min_steps, cfg.max_steps + 1))
    relevant = rng.random(t_max) < cfg.p_relevant
    favoured = np.where(relevant, np.where(rng.random(t_max) < cfg.accuracy, y, rng.integers(k, size=t_max)), bias)
    alpha = np.ones((t_max, k))
    alpha[np.arange(t_max), favoured] += cfg.concentration * np.where(relevant, 1.0, 3.0)
    probs = rng.gamma(alpha)
    probs /= probs.sum(axis=1, keepdims=True)
    rel = np.where(relevant, rng.beta(*cfg.relevant_rel, size=t_max), rng.beta(*cfg.irrelevant_rel, size=t_max))
    return SyntheticEpisode(answer=y, probs=probs, relevance=rel)


def episodes(n: int, seed: int, cfg: SyntheticConfig = SyntheticConfig()) -> list[SyntheticEpisode]:
    rng = np.random.default_rng(seed)
    return [episode(rng, cfg) for _ in range(n)]


def to_trace(ep: SyntheticEpisode, question_id: str, strategy: str = "synthetic") -> Trace:
    k = ep.probs.shape[1]
    return Trace(
        question_id=question_id,
        scene="synthetic",
        category="synthetic",
        choices=[f"choice {i}" for i in range(k)],
        answer="ABCDEFGHIJKLMNOPQRSTUVWXYZ"[ep.answer],
        max_steps=ep.probs.shape[0],
        strategy=strategy,
        steps=[
            TraceStep(answer_probs=p.tolist(), relevance=float(r)) for p, r in zip(ep.probs, ep.relevance, strict=True)
        ],
    )
