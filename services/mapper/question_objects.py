"""The HELIOS object layer in a question episode: track the question's target class.

For an existence or counting question (``question.query`` names the ``category`` and maybe a ``room_kind``) the
mapper keeps an :class:`~services.mapper.object_map.ObjectMap` with the one target class (detector threshold
od_g, HELIOS Table 3), fuses each frame's detections into it (the layer is used as is, not restructured) and
reports, per step, an :class:`~services.stopper.object_evidence.ObjectEvidence`: the ``Psi`` (HELIOS Eq. 7) of
the target-class instances whose centre lies in the asked region, and the explored share of that region.

The region is the rooms of the asked kind (or the whole house) as rectangles in world coordinates. The robot
needs a room layout for that; here it is the scene's floor plan (:attr:`services.sim.scene.Scene.rooms`), i.e.
the robot is assumed to know the floor plan (not the objects). That is a simplification: a real robot would
segment rooms from its own map, with errors this evaluation does not have.

In the product (the mapper service, :class:`QuestionObjectsExtension`): a question typed by a user carries no
``query``; :func:`parse_question` reads the target from the text ("How many chairs are there in the kitchen?",
"Is there a mug in the office?", "Are there any towels in the bathroom?"). The detector is open-vocabulary
(DETIC), so the class is the noun phrase itself (:func:`eqa.instructions.class_name`, singular). The mapper
has no floor plan (the :class:`~eqa.messages.EpisodeStart` carries none and the mapper must not read the
simulator's scene): the region is then the whole map (``rects=None``), the explored share is the observed
share of the mapped area's bounding box, and the existence prior refers to the whole explored map, not to the
asked room. The room kind is parsed and reported but does not narrow the whole-map region. With the whole map
as the region only existence questions get evidence (:data:`WHOLE_MAP_CATEGORIES`, measured: counting did not
gain).

Counting across views (``EQA_ANSWER_COUNTING=views``, the default): a counting question's region is instead the
asked room's extent on the robot's own map (:class:`~services.mapper.room_extent.RoomExtent`, voted by the
scorer's IN_ROOM answers, which the extension asks for with the step's score request; the whole viewed map when
no room is asked), an instance counts when its centre is within ``REACH_CELLS`` of it (:meth:`QuestionObjects.in_room`)
and the unexplored share is the room's open share (:func:`count_evidence`):
rule 2 of ``docs/results/closed-world-answers.md``, where it was measured.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from eqa.instructions import InstructionError, class_name
from eqa.messages import (
    MAX_EVIDENCE_INSTANCES,
    DetectRequest,
    DetectResult,
    EpisodeStart,
    Frame,
    GridSpec,
    ObjectEvidence,
    PresenceQuery,
    Question,
    ScoreRequest,
    ScoreResult,
)
from services.mapper.episode_map import EpisodeMap
from services.mapper.extension import MapperContext, MapperExtension, StepOutputs, call_pool, failure
from services.mapper.room_extent import RoomExtent, room_vote

log = logging.getLogger(__name__)

CATEGORIES = ("counting", "existence")  # the question categories the class-level layer can answer (not colours)
# The categories that get evidence when the region is the whole map (no floor plan: the product). Chosen on the
# tuning seed 11 (eqa_app/benches/object_evidence_region.py, n = 48): whole-map evidence vs VLM-only, existence
# +16.7 points, counting +0.0 (the count of the class anywhere in the map is not the count in the asked room,
# and the bounding-box explored share is a poor stand-in for the room's). Seeds 1-3: existence +14.6, counting
# -8.3 points (bench/results/object_evidence_region.json).
WHOLE_MAP_CATEGORIES = ("existence",)

Rect = tuple[float, float, float, float]  # x0, y0, x1, y1


MAX_PARSED_CHARS = 300  # longer texts are not parsed (a question about one object class is short)
# Nouns after "how many" that are no detectable object class (structure, time, quantities).
NOT_OBJECTS = frozenset({"room", "floor", "wall", "ceiling", "storey", "story", "level", "time", "minute", "hour",
                         "second", "day", "year", "step", "meter", "metre", "foot", "feet", "inch", "kind",
                         "type", "color", "colour", "way", "thing", "object", "item"})
PLURAL_ONLY = frozenset({"shoes", "glasses", "scissors", "pants", "jeans", "clothes", "stairs"})
WHOLE_HOUSE = frozenset({"house", "home", "apartment", "flat", "building"})
_PHRASE = r"(?P<obj>[a-z][a-z -]{0,60}?)"
_ROOM = r"(?:\s+(?:in|inside)\s+(?:the|this|my|our)\s+(?P<room>[a-z][a-z ]{0,40}?))?"
_END = r"\s*\??\s*$"
_COUNT = re.compile(r"^\s*how\s+many\s+" + _PHRASE + r"(?:\s+(?:are|is)(?:\s+there)?|\s+(?:do|does|can)\s+"
                    r"(?:you|we|it)\s+(?:see|find))?" + _ROOM + _END)
_EXIST = re.compile(r"^\s*(?:is|are)\s+there\s+(?:(?:any|some|an|a)\s+)?" + _PHRASE + _ROOM + _END)
# Words that are no part of a class name: a phrase holding one is a sentence the forms above do not cover.
FUNCTION_WORDS = frozenset({"are", "is", "was", "were", "be", "did", "do", "does", "you", "we", "i", "it", "they",
                            "the", "a", "an", "on", "of", "in", "at", "here", "there", "have", "has", "live", "can",
                            "could", "see", "find", "to", "with", "and", "or", "not", "no", "under", "near"})


def singular(word: str) -> str:
    """A simple English singular of a class's last word (``chairs`` -> ``chair``, ``boxes`` -> ``box``,
    ``shelves`` -> ``shelf``); plural-only words stay (``shoes``)."""
    if word in PLURAL_ONLY or word.endswith(("ss", "us", "is")) or len(word) <= 3:
        return word
    if word.endswith("ies"):
        return word[:-3] + "y"
    if word.endswith("ves"):
        return word[:-3] + "f"
    if word.endswith(("ses", "xes", "ches", "shes", "zes")):
        return word[:-2]
    return word[:-1] if word.endswith("s") else word


def parse_question(text: str) -> tuple[str, str, str | None] | None:
    """``(category, class, room kind or None)`` from a question's words, or None when it is not one of the
    forms the layer can answer:

    - counting: "How many <class> (are there | do you see | can you find) (in the <room>)?"
    - existence: "Is there a/an/any <class> (in the <room>)?", "Are there (any) <class> (in the <room>)?"

    ``<class>`` is 1-5 plain words, made singular (last word) and joined with ``_`` (``"coffee tables"`` ->
    ``coffee_table``): the detector is open-vocabulary. A leading colour word is dropped from the class (the
    class-level layer does not see colours). ``<room>`` likewise (``"living room"`` -> ``living_room``);
    "the house" / "home" = no room. Structure and time words ("how many rooms", "how many times") are no
    object class."""
    if not isinstance(text, str) or len(text) > MAX_PARSED_CHARS:
        return None
    t = " ".join(text.lower().replace(",", " ").split())
    for category, rx in (("counting", _COUNT), ("existence", _EXIST)):
        m = rx.match(t)
        if m is None:
            continue
        try:
            cls, _ = class_name(m.group("obj"))
        except InstructionError:
            return None
        words = cls.split("_")
        if any(w in FUNCTION_WORDS for w in words):
            return None
        words[-1] = singular(words[-1])
        if words[-1] in NOT_OBJECTS or words[0] in ("of", "more", "other"):
            return None
        room = None
        if m.group("room"):
            try:
                room, _ = class_name(m.group("room"))
            except InstructionError:
                return None
            room = None if room in WHOLE_HOUSE else room
        return category, "_".join(words), room
    return None


def question_target(question: Question) -> tuple[str, str, str | None] | None:
    """``(question category, target class, room kind or None)`` for a question the layer can help with: from
    the benchmark's structured ``query`` when it has one, else parsed from the text (:func:`parse_question`)."""
    q = {str(k).lower(): v for k, v in question.query.items()}
    if q:
        category = question.category or q.get("type")
        cls = q.get("category")
        if category not in CATEGORIES or not cls:
            return None
        return str(category), str(cls), (str(q["room_kind"]) if q.get("room_kind") else None)
    if question.category is not None and question.category not in CATEGORIES:
        return None
    parsed = parse_question(question.text)
    if parsed is None or (question.category is not None and parsed[0] != question.category):
        return None
    return parsed


def region_share(mask: np.ndarray, grid: GridSpec, rects: list[Rect] | None) -> float:
    """Share of the region's cells (``rects``; None = every cell of ``total``) set in ``mask``."""
    rows, cols = mask.shape
    if rects is None:
        return float(mask.mean()) if mask.size else 0.0
    ys = grid.origin_y + (np.arange(rows) + 0.5) * grid.resolution
    xs = grid.origin_x + (np.arange(cols) + 0.5) * grid.resolution
    inside = np.zeros_like(mask, dtype=bool)
    for x0, y0, x1, y1 in rects:
        inside |= ((ys >= y0) & (ys < y1))[:, None] & ((xs >= x0) & (xs < x1))[None, :]
    n = int(inside.sum())
    return float((mask & inside).sum()) / n if n else 0.0


def in_rects(x: float, y: float, rects: list[Rect] | None) -> bool:
    return rects is None or any(x0 <= x < x1 and y0 <= y < y1 for x0, y0, x1, y1 in rects)


class QuestionObjects:
    """One question episode's object layer for its target class (module docstring)."""

    def __init__(self, question: Question, rects: list[Rect] | None, floor_area_m2: float | None = None,
                 config: Any = None) -> None:
        from services.mapper.object_map import ObjectMap, ObjectMapConfig

        target = question_target(question)
        if target is None:
            raise ValueError(f"question {question.id} is not an existence or counting question with a target class")
        self.category, self.cls, self.room_kind = target
        self.rects = rects
        self.floor_area_m2 = floor_area_m2
        cfg = config or ObjectMapConfig()
        self.objects = ObjectMap([self.cls], [cfg.od_object], cfg)

    def detect_request(self, frame: Frame, seed: int = 0, draws: str | None = None) -> DetectRequest:
        return self.objects.detect_request(frame, seed, draws)

    def integrate(self, frame: Frame, result: DetectResult) -> None:
        self.objects.integrate(frame, result)

    def evidence(self, explored: np.ndarray | None, grid: GridSpec | None) -> ObjectEvidence:
        """The step's evidence: target-class instances in the region (best first, at most MAX_TRACKED) and
        the explored share of the region (of the house's floor area when no room is asked). ``explored``: the
        mapper's 2D cells seen by the camera (``Maps2D.observed``: the detector sees the whole frame, not only
        Explore-EQA's narrow view)."""
        psi = []
        for inst in self.objects.layer.instances():
            if inst.cls != 0:  # believed "other"
                continue
            x, y, _ = inst.centre
            if in_rects(float(x), float(y), self.rects):
                psi.append(float(inst.psi[0]))
        psi = sorted(psi, reverse=True)[:MAX_EVIDENCE_INSTANCES]
        share = 0.0
        if explored is not None and grid is not None:
            if self.rects is None and self.floor_area_m2:
                share = min(1.0, float(explored.sum()) * grid.resolution**2 / self.floor_area_m2)
            else:
                share = region_share(explored.astype(bool), grid, self.rects)
        return ObjectEvidence(category=self.category, psi=psi, explored=min(max(share, 0.0), 1.0))

    def in_room(self, room: np.ndarray | None, origin: tuple[float, float],
                resolution: float) -> list[tuple[float, bool]]:
        """Counting across views: ``(Psi, centre within REACH_CELLS of the room's cells)`` of every target-class
        instance; ``room`` is :meth:`RoomExtent.room_mask` on the map's grid (None: no room yet, none inside)."""
        from scipy import ndimage

        from eqa import grid as gridm
        from services.mapper.room_extent import REACH_CELLS

        near = ndimage.binary_dilation(room, iterations=REACH_CELLS) if room is not None else None
        out: list[tuple[float, bool]] = []
        for inst in self.objects.layer.instances():
            if inst.cls != 0:  # believed "other"
                continue
            x, y, _ = inst.centre
            r, c = (int(v) for v in gridm.cell_of(x, y, origin, resolution))
            inside = bool(near is not None and 0 <= r < near.shape[0] and 0 <= c < near.shape[1] and near[r, c])
            out.append((float(inst.psi[0]), inside))
        return out

    # ---- persistence (the mapper's episode state) -------------------------------------------------------
    def snapshot(self) -> bytes:
        return self.objects.snapshot()

    @classmethod
    def restore(cls, question: Question, data: bytes, rects: list[Rect] | None, config: Any = None) -> QuestionObjects:
        from services.mapper.object_map import ObjectMap

        layer = cls(question, rects, config=config)
        layer.objects = ObjectMap.restore(data, config)
        return layer


class QuestionObjectsExtension(MapperExtension):
    """The object evidence of question episodes (existence with ``EQA_OBJECT_EVIDENCE`` on, counting with
    ``EQA_ANSWER_COUNTING=views``), as a mapper extension
    (:mod:`services.mapper.extension`): the episode's :class:`QuestionObjects` (``layers``), a detection per
    frame through the scorer pool (on its own worker, while the mapper waits for the question's scores), the
    step's :class:`~eqa.messages.ObjectEvidence`, and the layer in the episode's stored state. A failed
    detection does not fail the question: logged, and that step carries no evidence (the stopper then uses the
    VLM's distribution alone)."""

    state_key = "question_objects"  # a dict with "map"

    def __init__(self, context: MapperContext) -> None:
        self.context = context
        self.layers: dict[str, QuestionObjects] = {}
        self.rooms: dict[str, RoomExtent] = {}  # counting across views: the asked room's extent
        self.in_room: dict[str, float | None] = {}  # ... and the step's IN_ROOM answer, until it is fused
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapper-question-objects")
        self._told: set[str] = set()

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    def counting_across_views(self, category: str) -> bool:
        """Counting across views (EQA_ANSWER_COUNTING=views) for a question of ``category``."""
        return category == "counting" and self.context.settings.answer_counting == "views"

    def _wanted(self, start: EpisodeStart) -> bool:
        settings = self.context.settings
        if start.task is not None or not (settings.object_evidence or settings.answer_counting == "views"):
            return False
        target = question_target(start.question)
        if target is None:
            if settings.object_evidence and start.episode_id not in self._told:
                self._told.add(start.episode_id)
                log.info("episode %s: object evidence on, but the question names no class to count or find "
                         "(forms: 'How many <class> ...', 'Is there a <class> ...'); no evidence", start.episode_id)
            return False
        if self.counting_across_views(target[0]):
            return True
        if not settings.object_evidence:
            return False
        if target[0] not in WHOLE_MAP_CATEGORIES:
            if start.episode_id not in self._told:
                self._told.add(start.episode_id)
                log.info("episode %s: no whole-map object evidence for a %s question (the whole map's count is not "
                         "the asked room's; WHOLE_MAP_CATEGORIES; EQA_ANSWER_COUNTING=views counts in the room)",
                         start.episode_id, target[0])
            return False
        return True

    def _new_layer(self, start: EpisodeStart) -> None:
        layer = QuestionObjects(start.question, None, config=self.context.objects_config)
        self.layers[start.episode_id] = layer
        if self.counting_across_views(layer.category):
            self.rooms[start.episode_id] = RoomExtent()
            log.info("episode %s: counting '%s' across views in %s", start.episode_id, layer.cls,
                     f"the {layer.room_kind}'s extent (IN_ROOM votes)" if layer.room_kind else "the whole map")
        else:
            log.info("episode %s: object evidence for %s '%s' (room %s: not narrowed, no floor plan)",
                     start.episode_id, layer.category, layer.cls, layer.room_kind)

    def begin(self, episode_map: EpisodeMap, part: Any | None, restored: bool) -> None:
        """The episode's layer when the question gets evidence (the stored one when taken up from the store):
        whole-map evidence for an existence question with EQA_OBJECT_EVIDENCE on (no room layout is known to the
        mapper, module docstring), counting across views in the asked room's extent with EQA_ANSWER_COUNTING=views
        (:class:`~services.mapper.room_extent.RoomExtent`)."""
        start = episode_map.start
        if not self._wanted(start):
            return
        if part is None:
            self._new_layer(start)
            return
        room = None
        if isinstance(part, dict):  # counting across views: the layer and the room's extent
            part, room = part["map"], RoomExtent.from_state(part["room"])
        self.layers[start.episode_id] = QuestionObjects.restore(start.question, part, None,
                                                                config=self.context.objects_config)
        if self.counting_across_views(self.layers[start.episode_id].category):
            self.rooms[start.episode_id] = room or RoomExtent()

    def finish(self, episode_map: EpisodeMap) -> None:
        self.layers.pop(episode_map.episode_id, None)
        self.rooms.pop(episode_map.episode_id, None)
        self.in_room.pop(episode_map.episode_id, None)
        self._told.discard(episode_map.episode_id)

    def dump(self, episode_id: str) -> bytes | dict[str, Any] | None:
        layer = self.layers.get(episode_id)
        if layer is None:
            return None
        room = self.rooms.get(episode_id)
        return layer.snapshot() if room is None else {"map": layer.snapshot(), "room": room.state()}

    def score_request(self, episode_map: EpisodeMap, request: ScoreRequest) -> ScoreRequest:
        """Counting across views in a room: the step's IN_ROOM prompt (only it: the count is the layer's)."""
        layer = self.layers.get(episode_map.episode_id)
        if layer is None or episode_map.episode_id not in self.rooms or not layer.room_kind:
            return request
        return request.model_copy(update={"presence": PresenceQuery(object=layer.cls, room=layer.room_kind,
                                                                    ask_object=False)})

    def submit(self, robot: str, episode_map: EpisodeMap, frame: Frame) -> Future[Any] | None:
        layer = self.layers.get(episode_map.episode_id)
        if layer is None:
            return None
        return self._pool.submit(self._detect, layer, episode_map, frame)

    def _detect(self, layer: QuestionObjects, episode_map: EpisodeMap, frame: Frame) -> tuple[Any, float]:
        detect, _ = self.context.detect_and_values()
        t0 = time.perf_counter()
        start = episode_map.start
        det = call_pool(detect, layer.detect_request(frame, seed=start.seed, draws=start.draws))
        return det, (time.perf_counter() - t0) * 1000.0

    def apply(self, robot: str, episode_map: EpisodeMap, frame: Frame, pending: Future[Any] | None, out: StepOutputs,
              timing: dict[str, float]) -> None:
        """Fuse the frame's detections (and its IN_ROOM vote into the room's extent); the step's evidence, or none
        (no layer, or the detection failed)."""
        layer = self.layers.get(episode_map.episode_id)
        if pending is None or layer is None:
            return
        room = self.rooms.get(episode_map.episode_id)
        if room is not None and episode_map.maps is not None:
            t0 = time.perf_counter()
            m = episode_map.maps
            room.update(frame.depth, frame.intrinsics, frame.camera_pose,
                        room_vote(self.in_room.pop(episode_map.episode_id, None), layer.room_kind),
                        m.explored, m.free, m.occupied, episode_map.origin, episode_map.resolution)
            timing["question_objects_room"] = (time.perf_counter() - t0) * 1000.0
        det, ask_ms = pending.result()
        timing["question_objects_ask"] = ask_ms
        if not isinstance(det, DetectResult):
            log.warning("episode %s step %d: detection failed, no object evidence this step: %s",
                        episode_map.episode_id, frame.step, failure(det))
            return
        t0 = time.perf_counter()
        try:
            layer.integrate(frame, det)
        except Exception:
            log.exception("episode %s step %d: object layer not updated, no object evidence this step",
                          episode_map.episode_id, frame.step)
            return
        timing["question_objects_fuse"] = (time.perf_counter() - t0) * 1000.0
        out.object_evidence = self.evidence(episode_map)

    def scores(self, episode_map: EpisodeMap, frame: Frame, result: ScoreResult, out: StepOutputs,
               timing: dict[str, float], again: bool) -> ScoreResult:
        """The step's IN_ROOM answer for the room's extent (fused in :meth:`apply`); a step sent again gets the
        evidence of the stored layer (nothing is fused twice)."""
        room = self.rooms.get(episode_map.episode_id)
        if again:
            if room is not None and room.votes_in is None and episode_map.maps is not None:
                m = episode_map.maps  # taken up from the store before any update: the maps, no vote
                room.update(frame.depth, frame.intrinsics, frame.camera_pose, None, m.explored, m.free, m.occupied,
                            episode_map.origin, episode_map.resolution)
            out.object_evidence = self.evidence(episode_map)
        elif room is not None:
            self.in_room[episode_map.episode_id] = result.in_room
        return result

    def evidence(self, episode_map: EpisodeMap) -> ObjectEvidence | None:
        """The layer's evidence on the episode's current map: counting across views, the instances within reach of
        the asked room's extent and its open share (:func:`count_evidence`);
        else the whole map's."""
        layer = self.layers.get(episode_map.episode_id)
        if layer is None:
            return None
        room = self.rooms.get(episode_map.episode_id)
        if room is not None:
            inst = layer.in_room(room.room_mask(), episode_map.origin, episode_map.resolution)
            return count_evidence(inst, room.coverage(0.0, 1.0).open_share)
        observed = episode_map.maps.observed if episode_map.maps is not None else None
        return layer.evidence(observed, episode_map.grid() if observed is not None else None)


def count_evidence(instances: Sequence[tuple[float, bool]], open_share: float) -> ObjectEvidence:
    """Counting across views (docs/results/closed-world-answers.md, rule 2): the evidence of the instances whose
    centre is in the asked room (``(Psi, inside)`` per instance,
    :meth:`QuestionObjects.in_room`; the stopper pools it, services/stopper/object_evidence.py), best first,
    with the room's open share
    (:meth:`services.mapper.room_extent.RoomExtent.coverage`, capped at 1) as the unexplored share."""
    psi = sorted((float(min(max(p, 0.0), 1.0)) for p, inside in instances if inside), reverse=True)
    return ObjectEvidence(category="counting", psi=psi[:MAX_EVIDENCE_INSTANCES],
                          explored=1.0 - min(max(float(open_share), 0.0), 1.0))
