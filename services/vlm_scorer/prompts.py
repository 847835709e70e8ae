"""The text prompts of the four per-step queries (Explore-EQA section IV-C and V) and their candidates.

* answer distribution  f(x^t): the multiple-choice question, candidates = the choice letters A, B, ...
* question-image relevance Rel(x^t), Eq. 5: prompt s_Rel, candidates Yes / No, value = P(Yes).
  (The paper's prompt ends with "...given the current view?"; we append "Answer with Yes or No." so that
  the next token is one of the two candidates, as the paper does for the GSV prompt.)
* local semantic value LSV_p, Eq. 1: prompt s_LSV on the image annotated with lettered prompt points,
  candidates = the point letters.
* global semantic value GSV, Eq. 2: prompt s_GSV, candidates Yes / No, value = P(Yes).
* presence (the closed-world existence rule, ``services/stopper/closed_world.py``; not in either paper): prompt
  PRESENCE "is there an <object> in this image?" and IN_ROOM "is this image taken in the <room>?", candidates
  Yes / No, value = P(Yes); asked only when the request names an object (``ScoreRequest.presence``).
* questions without choices (section VI-A): prompt PROPOSE asks for short candidate answers, one per line;
  :data:`eqa.messages.NOT_LISTED_CHOICE` is appended to what the model proposes.
"""

from __future__ import annotations

from dataclasses import dataclass

from eqa.messages import PresenceQuery, Question, letters

SYSTEM = "You are a helpful assistant."

ANSWER_INSTRUCTION = "Answer with the option's letter from the given choices directly."

RELEVANCE = (
    "Consider the question: {question}. Are you confident about answering the question given the current "
    "view? Answer with Yes or No."
)

LSV = (
    "Consider the question: {question}, and you will explore the scene for answering it. Which direction "
    "(black letters on the image) would you explore then? Answer with a single letter."
)

GSV = (
    "Consider the question: {question}, and you will explore the scene for answering it. Is there any "
    "direction shown in the image worth exploring? Answer with Yes or No."
)

PROPOSE = (
    "Consider the question: {question}. Propose up to {n} different short possible answers given the current "
    "view, one per line, without numbering."
)

PRESENCE = "Is there {object} in this image? Answer with Yes or No."

IN_ROOM = "Is this image taken in the {room}? Answer with Yes or No."

YES_NO = ("Yes", "No")
MAX_PROPOSALS = 4


@dataclass(frozen=True)
class Query:
    """One next-token query: which image (plain or annotated), the prompt text and the candidate tokens."""

    name: str  # "answer" | "relevance" | "lsv" | "gsv" | "presence" | "in_room"
    text: str
    candidates: tuple[str, ...]
    annotated: bool = False


def answer_prompt(question: Question, choices: list[str]) -> str:
    opts = "\n".join(f"{k}) {c}" for k, c in zip(letters(len(choices)), choices, strict=True))
    return f"Question: {question.text.strip()}\nOptions:\n{opts}\n{ANSWER_INSTRUCTION}"


MEMORY_PREAMBLE = (
    "The {n} images are views of the same scene, taken by a robot while exploring it, most relevant first. "
    "Use all of them."
)
MAX_MEMORY_VIEWS = 16  # images in one answer-memory prompt (services/stopper/answer_memory.MAX_K)


def memory_answer_prompt(question: Question, choices: list[str], n_views: int) -> str:
    """The answer prompt over ``n_views`` images at once (answer memory): a preamble saying the
    images are views of one scene, then the usual multiple-choice question."""
    if not 1 <= n_views <= MAX_MEMORY_VIEWS:
        raise ValueError(f"an answer-memory prompt takes 1..{MAX_MEMORY_VIEWS} views, got {n_views}")
    return f"{MEMORY_PREAMBLE.format(n=n_views)}\n{answer_prompt(question, choices)}"


def _spoken(name: str) -> str:
    return " ".join(name.replace("_", " ").split())


def presence_queries(presence: PresenceQuery) -> list[Query]:
    """PRESENCE for the object (with its article: "a mug", "an apple", "any shoes" for a plural-only class)
    unless ``ask_object`` is False, and IN_ROOM when a room is named."""
    obj = _spoken(presence.object)
    article = "any" if obj.endswith("s") and not obj.endswith("ss") else "an" if obj[0] in "aeiou" else "a"
    out = [Query("presence", PRESENCE.format(object=f"{article} {obj}"), YES_NO)] if presence.ask_object else []
    if presence.room:
        out.append(Query("in_room", IN_ROOM.format(room=_spoken(presence.room)), YES_NO))
    return out


def step_queries(question: Question, choices: list[str], n_points: int,
                 presence: PresenceQuery | None = None) -> list[Query]:
    """The queries of one step, in batch order: answer, relevance, GSV, LSV when there are points, and the
    presence queries when ``presence`` is given."""
    q = question.text.strip().rstrip("?.! ") + "?"
    out = [
        Query("answer", answer_prompt(question, choices), tuple(letters(len(choices)))),
        Query("relevance", RELEVANCE.format(question=q), YES_NO),
        Query("gsv", GSV.format(question=q), YES_NO),
    ]
    if n_points >= 2:
        out.append(Query("lsv", LSV.format(question=q), tuple(letters(n_points)), annotated=True))
    if presence is not None:
        out += presence_queries(presence)
    return out


def propose_prompt(question: Question, n: int = MAX_PROPOSALS) -> str:
    q = question.text.strip().rstrip("?.! ") + "?"
    return PROPOSE.format(question=q, n=n)


def parse_proposals(text: str, n: int = MAX_PROPOSALS) -> list[str]:
    """Candidate answers from a model's free text: one per line (or comma-separated), cleaned, unique."""
    raw = (
        [p for line in text.splitlines() for p in line.split(",")]
        if "\n" not in text.strip()
        else text.splitlines()
    )
    out: list[str] = []
    for item in raw:
        s = item.strip().lstrip("-*0123456789.) ").strip().strip('"').strip()
        if not s or len(s) > 300 or not s.isprintable() or not any(ch.isalnum() for ch in s):
            continue
        if s.lower() not in {o.lower() for o in out}:
            out.append(s)
        if len(out) >= n:
            break
    return out
