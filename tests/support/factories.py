"""Messages the tests build again and again, with defaults a test overrides where it matters."""

from __future__ import annotations

from typing import Any

from eqa.messages import EpisodeStart, Question


def question(**fields: Any) -> Question:
    """A two-choice question about scene ``s`` (answer A) unless ``fields`` say otherwise."""
    base: dict[str, Any] = {"text": "Is it?", "choices": ["yes", "no"], "scene": "s", "answer": "A"}
    return Question(**{**base, **fields})


def episode_start(q: Question | None = None, **fields: Any) -> EpisodeStart:
    """An ``EpisodeStart`` of episode ``e`` on robot ``r`` for ``q`` (default :func:`question`), 10 steps."""
    base: dict[str, Any] = {"episode_id": "e", "robot": "r", "question": q or question(), "max_steps": 10}
    return EpisodeStart(**{**base, **fields})
