"""Questions about generated houses in the five HM-EQA categories, and the fixed benchmark.

Categories and their shares in HM-EQA (Explore-EQA section VI): identification 16 %, counting 16 %,
existence 22 %, state 20 %, location 26 %. Yes/no questions use the HM-EQA form: four choices, "Yes" and
"No" at random places and two "(Do not choose this option)" paddings. Every question carries its ground
truth (``answer``), the ids of the objects that are the evidence (empty for a "no" existence question:
there the whole room is the evidence), ``max_steps = int(3 * sqrt(floor area))`` (appendix B), a start
pose with 0.5 m clearance, and ``query``: the structured parse of the text (never the answer) that the
oracle scorer reads instead of parsing English.

Only objects that are visible from at least one pose the robot can reach are asked about: for each object
rays are cast from reachable camera positions (1.5 m high) to points on it, within the vertical field of
view of the tilted camera; :func:`services.sim.visibility.witness_poses` returns one such pose per visible object.
"""

from __future__ import annotations

import logging
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eqa.budget import max_steps_for
from eqa.messages import PADDING_CHOICE, Pose2D, Question
from services.sim import catalog
from services.sim.benchfile import load_json, save_json
from services.sim.catalog import OPPOSITE_STATE, PLURAL_ONLY, display_name, plural
from services.sim.library import load_or_generate
from services.sim.motion import START_CLEARANCE, sample_start_pose
from services.sim.scene import InstanceInfo, Scene
from services.sim.visibility import VIEW_MAX, VIEW_MIN, witness_poses  # noqa: F401 (public here too)

log = logging.getLogger(__name__)

CATEGORIES = ("identification", "counting", "existence", "state", "location")
SHARES = {"identification": 0.16, "counting": 0.16, "existence": 0.22, "state": 0.20, "location": 0.26}
NUMBER_WORDS = ("None", "One", "Two", "Three", "Four", "Five", "Six", "Seven", "Eight", "Nine", "Ten")
BENCHMARK_SIZE = 500
CALIBRATION_SIZE = 300
QUESTIONS_PER_HOUSE = 3


# ---- question generation ----------------------------------------------------------------------------------


def _yes_no(rng: np.random.Generator, yes: bool, yes_text: str = "Yes", no_text: str = "No") -> tuple[list[str], str]:
    """HM-EQA yes/no choices: Yes and No at two random places of four, paddings elsewhere."""
    slots = rng.permutation(4)
    choices = [PADDING_CHOICE] * 4
    choices[int(slots[0])] = yes_text
    choices[int(slots[1])] = no_text
    answer = "ABCD"[int(slots[0]) if yes else int(slots[1])]
    return choices, answer


def _shuffled(rng: np.random.Generator, correct: str, distractors: list[str]) -> tuple[list[str], str]:
    choices = [correct, *distractors[:3]]
    order = rng.permutation(len(choices))
    out = [choices[int(k)] for k in order]
    return out, "ABCD"[out.index(correct)]


def _article(word: str) -> str:
    return ("an " if word[0] in "aeiou" else "a ") + word


def _pick(rng: np.random.Generator, items: list) -> object:
    return items[int(rng.integers(0, len(items)))]


# one generated question before it becomes a Question: text, choices, answer letter, evidence ids, parsed query
_Draft = tuple[str, list[str], str, list[int], dict[str, str]]


@dataclass
class _Inventory:
    """What the question makers read of a house: its objects by category, room kind and colour, and which
    of them are visible from a reachable pose."""

    objects: list[InstanceInfo]
    visible: dict[int, Pose2D]  # object id -> a reachable pose it is visible from
    kinds_in_house: Counter[str]
    unique_kinds: set[str]
    by_cat_kind: dict[tuple[str, str], list[int]]
    by_cat: dict[str, list[int]]
    by_cat_color: dict[tuple[str, str], list[int]]
    small: list[InstanceInfo]  # visible small objects
    singles: list[InstanceInfo]  # "the X in the Y": the only X in the only room of kind Y

    @classmethod
    def of(cls, scene: Scene, visible: dict[int, Pose2D]) -> _Inventory:
        objs = scene.objects()
        kinds_in_house = Counter(r.kind for r in scene.rooms)
        unique_kinds = {k for k, n in kinds_in_house.items() if n == 1}
        by_cat_kind: dict[tuple[str, str], list[int]] = defaultdict(list)
        by_cat: dict[str, list[int]] = defaultdict(list)
        by_cat_color: dict[tuple[str, str], list[int]] = defaultdict(list)
        for o in objs:
            by_cat_kind[(o.category, o.room_kind or "")].append(o.id)
            by_cat[o.category].append(o.id)
            by_cat_color[(o.category, o.attributes.get("color", ""))].append(o.id)
        small = [o for o in objs if o.category in catalog.SMALL_OBJECTS and o.id in visible]
        singles = [o for o in small
                   if o.room_kind in unique_kinds and len(by_cat_kind[(o.category, o.room_kind)]) == 1]
        return cls(objs, visible, kinds_in_house, unique_kinds, by_cat_kind, by_cat, by_cat_color, small, singles)


def _identification(inv: _Inventory, rng: np.random.Generator, per_category: int) -> list[_Draft]:
    """The colour of a unique object in a unique room."""
    out: list[_Draft] = []
    for o in rng.permutation(len(inv.singles))[: per_category * 2]:
        ob = inv.singles[int(o)]
        color = ob.attributes["color"]
        others = [c for c in catalog.SMALL_OBJECTS[ob.category].colors if c != color]
        others += [c for c in catalog.COLORS if c != color and c not in others]
        distract = [others[int(k)] for k in rng.permutation(min(len(others), 6))[:3]]
        if len(distract) < 3:
            continue
        room = display_name(ob.room_kind or "")
        text = str(_pick(rng, [f"What color is the {display_name(ob.category)} in the {room}?",
                               f"Which color is the {display_name(ob.category)} in the {room}?"]))
        choices, answer = _shuffled(rng, color.capitalize(), [d.capitalize() for d in distract])
        q = {"type": "identification", "category": ob.category, "room_kind": ob.room_kind or "",
             "attribute": "color"}
        out.append((text, choices, answer, [ob.id], q))
    return out


def _counting(inv: _Inventory, rng: np.random.Generator, per_category: int) -> list[_Draft]:
    """How many of a category in a unique room, or in the whole house (all of them visible)."""
    count_cands = []
    for (cat, kind), ids in inv.by_cat_kind.items():
        if kind in inv.unique_kinds and 1 <= len(ids) <= 5 and all(i in inv.visible for i in ids):
            count_cands.append((cat, kind, ids))
    for cat, ids in inv.by_cat.items():
        if 2 <= len(ids) <= 6 and all(i in inv.visible for i in ids):
            count_cands.append((cat, "", ids))
    out: list[_Draft] = []
    for k in rng.permutation(len(count_cands))[:per_category]:
        cat, kind, ids = count_cands[int(k)]
        n = len(ids)
        where = f"in the {display_name(kind)}" if kind else "in the house"
        text = f"How many {plural(cat)} are there {where}?"
        pool = [w for m, w in enumerate(NUMBER_WORDS[:8]) if m != n and m >= 1]
        distract = [pool[int(j)] for j in rng.permutation(len(pool))[:3]]
        choices, answer = _shuffled(rng, NUMBER_WORDS[n], distract)
        q = {"type": "counting", "category": cat}
        if kind:
            q["room_kind"] = kind
        out.append((text, choices, answer, sorted(ids), q))
    return out


def _existence(inv: _Inventory, rng: np.random.Generator, per_category: int) -> list[_Draft]:
    """Is there an X in the Y (yes: a visible X there; no: none anywhere in that room kind)."""
    out: list[_Draft] = []
    for _ in range(per_category):
        yes = bool(rng.random() < 0.5)
        if yes and inv.singles:
            ob = inv.singles[int(rng.integers(0, len(inv.singles)))]
            cat, kind, ev = ob.category, ob.room_kind or "", [ob.id]
        else:
            kinds = sorted(inv.unique_kinds)
            if not kinds:
                continue
            kind = str(_pick(rng, kinds))
            absent = [c for c in catalog.SMALL_OBJECTS if not inv.by_cat_kind.get((c, kind))]
            if not absent:
                continue
            cat, ev, yes = str(_pick(rng, absent)), [], False
        if cat in PLURAL_ONLY:
            text = f"Are there {display_name(cat)} in the {display_name(kind)}?"
        else:
            text = f"Is there {_article(display_name(cat))} in the {display_name(kind)}?"
        choices, answer = _yes_no(rng, yes)
        out.append((text, choices, answer, ev, {"type": "existence", "category": cat, "room_kind": kind}))
    return out


def _state(inv: _Inventory, rng: np.random.Generator, per_category: int) -> list[_Draft]:
    """Is the X in the Y <state>?"""
    stateful = [o for o in inv.singles if "state" in o.attributes]
    out: list[_Draft] = []
    for k in rng.permutation(len(stateful))[:per_category]:
        ob = stateful[int(k)]
        actual = ob.attributes["state"]
        yes = bool(rng.random() < 0.5)
        asked = actual if yes else OPPOSITE_STATE[actual]
        text = f"Is the {display_name(ob.category)} in the {display_name(ob.room_kind or '')} {asked}?"
        choices, answer = _yes_no(rng, yes)
        q = {"type": "state", "category": ob.category, "room_kind": ob.room_kind or "", "attribute": "state",
             "value": asked}
        out.append((text, choices, answer, [ob.id], q))
    return out


def _location(inv: _Inventory, rng: np.random.Generator, per_category: int) -> list[_Draft]:
    """Where is the <colour> X (the only one of that colour in the house)."""
    located = [o for o in inv.small if len(inv.by_cat_color[(o.category, o.attributes.get("color", ""))]) == 1]
    out: list[_Draft] = []
    for k in rng.permutation(len(located))[:per_category]:
        ob = located[int(k)]
        kind = ob.room_kind or ""
        color = ob.attributes["color"]
        others = [r for r in dict.fromkeys(sorted(inv.kinds_in_house)) if r != kind]
        others += [r for r in catalog.ROOM_KINDS if r != kind and r not in others]
        distract = [others[int(j)] for j in rng.permutation(min(len(others), 5))[:3]]
        verb = "are" if ob.category in PLURAL_ONLY else "is"
        text = str(_pick(rng, [f"Where {verb} the {color} {display_name(ob.category)}?",
                               f"In which room did I leave the {color} {display_name(ob.category)}?"]))
        wrong = [f"In the {display_name(r)}" for r in distract]
        choices, answer = _shuffled(rng, f"In the {display_name(kind)}", wrong)
        q = {"type": "location", "category": ob.category, "color": color}
        out.append((text, choices, answer, [ob.id], q))
    return out


# the question makers in the order they draw from the generator (the order fixes every benchmark)
_MAKERS = {"identification": _identification, "counting": _counting, "existence": _existence, "state": _state,
           "location": _location}


def generate_questions(scene: Scene, rng: np.random.Generator, per_category: int = 2) -> list[Question]:
    """Up to ``per_category`` questions of each of the five categories about ``scene`` (fewer when the
    house offers no fitting object); every answer is ground truth from the scene graph and every evidence
    object is visible from a reachable pose."""
    start = sample_start_pose(scene, rng, START_CLEARANCE)
    inv = _Inventory.of(scene, witness_poses(scene, start))
    max_steps = max_steps_for(scene.floor_area_m2)
    drafts = {category: make(inv, rng, per_category) for category, make in _MAKERS.items()}
    questions = []
    for cat in CATEGORIES:
        for k, (text, choices, answer, ev, q) in enumerate(drafts[cat][:per_category]):
            questions.append(Question(
                id=f"{scene.id}-{cat[:3]}{k}", text=text, choices=choices, scene=scene.id, category=cat,
                query=q, answer=answer, evidence_ids=ev, start_pose=start, max_steps=max_steps,
                targets=question_targets(scene, ev, q.get("room_kind")),
            ))
    return questions


def question_targets(scene: Scene, evidence_ids: list[int], room_kind: str | None) -> list[tuple[float, float]]:
    """Ground-truth floor positions for the benchmark-only yardstick strategies (``Question.targets``): the
    evidence objects' centres, or the centres of the asked room kind's rooms when no object is the evidence
    (a "no" existence question: the room is the evidence). No scorer reads them."""
    pts = [(round(float(scene.instances[i].position[0]), 3), round(float(scene.instances[i].position[1]), 3))
           for i in evidence_ids if i in scene.instances]
    if not pts and room_kind:
        pts = [(round(r.center[0], 3), round(r.center[1], 3)) for r in scene.rooms if r.kind == room_kind]
    return pts[:64]


# ---- the fixed benchmark -----------------------------------------------------------------------------------


@dataclass
class Benchmark:
    """A fixed question set: ``calibration`` (300 questions, for conformal calibration) and ``test`` (200)."""

    seed: int
    calibration: list[Question] = field(default_factory=list)
    test: list[Question] = field(default_factory=list)

    @property
    def questions(self) -> list[Question]:
        return self.calibration + self.test

    @property
    def scenes(self) -> list[str]:
        return sorted({q.scene for q in self.questions})

    def to_json(self) -> dict[str, object]:
        return {
            "seed": self.seed,
            "calibration": [q.model_dump(mode="json") for q in self.calibration],
            "test": [q.model_dump(mode="json") for q in self.test],
        }

    def save(self, path: Path) -> Path:
        return save_json(self.to_json(), path)

    @classmethod
    def load(cls, path: Path) -> Benchmark:
        data = load_json(path)
        return cls(seed=int(data["seed"]), calibration=[Question.model_validate(q) for q in data["calibration"]],
                   test=[Question.model_validate(q) for q in data["test"]])


def category_round_robin(questions: list[Question], limit: int | None,
                          categories: Sequence[str] | None = None) -> list[Question]:
    """At most ``limit`` of ``questions`` (all when None) keeping the category mix: one of each category in turn
    (each in its own order), the categories in sorted order, or only ``categories`` in that order when given."""
    by_category: dict[str, list[Question]] = {c: [] for c in categories or ()}
    for q in questions:
        if categories is None or (q.category or "") in by_category:
            by_category.setdefault(q.category or "", []).append(q)
    turn = list(categories) if categories is not None else sorted(by_category)
    total = sum(len(qs) for qs in by_category.values())
    limit = total if limit is None else min(limit, total)
    out: list[Question] = []
    while len(out) < limit:
        for category in turn:
            if by_category[category] and len(out) < limit:
                out.append(by_category[category].pop(0))
    return out


def benchmark_scene_id(seed: int, index: int) -> str:
    return f"gen-{seed * 10000 + index:05d}"


def benchmark_candidates(seed: int, index: int, scenes_dir: Path | None = None) -> dict[str, list[Question]]:
    """The questions house ``index`` of benchmark ``seed`` offers, per category, in the benchmark's order: the
    benchmark takes the first one of a category; ``eqa ask``'s demo reproduces one without the whole benchmark."""
    from services.sim.housegen import generate_house

    sid = benchmark_scene_id(seed, index)
    scene = load_or_generate(sid, scenes_dir) if scenes_dir is not None else generate_house(seed * 10000 + index)
    cands: dict[str, list[Question]] = defaultdict(list)
    for q in generate_questions(scene, np.random.default_rng([seed, index, 11])):
        cands[q.category or ""].append(q)
    return cands


def benchmark(seed: int = 0, scenes_dir: Path | None = None, size: int = BENCHMARK_SIZE,
              calibration: int = CALIBRATION_SIZE) -> Benchmark:
    """The fixed benchmark of ``seed``: ``size`` questions in the HM-EQA category proportions over
    ``size / 3`` generated houses (houses ``gen-{seed*10000 + i}``), split ``calibration`` / rest with the
    same proportions on both sides. Deterministic; houses are cached in ``scenes_dir`` when given."""

    quota = {c: round(SHARES[c] * size) for c in CATEGORIES}
    quota[CATEGORIES[-1]] += size - sum(quota.values())
    picked: dict[str, list[Question]] = defaultdict(list)
    index = 0
    while sum(len(v) for v in picked.values()) < size:
        if index > size * 2:
            raise RuntimeError("benchmark: houses ran out of questions for the category quotas")
        cands = benchmark_candidates(seed, index, scenes_dir)
        index += 1
        order = sorted(CATEGORIES, key=lambda c: -(quota[c] - len(picked[c])) / quota[c])
        taken = 0
        for cat in order:
            if taken >= QUESTIONS_PER_HOUSE or len(picked[cat]) >= quota[cat] or not cands[cat]:
                continue
            picked[cat].append(cands[cat][0])
            taken += 1
    split_rng = np.random.default_rng([seed, 99])
    cal, test = [], []
    for cat in CATEGORIES:
        qs = picked[cat]
        n_cal = round(len(qs) * calibration / size)
        order = split_rng.permutation(len(qs))
        cal += [qs[int(k)] for k in order[:n_cal]]
        test += [qs[int(k)] for k in order[n_cal:]]
    # rounding per category may leave the split off by one; move questions to hit the exact sizes
    while len(cal) > calibration:
        test.append(cal.pop())
    while len(cal) < calibration:
        cal.append(test.pop(0))
    return Benchmark(seed=seed, calibration=cal, test=test)
