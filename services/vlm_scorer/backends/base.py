"""The backend interface and the part every model backend shares.

A backend turns one :class:`eqa.messages.ScoreRequest` into :class:`Scores`: the answer distribution
f(x^t) over the choices, Rel(x^t) (Eq. 5), LSV_p per prompt point (Eq. 1) and GSV (Eq. 2).

:class:`ModelBackend` implements that once for next-token models: it builds the queries of
:mod:`services.vlm_scorer.prompts` and asks the subclass for the next-token probabilities of each query's
candidate tokens (:meth:`ModelBackend.candidate_probs`), normalised over the candidates.
"""

from __future__ import annotations

import abc
import logging
from dataclasses import dataclass, field

import numpy as np

from eqa.messages import MAX_CHOICES, NOT_LISTED_CHOICE, ScoreRequest
from services.vlm_scorer import prompts
from services.vlm_scorer.visual_prompt import annotate

log = logging.getLogger(__name__)

MIN_IMAGE_SIDE = 8
MAX_IMAGE_SIDE = 8192


class BadRequest(ValueError):  # noqa: N818
    """The request itself is wrong (answered with an error reply, never retried)."""


class BackendUnavailable(RuntimeError):  # noqa: N818
    """The backend cannot run (missing model directory, not a vision-language model, no logprobs...)."""


@dataclass
class Scores:
    answer_probs: list[float]
    relevance: float
    lsv: list[float] = field(default_factory=list)
    gsv: float = 0.0
    proposed_choices: list[str] = field(default_factory=list)
    annotated: np.ndarray | None = None  # the visually prompted image (for monitoring)
    # "logprobs" = read from the model's probabilities; "sampling" = frequencies of sampled
    # completions, each a multiple of ``resolution`` (1 / the fewest valid samples of the step's queries)
    mode: str = "logprobs"
    resolution: float = 0.0
    object_yes: float | None = None  # P(Yes) to PRESENCE / IN_ROOM (None: not asked)
    in_room: float | None = None


@dataclass
class ProbeItem:
    """The queries of one image: what :meth:`ModelBackend.candidate_probs` takes."""

    rgb: np.ndarray
    annotated: np.ndarray | None
    queries: list[prompts.Query]


def validate_request(req: ScoreRequest) -> None:
    """Raise :class:`BadRequest` with the reason for a request no backend can score."""
    rgb = req.rgb
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3:
        shape = getattr(rgb, "shape", None)
        raise BadRequest(f"rgb must be an HxWx3 uint8 image, got shape {shape}")
    if rgb.dtype != np.uint8:
        raise BadRequest(f"rgb must be uint8, got dtype {rgb.dtype}")
    h, w = rgb.shape[:2]
    if not (MIN_IMAGE_SIDE <= h <= MAX_IMAGE_SIDE and MIN_IMAGE_SIDE <= w <= MAX_IMAGE_SIDE):
        raise BadRequest(f"rgb is {w}x{h}; each side must be {MIN_IMAGE_SIDE}..{MAX_IMAGE_SIDE} pixels")
    if not req.question.text.strip():
        raise BadRequest("question text is empty")
    if len(req.question.choices) > MAX_CHOICES:
        raise BadRequest(f"{len(req.question.choices)} choices; at most {MAX_CHOICES} (letters A..Z)")
    if len(req.prompt_points) > MAX_CHOICES:
        raise BadRequest(f"{len(req.prompt_points)} prompt points; at most {MAX_CHOICES} (letters A..Z)")
    for p in req.prompt_points:
        if not (np.isfinite(p.u) and np.isfinite(p.v)):
            raise BadRequest(f"prompt point {p.label} has a non-finite pixel position")
    if req.instances is not None and req.instances.shape != (h, w):
        raise BadRequest(f"instances has shape {req.instances.shape}, expected {(h, w)} like rgb")
    if req.depth is not None and req.depth.shape != (h, w):
        raise BadRequest(f"depth has shape {req.depth.shape}, expected {(h, w)} like rgb")


def normalise(values: dict[str, float], candidates: tuple[str, ...] | list[str]) -> list[float]:
    """Probabilities of ``candidates`` normalised to sum to 1 (the paper's "normalized probability")."""
    p = np.array([max(float(values.get(c, 0.0)), 0.0) for c in candidates], dtype=np.float64)
    total = p.sum()
    if not np.isfinite(total) or total <= 0.0:
        return [1.0 / len(candidates)] * len(candidates)
    return (p / total).tolist()


class Backend(abc.ABC):
    """One scorer backend. ``score`` must be safe to call from one thread at a time."""

    name: str = "backend"
    model_name: str = ""

    @abc.abstractmethod
    def score(self, req: ScoreRequest) -> Scores:
        """The four numbers of one step. Raise :class:`BadRequest` for bad input."""

    def score_many(self, reqs: list[ScoreRequest]) -> list[Scores | Exception]:
        """Several steps (of several robots) at once: per request its :class:`Scores`, or the exception
        scoring it raised, so a bad request never fails its batch mates. This default scores them one by one;
        a backend that can merge them into one model call overrides it."""
        out: list[Scores | Exception] = []
        for req in reqs:
            try:
                out.append(self.score(req))
            except Exception as exc:
                out.append(exc)
        return out

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release resources."""


class ModelBackend(Backend):
    """A next-token model: the four prompts of a step go to :meth:`candidate_probs` together (one batch)."""

    @abc.abstractmethod
    def candidate_probs(
        self, rgb: np.ndarray, annotated: np.ndarray | None, queries: list[prompts.Query]
    ) -> list[dict[str, float]]:
        """For each query, the next-token probability (unnormalised is fine) of each candidate."""

    @abc.abstractmethod
    def generate(self, rgb: np.ndarray, text: str, max_new_tokens: int = 48) -> str:
        """Free text of the model for one prompt on the image (candidate proposals, VI-A)."""

    def propose_choices(self, req: ScoreRequest) -> list[str]:
        """Section VI-A: the model proposes answers; "An option not listed here" is added."""
        text = self.generate(req.rgb, prompts.propose_prompt(req.question))
        proposals = prompts.parse_proposals(text)
        if not proposals:
            log.warning("model proposed no parsable answer for %r (got %r)", req.question.text, text[:200])
        return [*proposals, NOT_LISTED_CHOICE]

    def candidate_probs_many(self, items: list[ProbeItem]) -> list[list[dict[str, float]]]:
        """:meth:`candidate_probs` of several images' queries; per item its list. A backend that can put all
        of them into one forward pass overrides this (hf); the default asks item by item."""
        return [self.candidate_probs(it.rgb, it.annotated, it.queries) for it in items]

    def prepare(self, req: ScoreRequest) -> tuple[ProbeItem, list[str]]:
        """The step's queries on its image (and the proposed choices when the question has none)."""
        validate_request(req)
        proposed: list[str] = []
        choices = list(req.question.choices)
        if not choices:
            proposed = self.propose_choices(req)
            choices = proposed
        points = req.prompt_points
        annotated = annotate(req.rgb, points) if len(points) >= 2 else None
        queries = prompts.step_queries(req.question, choices, len(points), req.presence)
        return ProbeItem(req.rgb, annotated, queries), proposed

    @staticmethod
    def finish(req: ScoreRequest, item: ProbeItem, proposed: list[str], raw: list[dict[str, float]]) -> Scores:
        """Scores from the candidates' next-token probabilities, each query normalised over its candidates."""
        by_name = {q.name: normalise(r, q.candidates) for q, r in zip(item.queries, raw, strict=True)}
        points = req.prompt_points
        lsv = by_name.get("lsv", [1.0] * len(points))  # one point: nothing to compare, LSV = 1
        return Scores(
            answer_probs=by_name["answer"],
            relevance=by_name["relevance"][0],
            lsv=lsv if points else [],
            gsv=by_name["gsv"][0],
            proposed_choices=proposed,
            annotated=item.annotated,
            object_yes=by_name["presence"][0] if "presence" in by_name else None,
            in_room=by_name["in_room"][0] if "in_room" in by_name else None,
        )

    def score(self, req: ScoreRequest) -> Scores:
        item, proposed = self.prepare(req)
        return self.finish(req, item, proposed, self.candidate_probs(item.rgb, item.annotated, item.queries))

    def score_many(self, reqs: list[ScoreRequest]) -> list[Scores | Exception]:
        """Every request's queries in one :meth:`candidate_probs_many` call. A request that cannot be
        prepared gets its exception; when the merged call fails, each request is scored alone, so only the
        one that fails gets an error. A subclass that overrides :meth:`score` (extra bookkeeping per step)
        keeps it: its requests are scored one by one."""
        if type(self).score is not ModelBackend.score:
            return super().score_many(reqs)
        out: list[Scores | Exception | None] = [None] * len(reqs)
        ready: list[tuple[int, ProbeItem, list[str]]] = []
        for i, req in enumerate(reqs):
            try:
                item, proposed = self.prepare(req)
            except Exception as exc:
                out[i] = exc
                continue
            ready.append((i, item, proposed))
        if ready:
            try:
                raws = self.candidate_probs_many([item for _, item, _ in ready])
            except Exception:
                log.warning("a merged batch of %d steps failed; scoring them one by one", len(ready), exc_info=True)
                for i, _, _ in ready:
                    try:
                        out[i] = self.score(reqs[i])
                    except Exception as exc:
                        out[i] = exc
            else:
                for (i, item, proposed), raw in zip(ready, raws, strict=True):
                    out[i] = self.finish(reqs[i], item, proposed, raw)
        return [o if o is not None else RuntimeError("not scored") for o in out]
