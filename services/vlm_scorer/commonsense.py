"""Commonsense prior of the simulated perception model: which rooms hold which objects.

``ROOM_PRIOR[category][room_kind]`` is a plausibility in [0, 1] that an object of ``category`` is found in
a room of ``room_kind`` - general household knowledge of the kind a VLM has, written once by hand, never
derived from any scene. Categories missing from the table get :data:`UNKNOWN_PRIOR` everywhere.
``CONNECTORS`` are categories that lead elsewhere (worth exploring through when the wanted room is not in
view).
"""

from __future__ import annotations

import re

ROOM_KINDS = (
    "kitchen",
    "living_room",
    "dining_room",
    "bedroom",
    "bathroom",
    "hallway",
    "office",
    "laundry_room",
    "garage",
    "storage_room",
    "closet",
    "entryway",
    "staircase",
    "balcony",
    "gym",
    "playroom",
)

UNKNOWN_PRIOR = 0.3
CONNECTORS = frozenset({"door", "doorway", "stairs", "staircase", "arch", "opening", "corridor"})
STRUCTURE = frozenset({"floor", "wall", "ceiling", "window"})

_R = dict[str, float]


def _p(**kw: float) -> _R:
    return dict(kw)


ROOM_PRIOR: dict[str, _R] = {
    "sofa": _p(living_room=0.95, office=0.2, bedroom=0.15, playroom=0.3),
    "couch": _p(living_room=0.95, office=0.2, bedroom=0.15, playroom=0.3),
    "armchair": _p(living_room=0.8, bedroom=0.35, office=0.3),
    "coffee table": _p(living_room=0.9),
    "tv": _p(living_room=0.85, bedroom=0.45, playroom=0.3, gym=0.2),
    "television": _p(living_room=0.85, bedroom=0.45, playroom=0.3),
    "rug": _p(living_room=0.7, bedroom=0.55, dining_room=0.35, hallway=0.35, entryway=0.3, bathroom=0.3),
    "carpet": _p(living_room=0.7, bedroom=0.55, hallway=0.3),
    "lamp": _p(living_room=0.7, bedroom=0.75, office=0.55),
    "floor lamp": _p(living_room=0.75, bedroom=0.5, office=0.35),
    "fireplace": _p(living_room=0.85),
    "piano": _p(living_room=0.7, playroom=0.2),
    "bookshelf": _p(living_room=0.6, office=0.75, bedroom=0.35, playroom=0.3),
    "plant": _p(living_room=0.65, dining_room=0.4, office=0.4, balcony=0.6, entryway=0.35, kitchen=0.3),
    "potted plant": _p(living_room=0.65, dining_room=0.4, office=0.4, balcony=0.6, entryway=0.35),
    "painting": _p(living_room=0.6, dining_room=0.5, bedroom=0.5, hallway=0.45, office=0.35),
    "picture": _p(living_room=0.6, dining_room=0.5, bedroom=0.5, hallway=0.45, office=0.35),
    "clock": _p(living_room=0.5, kitchen=0.5, dining_room=0.4, office=0.35, hallway=0.3),
    "curtain": _p(living_room=0.65, bedroom=0.7, dining_room=0.4),
    "cushion": _p(living_room=0.8, bedroom=0.55),
    "pillow": _p(bedroom=0.9, living_room=0.55),
    "bed": _p(bedroom=0.98),
    "blanket": _p(bedroom=0.85, living_room=0.4),
    "nightstand": _p(bedroom=0.95),
    "wardrobe": _p(bedroom=0.85, closet=0.6, hallway=0.2),
    "dresser": _p(bedroom=0.85, closet=0.35),
    "mirror": _p(bathroom=0.8, bedroom=0.55, entryway=0.4, hallway=0.35, closet=0.3),
    "fridge": _p(kitchen=0.97, garage=0.2),
    "refrigerator": _p(kitchen=0.97, garage=0.2),
    "stove": _p(kitchen=0.98),
    "oven": _p(kitchen=0.97),
    "microwave": _p(kitchen=0.95),
    "dishwasher": _p(kitchen=0.97),
    "sink": _p(kitchen=0.8, bathroom=0.9, laundry_room=0.4),
    "kettle": _p(kitchen=0.95),
    "coffee machine": _p(kitchen=0.95, office=0.2),
    "toaster": _p(kitchen=0.95),
    "stool": _p(kitchen=0.75, dining_room=0.3, bathroom=0.2, garage=0.2),
    "kitchen island": _p(kitchen=0.95),
    "cabinet": _p(kitchen=0.85, bathroom=0.6, laundry_room=0.5, garage=0.4, living_room=0.3, office=0.3),
    "dining table": _p(dining_room=0.95, kitchen=0.5, living_room=0.25),
    "table": _p(dining_room=0.8, kitchen=0.55, living_room=0.55, office=0.4, balcony=0.3),
    "chair": _p(dining_room=0.8, kitchen=0.6, office=0.75, living_room=0.45, bedroom=0.3),
    "toilet": _p(bathroom=0.98),
    "bathtub": _p(bathroom=0.97),
    "shower": _p(bathroom=0.97),
    "towel": _p(bathroom=0.9, kitchen=0.4, laundry_room=0.4),
    "washing machine": _p(laundry_room=0.95, bathroom=0.35, kitchen=0.25, garage=0.25),
    "dryer": _p(laundry_room=0.95, garage=0.2),
    "laundry basket": _p(laundry_room=0.85, bedroom=0.4, bathroom=0.4, closet=0.35),
    "ironing board": _p(laundry_room=0.8, closet=0.4, bedroom=0.2),
    "desk": _p(office=0.95, bedroom=0.45, playroom=0.3),
    "computer": _p(office=0.95, bedroom=0.35),
    "monitor": _p(office=0.95, bedroom=0.3, living_room=0.2),
    "laptop": _p(office=0.85, bedroom=0.45, living_room=0.4),
    "printer": _p(office=0.9),
    "office chair": _p(office=0.95, bedroom=0.3),
    "car": _p(garage=0.95),
    "bicycle": _p(garage=0.85, hallway=0.3, balcony=0.2, storage_room=0.4),
    "tool box": _p(garage=0.85, storage_room=0.6, laundry_room=0.2),
    "toolbox": _p(garage=0.85, storage_room=0.6, laundry_room=0.2),
    "box": _p(storage_room=0.8, garage=0.6, closet=0.5, office=0.3),
    "suitcase": _p(bedroom=0.6, closet=0.7, storage_room=0.6, hallway=0.35, entryway=0.3),
    "shoe": _p(entryway=0.8, closet=0.7, bedroom=0.45, hallway=0.4),
    "shoe rack": _p(entryway=0.85, hallway=0.5, closet=0.5),
    "coat rack": _p(entryway=0.9, hallway=0.6),
    "umbrella": _p(entryway=0.8, hallway=0.5, closet=0.3),
    "treadmill": _p(gym=0.95, garage=0.3, living_room=0.15),
    "exercise bike": _p(gym=0.95, garage=0.3),
    "toy": _p(playroom=0.95, bedroom=0.5, living_room=0.35),
    "fire extinguisher": _p(kitchen=0.6, garage=0.5, hallway=0.45, staircase=0.4),
    "trash can": _p(kitchen=0.85, bathroom=0.55, office=0.5, garage=0.35),
    "air conditioner": _p(living_room=0.6, bedroom=0.6, office=0.4),
    "fan": _p(bedroom=0.55, living_room=0.5, office=0.35),
    "grill": _p(balcony=0.85, garage=0.3),
    "vase": _p(living_room=0.65, dining_room=0.6, entryway=0.35),
    "book": _p(living_room=0.55, office=0.7, bedroom=0.55, playroom=0.3),
    "basket": _p(laundry_room=0.5, living_room=0.35, bathroom=0.35, kitchen=0.35, closet=0.3),
    "bottle": _p(kitchen=0.75, dining_room=0.4, bathroom=0.35),
    "cup": _p(kitchen=0.8, dining_room=0.5, office=0.35, living_room=0.3),
    "mug": _p(kitchen=0.8, dining_room=0.5, office=0.4, living_room=0.3),
    "bowl": _p(kitchen=0.85, dining_room=0.55),
    "fruit bowl": _p(kitchen=0.85, dining_room=0.55),
    "stairs": _p(staircase=0.95, hallway=0.5, entryway=0.4, living_room=0.2),
    "door": _p(hallway=0.6, entryway=0.6, bedroom=0.4, bathroom=0.4),
    "tv stand": _p(living_room=0.9, bedroom=0.35),
    "sideboard": _p(dining_room=0.8, living_room=0.5, kitchen=0.3),
    "kitchen counter": _p(kitchen=0.98),
    "bathroom sink": _p(bathroom=0.98),
    "filing cabinet": _p(office=0.95, storage_room=0.3),
    "laundry shelf": _p(laundry_room=0.95),
    "workbench": _p(garage=0.9, storage_room=0.4),
    "storage shelf": _p(storage_room=0.9, garage=0.6, laundry_room=0.3),
    "bench": _p(entryway=0.6, hallway=0.55, dining_room=0.4, garage=0.3, balcony=0.4),
    "console table": _p(hallway=0.7, entryway=0.7, living_room=0.5),
    "side table": _p(living_room=0.8, bedroom=0.5),
    "backpack": _p(bedroom=0.6, entryway=0.6, hallway=0.45, office=0.4),
}

# room-kind spellings of other sources (the simulator's catalog says "laundry", "storage")
ROOM_ALIASES = {"laundry": "laundry_room", "storage": "storage_room", "living": "living_room"}


def canonical_room(room_kind: str | None) -> str | None:
    if room_kind is None:
        return None
    rk = room_kind.strip().lower().replace(" ", "_")
    return ROOM_ALIASES.get(rk, rk)


_PLURAL = re.compile(r"(?<=[a-z])(es|s)$")


def norm_category(name: str) -> str:
    """Lower-case, spaces for underscores, simple singular (``"towels"`` -> ``"towel"``)."""
    s = name.strip().lower().replace("_", " ").replace("-", " ")
    s = " ".join(s.split())
    if s in ROOM_PRIOR or s.endswith("ss"):
        return s
    for suffix in ("es", "s"):
        cut = s[: -len(suffix)]
        if s.endswith(suffix) and cut in ROOM_PRIOR:
            return cut
    return s[:-1] if s.endswith("s") and not s.endswith("ss") and len(s) > 3 else s


def room_display(room_kind: str) -> str:
    """``"living_room"`` -> ``"living room"``."""
    return room_kind.replace("_", " ").strip().lower()


def prior(category: str, room_kind: str | None) -> float:
    """P-like plausibility that ``category`` is in a ``room_kind`` room (the commonsense table)."""
    room_kind = canonical_room(room_kind)
    if room_kind is None:
        return UNKNOWN_PRIOR
    table = ROOM_PRIOR.get(norm_category(category))
    if table is None:
        return UNKNOWN_PRIOR
    return table.get(room_kind, 0.05)


def likely_rooms(category: str, n: int = 3) -> list[str]:
    """The ``n`` room kinds most likely to hold ``category`` (for proposing location answers)."""
    table = ROOM_PRIOR.get(norm_category(category), {})
    ranked = sorted(table, key=lambda k: -table[k])
    for rk in ("living_room", "kitchen", "bedroom", "bathroom"):
        if rk not in ranked:
            ranked.append(rk)
    return ranked[:n]


def known_categories() -> list[str]:
    """Category names the free-text fallback looks for, longest first ("coffee table" before "table")."""
    return sorted(ROOM_PRIOR, key=len, reverse=True)
