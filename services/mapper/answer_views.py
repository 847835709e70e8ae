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
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eqa.messages import (
    MAX_MEMORY_VIEW_SIDE,
    MAX_MEMORY_VIEWS,
    EpisodeStart,
    Frame,
    ScoreRequest,
    ScoreResult,
)
from eqa.scorer_client import ScorerError
from services.mapper.episode_map import EpisodeMap
from services.mapper.extension import MapperContext, MapperExtension, StepOutputs, call_pool, failure

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
        memory = cls(int(data["k"]))
        steps, rel, images = list(data["steps"]), list(data["relevance"]), list(data["images"])
        if not len(steps) == len(rel) == len(images) <= memory.k:
            raise ValueError("answer views state: inconsistent or too many views")
        for s, r, im in zip(steps, rel, images, strict=True):
            memory.steps.append(int(s))
            memory.relevance.append(float(r))
            memory.images.append(shrink(np.asarray(im)))
        ans = data.get("answer")
        memory.answer = None if ans is None else [float(v) for v in ans]
        memory.last_step = int(data.get("last_step", -1))
        return memory


class AnswerViewsExtension(MapperExtension):
    """The joint answer memory as a mapper extension (module docstring, :mod:`services.mapper.extension`):
    per episode its :class:`AnswerViews` (``memories``)."""

    state_key = STATE_KEY

    def __init__(self, context: MapperContext) -> None:
        self.context = context
        self.memories: dict[str, AnswerViews] = {}

    def _wanted(self, start: EpisodeStart) -> bool:
        return (self.context.settings.answer_memory_mode == "joint" and start.task is None
                and len(start.question.choices) >= 2)

    def _new_memory(self, start: EpisodeStart) -> None:
        k = self.context.settings.answer_memory_views
        self.memories[start.episode_id] = AnswerViews(k)
        log.info("episode %s: joint answer memory over the %d most relevant views", start.episode_id, k)

    def begin(self, episode_map: EpisodeMap, part: Any | None, restored: bool) -> None:
        start = episode_map.start
        if not self._wanted(start):
            return
        if part is not None:
            try:
                self.memories[start.episode_id] = AnswerViews.restore(part)
                return
            except (ValueError, KeyError, TypeError) as exc:
                log.warning("episode %s: stored answer views unusable (%s); starting an empty memory",
                            start.episode_id, exc)
        self._new_memory(start)

    def finish(self, episode_map: EpisodeMap) -> None:
        self.memories.pop(episode_map.episode_id, None)

    def dump(self, episode_id: str) -> dict[str, Any] | None:
        memory = self.memories.get(episode_id)
        return None if memory is None else memory.snapshot()

    def scores(self, episode_map: EpisodeMap, frame: Frame, result: ScoreResult, out: StepOutputs,
               timing: dict[str, float], again: bool) -> ScoreResult:
        """The step's result with the joint answer when the memory is on (else ``result`` unchanged); the
        steps it comes from go to ``out``."""
        t0 = time.perf_counter()
        result = self._joint(episode_map, frame.step, frame.rgb, result)
        memory = self.memories.get(episode_map.episode_id)
        out.answer_views = sorted(memory.steps) if memory is not None and memory.answer is not None else []
        timing["answer_views"] = timing.get("answer_views", 0.0) + (time.perf_counter() - t0) * 1000.0
        return result

    def _joint(self, episode_map: EpisodeMap, step: int, rgb: np.ndarray, result: ScoreResult) -> ScoreResult:
        memory = self.memories.get(episode_map.episode_id)
        if memory is None:
            return result
        if step > memory.last_step:  # a step sent again is not offered twice
            changed = memory.offer(step, result.relevance, rgb)
            if changed or memory.answer is None:
                memory.answer = self._ask(episode_map, step, memory)
        if memory.answer is None:
            return result
        # the scorer's mode (logprobs / sampling) stays: the joint prompt is read the same way
        return result.model_copy(update={"answer_probs": list(memory.answer)})

    def _ask(self, episode_map: EpisodeMap, step: int, memory: AnswerViews) -> list[float] | None:
        request = ScoreRequest(
            episode_id=episode_map.episode_id, step=step,
            question=episode_map.start.question.without_ground_truth(),
            rgb=memory.images[-1], memory_views=list(memory.images), seed=episode_map.start.seed,
        )
        reply = call_pool(self.context.score(), request)
        if isinstance(reply, ScoreResult) and len(reply.answer_probs) == len(episode_map.start.question.choices):
            return list(reply.answer_probs)
        reason = failure(reply)
        if isinstance(reply, Exception) and not isinstance(reply, ScorerError):  # no answer in time: next step
            log.warning("episode %s step %d: no joint answer this step (%s); per-view answer", episode_map.episode_id,
                        step, reason)
            return None
        log.warning("episode %s step %d: joint answer refused, the episode keeps the per-view answer "
                    "(single view, or the stopper's fusion): %s", episode_map.episode_id, step, reason)
        self.memories.pop(episode_map.episode_id, None)  # once per episode: no joint request again
        return None
