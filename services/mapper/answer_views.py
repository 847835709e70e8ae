"""Joint answer memory in the mapper (``EQA_ANSWER_MEMORY_MODE=joint``).

The mapper keeps the K (``EQA_ANSWER_MEMORY_VIEWS``, <= 16) most relevant views of a question episode, each
downscaled so that its longer side is <= :data:`eqa.messages.MAX_MEMORY_VIEW_SIDE` pixels; a step's relevance
is the Rel(x^t) (Explore-EQA Eq. 5) of the ScoreResult the mapper already receives. Whenever that set changes,
it asks the scorer pool for ONE answer distribution over all kept views (a ScoreRequest with
``memory_views``: several images in one prompt, the hf backend's ``answer_from_views``), and the step's
StepScores.answer_probs is that joint answer (relevance unchanged), so the stopper's CP covers it when its
table was calibrated on traces made with the same mode. When the set did not change, the last joint answer
is used again (the same views give the same answer).

Backends that take one image per prompt (oracle, remote) refuse the joint request: the mapper logs it once
per episode and keeps the per-view answer for that episode (the single-view rule, or the stopper's fusion
when ``EQA_ANSWER_MEMORY_K`` > 0). Questions without choices keep the per-view answer as well.

State: the kept views (images included) and the last joint answer are the ``answer_views`` part of the
mapper's episode state, so a restarted mapper goes on with the same memory. Bounded: 16 views x 448^2 x 3
bytes at most (9.6 MB); the default K = 4 at 640x480 frames keeps 4 x 448x336x3 (1.8 MB).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eqa.messages import MAX_MEMORY_VIEW_SIDE, MAX_MEMORY_VIEWS, EpisodeStart, ErrorReply, ScoreRequest, ScoreResult
from eqa.scorer_client import ScorerError
from services.mapper import snapshots

log = logging.getLogger(__name__)

STATE_KEY = "answer_views"  # this memory's part of the mapper's episode state


def shrink(rgb: np.ndarray, max_side: int = MAX_MEMORY_VIEW_SIDE) -> np.ndarray:
    """Integer-stride downscale so that the longer side is at most ``max_side`` pixels (uint8 RGB)."""
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"a memory view must be HxWx3, got shape {img.shape}")
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    stride = max(1, -(-max(img.shape[:2]) // max_side))
    return np.ascontiguousarray(img[::stride, ::stride])


@dataclass
class AnswerViews:
    """The K most relevant views of one episode (ties: the earlier view stays) and the last joint answer."""

    k: int
    steps: list[int] = field(default_factory=list)
    relevance: list[float] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)
    answer: list[float] | None = None  # the joint answer over the current set
    last_step: int = -1

    def __post_init__(self) -> None:
        if not 1 <= self.k <= MAX_MEMORY_VIEWS:
            raise ValueError(f"answer memory K must be in 1..{MAX_MEMORY_VIEWS}, got {self.k}")

    def offer(self, step: int, relevance: float, rgb: np.ndarray) -> bool:
        """Offer step ``step``'s view; True if the kept set changed."""
        rel = float(relevance)
        if not np.isfinite(rel):
            raise ValueError("relevance must be finite")
        self.last_step = max(self.last_step, int(step))
        if len(self.steps) >= self.k:
            worst = min(range(len(self.steps)), key=lambda i: (self.relevance[i], -self.steps[i]))
            if rel <= self.relevance[worst]:
                return False
            for lst in (self.steps, self.relevance, self.images):
                lst.pop(worst)
        self.steps.append(int(step))
        self.relevance.append(rel)
        self.images.append(shrink(rgb))
        return True

    @property
    def nbytes(self) -> int:
        return sum(im.nbytes for im in self.images)

    def snapshot(self) -> dict[str, Any]:
        return {"k": self.k, "steps": list(self.steps), "relevance": list(self.relevance),
                "images": list(self.images), "answer": self.answer, "last_step": self.last_step}

    @classmethod
    def restore(cls, data: Any) -> AnswerViews:
        """From :meth:`snapshot`; ``ValueError`` on anything malformed or over the bounds."""
        if not isinstance(data, dict):
            raise ValueError("answer views state is not a map")
        av = cls(int(data["k"]))
        steps, rel, images = list(data["steps"]), list(data["relevance"]), list(data["images"])
        if not len(steps) == len(rel) == len(images) <= av.k:
            raise ValueError("answer views state: inconsistent or too many views")
        for s, r, im in zip(steps, rel, images, strict=True):
            av.steps.append(int(s))
            av.relevance.append(float(r))
            av.images.append(shrink(np.asarray(im)))
        ans = data.get("answer")
        av.answer = None if ans is None else [float(v) for v in ans]
        av.last_step = int(data.get("last_step", -1))
        return av


class AnswerViewsShell:
    """Mixin of :class:`services.mapper.service.MapperService` (module docstring). Needs ``self.settings`` and
    ``self.scorer()`` (the pool's ScoreRequest -> ScoreResult)."""

    settings: Any

    def scorer(self) -> Any: ...  # provided by MapperService

    def views_init(self) -> None:
        self.answer_views: dict[str, AnswerViews] = {}

    def _views_wanted(self, start: EpisodeStart) -> bool:
        return (self.settings.answer_memory_mode == "joint" and start.task is None
                and len(start.question.choices) >= 2)

    def views_start(self, start: EpisodeStart) -> None:
        if self._views_wanted(start):
            self.answer_views[start.episode_id] = AnswerViews(self.settings.answer_memory_views)
            log.info("episode %s: joint answer memory over the %d most relevant views", start.episode_id,
                     self.settings.answer_memory_views)

    def views_finish(self, episode_id: str) -> None:
        self.answer_views.pop(episode_id, None)

    def views_dump(self, episode_id: str, state: Any) -> Any:
        av = self.answer_views.get(episode_id)
        return state if av is None else snapshots.with_state_part(state, STATE_KEY, av.snapshot())

    @staticmethod
    def views_split(data: Any) -> tuple[Any, Any]:
        """Stored state -> (the rest, as the other loaders read it; this memory's snapshot or None)."""
        return snapshots.without_state_part(data, STATE_KEY)

    def views_restore(self, start: EpisodeStart, snapshot: Any) -> None:
        if not self._views_wanted(start):
            return
        if snapshot is not None:
            try:
                self.answer_views[start.episode_id] = AnswerViews.restore(snapshot)
                return
            except (ValueError, KeyError, TypeError) as exc:
                log.warning("episode %s: stored answer views unusable (%s); starting an empty memory",
                            start.episode_id, exc)
        self.views_start(start)

    def views_apply(self, em: Any, step: int, rgb: np.ndarray, result: ScoreResult) -> ScoreResult:
        """The step's result with the joint answer when the memory is on (else ``result`` unchanged)."""
        av = self.answer_views.get(em.episode_id)
        if av is None:
            return result
        if step > av.last_step:  # a step sent again is not offered twice
            changed = av.offer(step, result.relevance, rgb)
            if changed or av.answer is None:
                av.answer = self._views_ask(em, step, av)
        if av.answer is None:
            return result
        # the scorer's mode (logprobs / sampling) stays: the joint prompt is read the same way
        return result.model_copy(update={"answer_probs": list(av.answer)})

    def views_steps(self, episode_id: str) -> list[int]:
        """The steps the episode's current joint answer comes from (empty: no joint answer)."""
        av = self.answer_views.get(episode_id)
        return sorted(av.steps) if av is not None and av.answer is not None else []

    def _views_ask(self, em: Any, step: int, av: AnswerViews) -> list[float] | None:
        request = ScoreRequest(
            episode_id=em.episode_id, step=step,
            question=em.start.question.without_ground_truth(),
            rgb=av.images[-1], memory_views=list(av.images), seed=em.start.seed,
        )
        try:
            reply = self.scorer()(request)
        except Exception as exc:
            reply = exc
        if isinstance(reply, ScoreResult) and len(reply.answer_probs) == len(em.start.question.choices):
            return list(reply.answer_probs)
        reason = reply.reason if isinstance(reply, ErrorReply) else f"{type(reply).__name__}: {reply}"
        if isinstance(reply, Exception) and not isinstance(reply, ScorerError):  # no answer in time: next step
            log.warning("episode %s step %d: no joint answer this step (%s); per-view answer", em.episode_id,
                        step, reason)
            return None
        log.warning("episode %s step %d: joint answer refused, the episode keeps the per-view answer "
                    "(single view, or the stopper's fusion): %s", em.episode_id, step, reason)
        self.answer_views.pop(em.episode_id, None)  # once per episode: no joint request again
        return None
