"""Ground truth for finished episodes: ``POST /v1/episodes/{id}/label``.

A user who learns the true answer of a question the robot answered (it looked in the bedroom afterwards) posts
it here. The label is stored beside the episode (:func:`eqa.store.episode_label_key`, an
:class:`eqa.messages.EpisodeLabel`); with the per-step scores the stopper kept for the episode it is a new
calibration data point: ``eqa calibrate --check --from-store`` tests whether the calibration table still fits
the model that scores today, ``eqa calibrate --from-store`` recalibrates from labelled episodes.

Checked here: the episode exists and belongs to the caller's tenant (another tenant's is "not found"), it has
finished (a label on a running episode would be read by nobody, and would leak the answer into nothing: 409),
and the answer is one of the episode's choices (a letter ``A``.. or a 0-based index; 422 otherwise). Posting
again replaces the label (a correction).
"""

from __future__ import annotations

import json
import logging

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from eqa.messages import MAX_CHOICES, EpisodeLabel, letters
from eqa.store import episode_label_key, episode_trace_key
from gateway.deps import ManagerDep, SubmitterDep
from gateway.errors import ConflictError, InvalidError, NotFoundError
from gateway.manager import TERMINAL, EpisodeManager
from gateway.routers.episodes import READ_ERRORS, EpisodeId, _episode_id, errors

log = logging.getLogger(__name__)
router = APIRouter(prefix="/v1", tags=["episodes"])


class LabelRequest(BaseModel):
    """The true answer of a finished episode's question."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={"examples": [{"answer": "B"}, {"answer": 1}]})
    answer: str | int = Field(description="a choice letter ('B') or a 0-based choice index (1); not a boolean")


def _choices(manager: EpisodeManager, episode_id: str, asked: list[str]) -> list[str]:
    """The episode's choices: the question's, else the ones the scorer proposed (kept in the stopper's trace)."""
    if asked:
        return asked
    raw = manager.store.get(episode_trace_key(episode_id))
    if raw is None:
        return []
    try:
        choices = json.loads(raw).get("choices") or []
    except (ValueError, AttributeError):
        return []
    return [str(c) for c in choices][:MAX_CHOICES]


def _letter(answer: str | int, choices: list[str]) -> str:
    labels = letters(len(choices))
    if isinstance(answer, int):
        if not 0 <= answer < len(choices):
            raise InvalidError(f"answer index {answer} is outside the episode's {len(choices)} choices "
                               f"(0..{len(choices) - 1})", field="answer")
        return labels[answer]
    letter = answer.strip().upper()
    if letter not in labels:
        raise InvalidError(f"answer {answer!r} is not one of the episode's choice letters "
                           f"({', '.join(labels)})", field="answer")
    return letter


def store_label(manager: EpisodeManager, episode_id: str, answer: str | int, caller: object) -> EpisodeLabel:
    episode = manager.load(episode_id)
    if episode is None or not caller.sees(episode.owner):  # type: ignore[attr-defined]
        raise NotFoundError(f"no episode {episode_id!r}")
    if episode.status.state not in TERMINAL:
        raise ConflictError(f"episode {episode_id} has not finished ({episode.status.state}): label it once it ended")
    choices = _choices(manager, episode_id, list(episode.start.question.choices))
    if len(choices) < 2:
        raise ConflictError(f"episode {episode_id} has no choices to label (it ended before its first step)")
    letter = _letter(answer, choices)
    label = EpisodeLabel(episode_id=episode_id, answer=letter, answer_text=choices[letters(len(choices)).index(letter)],
                         question_id=episode.start.question.id, tenant=episode.owner)
    manager.store.set(episode_label_key(episode_id), label.model_dump_json().encode())
    log.info("episode %s labelled %s by tenant %s", episode_id, letter, episode.owner)
    return label


@router.post(
    "/episodes/{episode_id}/label",
    summary="Give the true answer of a finished episode (new calibration data)",
    responses=errors(404, 409, 413, *READ_ERRORS),
)
async def label_episode(episode_id: EpisodeId, body: LabelRequest, manager: ManagerDep,
                        caller: SubmitterDep) -> EpisodeLabel:
    return await run_in_threadpool(store_label, manager, _episode_id(episode_id), body.answer, caller)
