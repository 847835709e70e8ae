"""Task instructions in words -> class names (HELIOS section 4.1: "Move (object) from the (start_receptacle) to
the (goal_receptacle)"; section 4.2: "Find a (object)").

The classes stay open-vocabulary: a phrase becomes a class name by lower-casing, dropping articles and joining
words with ``_`` ("the kitchen counter" -> ``kitchen_counter``). A leading colour word is kept apart
(``object_color``) because detectors are asked about classes, not colours. Anything that does not fit one of
the two forms raises :class:`InstructionError` saying which forms are understood.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

MAX_INSTRUCTION_CHARS = 500
MAX_CLASS_WORDS = 5
ARTICLES = ("the", "a", "an", "some", "my")
COLOR_WORDS = frozenset({"red", "green", "blue", "yellow", "orange", "purple", "pink", "white", "black", "gray",
                         "grey", "brown", "beige"})

_MOVE = re.compile(r"^\s*(?:please\s+)?(?:move|bring|take|put)\s+(?P<obj>.+?)\s+from\s+(?P<start>.+?)\s+"
                   r"(?:to|onto|on|into)\s+(?P<goal>.+?)\s*[.!]?\s*$", re.IGNORECASE)
_FIND = re.compile(r"^\s*(?:please\s+)?(?:find|search for|look for|go to)\s+(?P<obj>.+?)\s*[.!]?\s*$", re.IGNORECASE)
_WORD = re.compile(r"^[a-z0-9-]+$")


class InstructionError(ValueError):
    """An instruction the parser does not understand; the message names the accepted forms."""


@dataclass(frozen=True)
class ParsedInstruction:
    kind: str  # "pick_place" | "find_object"
    object: str
    start_receptacle: str | None = None
    goal_receptacle: str | None = None
    object_color: str | None = None


def class_name(phrase: str) -> tuple[str, str | None]:
    """``"the red mug"`` -> ``("mug", "red")``; ``"the kitchen counter"`` -> ``("kitchen_counter", None)``."""
    words = [w for w in re.split(r"[\s_]+", phrase.strip().lower()) if w]
    while words and words[0] in ARTICLES:
        words.pop(0)
    color = None
    if len(words) > 1 and words[0] in COLOR_WORDS:
        color = "gray" if words[0] == "grey" else words[0]
        words.pop(0)
    if not words or len(words) > MAX_CLASS_WORDS or not all(_WORD.match(w) for w in words):
        raise InstructionError(f"{phrase!r} is not a class name (1-{MAX_CLASS_WORDS} plain words, e.g. 'the mug')")
    return "_".join(words), color


def parse_instruction(text: str) -> ParsedInstruction:
    """Parse "Move X from the Y to the Z" or "Find a X" (see the module doc)."""
    if not isinstance(text, str) or not text.strip():
        raise InstructionError("the instruction is empty")
    if len(text) > MAX_INSTRUCTION_CHARS:
        raise InstructionError(f"the instruction is longer than {MAX_INSTRUCTION_CHARS} characters")
    m = _MOVE.match(text)
    if m:
        obj, color = class_name(m.group("obj"))
        start, _ = class_name(m.group("start"))
        goal, _ = class_name(m.group("goal"))
        return ParsedInstruction("pick_place", obj, start, goal, color)
    m = _FIND.match(text)
    if m:
        obj, color = class_name(m.group("obj"))
        return ParsedInstruction("find_object", obj, object_color=color)
    raise InstructionError(f"cannot read {text!r}: write 'Move the <object> from the <start receptacle> to the "
                           f"<goal receptacle>' or 'Find a <object>'")
