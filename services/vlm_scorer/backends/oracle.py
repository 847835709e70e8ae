"""SIMULATED PERCEPTION MODEL (``scorer_backend=oracle``) - not a VLM.

The simulator's default scorer for benchmarks and demos without a GPU. It stands in for a VLM and is
always labelled as simulated (``ScoreResult.backend == "oracle"``, ``model == "simulated-perception"``).

What it reads: the labels of the instances *visible in the current frame* (``ScoreRequest.labels``, the
``instances`` id image, ``depth``), the prompt points, and the question's text, choices and structured
parse ``question.query``. It never reads ``question.answer`` or ``question.evidence_ids`` and never sees a
part of the scene outside the frame.

How it behaves (the knobs are :class:`OracleParams`, from settings ``EQA_ORACLE_*``):

* Perception: a target (an instance of the asked category, in the asked room when one is asked, of the
  asked colour when the question names one: "where is the blue towel?") counts as
  seen with a quality ``E`` in [0, 1] from its pixel share (``min_pixels_frac`` .. ``full_pixels_frac``) and
  its distance (full up to ``near_m``, none past ``max_range_m``). On a view with evidence the model reads
  the answer from what it sees (colour, state, count, room), right with probability ``accuracy`` - the draw
  is per (question, target instance), so the model is consistently right or wrong about one object, as a
  real VLM is about one view of it.
* Answer distribution f(x^t): with evidence, the read answer gets a top probability around
  ``evidence_confidence``; without evidence (or with probability 1 - E on weak views) the model answers
  anyway, confidently and biased (Explore-EQA VII-G): a per-question bias choice gets a top probability
  around ``bias_confidence`` (for a location question the bias follows the commonsense prior of
  :mod:`services.vlm_scorer.commonsense`: a VLM that has not seen the towel guesses "the bathroom").
  ``temperature`` (>1 flatter, <1 sharper) miscalibrates both. Padding choices "(Do not choose this
  option)" never get more than ``padding_floor``.
* Relevance Rel(x^t) (Eq. 5): ``relevance_scale * E`` with log-normal noise, so it runs low even on good
  views (appendix C, Fig. A5); about ``relevance_floor`` on views without evidence.
* LSV (Eq. 1): per prompt point, the rooms and objects whose instance ids lie within ``window_frac`` of the
  short image side around the point's pixel (floors and walls carry the room kind) scored with the
  commonsense prior of :mod:`services.vlm_scorer.commonsense`, a bonus for a seen target and for
  connectors (doors, stairs) when the asked room is not in view; softmax with ``lsv_temperature``; with
  probability 1 - ``accuracy`` the scores are shuffled (a confused model).
* GSV (Eq. 2): P(Yes) from the best prior among the rooms in view, connectors and seen targets, plus noise.

Miscalibration modes (each a level in [0, 1], 0 = the behaviour above, byte-identical). A real
VLM's confidences are miscalibrated in ways a raw threshold cannot undo (Explore-EQA section V, "miscalibrated
VLMs"; section VII-G; appendix C, Fig. A5). The modes imitate what the paper reports, and act on the answer
distribution and the relevance only (the stopping signals): LSV, GSV and hence the robot's path are those of
level 0, so one recorded run serves every level (``bench``'s sensitivity study re-scores it offline).

* ``miscal_category`` - relevance that varies by question category: ``Rel *= exp(level * b_c)`` with a fixed
  log-bias per category, :data:`CATEGORY_RELEVANCE_BIAS` (counting +1: a partial view of the objects to count
  looks sufficient; state -1: small objects that need close views, appendix C's remark that state questions
  stay hard; the others in between). Appendix C: the top relevance of correctly answered episodes spreads
  over the whole range, most below 0.5 (Fig. A5).
* ``miscal_view`` - relevance that varies by view type: ``Rel *= exp(level * (2 c - 1))`` where ``c`` in [0, 1]
  is the view's clutter (the share of the image covered by furniture and objects, full at
  :data:`CLUTTER_FULL`): a wall or an empty corridor ("facing an empty wall", VII-G) scores low, a busy view
  high, whatever it shows of the question.
* ``miscal_related`` - high relevance on a related-but-wrong object: an instance of the asked category that is
  *not* the one asked about (another room, another colour; a VLM reading the question as a bag of words,
  section VII-D and its ref. [55]) is taken for the target with probability ``level`` (a draw per question and
  instance, so a level's confusions include the lower levels'): the model reads its answer from the wrong
  object, with the relevance of real evidence.
* ``miscal_irrelevant`` - confident answers from irrelevant views: on a view without evidence the top
  probability of the (biased) answer moves towards 0.99, ``top += level * (0.99 - top)`` (VII-G: "the VLM still
  outputs highly confident, biased answers" facing an empty wall; what makes the entropy rule stop early).

Presence queries ("is there an X in this image?", "is this image taken in the Y?", the prompts ``PRESENCE``
and ``IN_ROOM`` of :mod:`services.vlm_scorer.prompts`, asked when ``ScoreRequest.presence`` names an object
class and maybe a room): :meth:`OracleBackend.presence` answers them from the current frame only, with the
errors open VLMs show on such yes/no probes (object-hallucination benchmarks such as POPE, Li et al. 2023,
report open VLMs answering "yes" for absent objects in roughly 5-30 % of probes and missing small objects):

* object: every visible instance of the class (any room: the question is about the image) with a quality
  ``E > 0`` (the perception above) is recognised with probability ``E``, unless the model consistently fails on
  that instance (``presence_miss``, drawn once per (question, instance), as a VLM that takes one mug for a
  vase does so from every side); with nothing recognised it still says "yes" with probability
  ``presence_false_yes`` (a hallucination, drawn per view);
* room: the view shows the room kind when at least half of the structure pixels in it (floor, walls, ceiling,
  windows, which carry their room's kind) belong to a room of that kind; the answer is the other one with
  probability ``presence_room_error`` (per view: a VLM confusing a bedroom with an office);
* confidence: the P(Yes) reported is ``c`` for "yes" and ``1 - c`` for "no" with ``c`` drawn around
  ``presence_confidence`` (sd 0.1, clipped to [0.5, 0.99]) whether the answer is right or wrong: as
  confident when wrong as when right (miscalibrated).

These knobs were set from the literature's error rates before any run and are not tuned on a benchmark.

Every draw comes from a generator seeded by (``ScoreRequest.seed``, question id, step), so the same request
gives the same numbers. The defaults aim at the paper's 56-65 % success at the full step budget for open
VLMs; the same defaults serve every exploration and stopping strategy.
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass, fields

import numpy as np

from eqa.messages import NOT_LISTED_CHOICE, PADDING_CHOICE, InstanceLabel, Question, ScoreRequest
from eqa.settings import SettingsGroup, SimulatedPerceptionSettings
from services.vlm_scorer import commonsense as cs
from services.vlm_scorer.backends.base import Backend, Scores, validate_request

MODEL_LABEL = "simulated-perception"

NUMBER_WORDS = {
    "none": 0,
    "zero": 0,
    "no": 0,
    "one": 1,
    "single": 1,
    "two": 2,
    "three": 3,
    "four": 4,
    "five": 5,
    "six": 6,
    "seven": 7,
    "eight": 8,
    "nine": 9,
    "ten": 10,
}
COLORS = (
    "white",
    "black",
    "gray",
    "grey",
    "brown",
    "beige",
    "red",
    "orange",
    "yellow",
    "green",
    "blue",
    "purple",
    "pink",
    "silver",
    "gold",
    "tan",
    "cream",
    "navy",
    "teal",
    "wooden",
)

# State words a yes/no question can end with ("Is the stove in the kitchen turned off?").
STATE_WORDS = ("on", "off", "open", "closed", "folded", "unfolded")


MISCALIBRATION_MODES: tuple[str, ...] = ("miscal_category", "miscal_view", "miscal_related", "miscal_irrelevant")
# log-relevance bias per question category at miscal_category = 1 (module docstring)
CATEGORY_RELEVANCE_BIAS: dict[str, float] = {
    "counting": 1.0,
    "identification": 0.5,
    "location": 0.0,
    "existence": -0.5,
    "state": -1.0,
}
CLUTTER_FULL = 0.25  # share of the image covered by objects at which a view counts as fully cluttered
IRRELEVANT_TOP = 0.99  # where miscal_irrelevant = 1 puts the top probability of an answer without evidence
STRUCTURE_CATEGORIES = frozenset({"floor", "wall", "ceiling", "door_frame", "window"})
View = tuple[InstanceLabel, float, float | None]  # (label, image share, median distance in metres or None)


@dataclass(frozen=True)
class OracleParams:
    """The knobs of the simulated perception model (documented in the module docstring)."""

    accuracy: float = 0.85
    evidence_confidence: float = 0.8
    bias_confidence: float = 0.7
    bias_stickiness: float = 0.75  # P(the no-evidence answer is the question's bias choice)
    temperature: float = 1.0
    relevance_scale: float = 0.55
    relevance_floor: float = 0.06
    relevance_noise: float = 0.35  # sd of the log-normal noise on Rel
    min_pixels_frac: float = 0.0005
    full_pixels_frac: float = 0.005
    near_m: float = 2.0
    max_range_m: float = 6.0
    padding_floor: float = 1e-3
    window_frac: float = 0.12
    lsv_temperature: float = 0.35
    miscal_category: float = 0.0  # miscalibration modes, 0 = off (module docstring)
    miscal_view: float = 0.0
    miscal_related: float = 0.0
    miscal_irrelevant: float = 0.0
    presence_miss: float = 0.15  # presence queries (module docstring)
    presence_false_yes: float = 0.1
    presence_room_error: float = 0.1
    presence_confidence: float = 0.85

    @property
    def miscalibrated(self) -> bool:
        return any(getattr(self, m) > 0 for m in MISCALIBRATION_MODES)

    @classmethod
    def from_settings(cls, settings: SettingsGroup) -> OracleParams:
        kw = {}
        for f in fields(cls):  # those with a setting of their own (the others keep their defaults)
            if (name := f"oracle_{f.name}") in SimulatedPerceptionSettings.model_fields:
                kw[f.name] = float(getattr(settings, name))
        return cls(**kw)


@dataclass(frozen=True)
class Target:
    """What the question is about, from ``question.query`` or the free-text fallback."""

    type: str
    category: str | None
    room_kind: str | None
    attribute: str | None
    value: str | None
    color: str | None = None


def parse_target(question: Question) -> Target:
    """The structured parse; a free-text question without ``query`` falls back to matching catalog names."""
    q = {k.lower(): v for k, v in question.query.items()}
    text = question.text.lower()
    qtype = q.get("type")
    category = q.get("category")
    room_kind = q.get("room_kind")
    if category is None:
        category = next((c for c in cs.known_categories() if re.search(rf"\b{re.escape(c)}s?\b", text)), None)
    if room_kind is None and not q:
        room_kind = next((rk for rk in cs.ROOM_KINDS if cs.room_display(rk) in text), None)
    state = re.search(rf"\b({'|'.join(STATE_WORDS)})\W*$", text)
    yes_no_choices = any(yes_no(c) for c in question.choices)
    if qtype is None:
        if "how many" in text:
            qtype = "counting"
        elif "color" in text or "colour" in text:
            qtype = "identification"
        elif text.startswith("where") or "which room" in text:
            qtype = "location"
        elif yes_no_choices and state is not None:
            qtype = "state"
        elif yes_no_choices:
            qtype = "existence"
        else:
            qtype = "identification"
    attribute, value, color = q.get("attribute"), q.get("value"), q.get("color")
    if not q:
        if qtype == "state" and state is not None:
            attribute, value = "state", state.group(1)
        if qtype != "identification":
            color = next((c for c in COLORS if re.search(rf"\b{c}\b", text)), None)
    return Target(
        qtype,
        cs.norm_category(category) if category else None,
        room_kind,
        attribute,
        value,
        color.lower() if color else None,
    )


def _words(s: str) -> list[str]:
    return re.findall(r"[a-z0-9]+", s.lower())


def choice_number(choice: str) -> int | None:
    for w in _words(choice):
        if w.isdigit():
            return int(w)
        if w in NUMBER_WORDS:
            return NUMBER_WORDS[w]
    return None


def yes_no(choice: str) -> str | None:
    w = _words(choice)
    return w[0] if w and w[0] in ("yes", "no") else None


class OracleBackend(Backend):
    """SIMULATED PERCEPTION MODEL standing in for a VLM (see the module docstring)."""

    name = "oracle"
    model_name = MODEL_LABEL

    def __init__(self, params: OracleParams | None = None) -> None:
        self.p = params or OracleParams()

    @classmethod
    def from_settings(cls, settings: SettingsGroup) -> OracleBackend:
        return cls(OracleParams.from_settings(settings))

    # ---- perception --------------------------------------------------------------------------------------
    def view_quality(self, frac: float, dist: float | None) -> float:
        """Evidence quality E in [0, 1] of a target covering ``frac`` of the image at ``dist`` metres."""
        p = self.p
        q = float(
            np.clip((frac - p.min_pixels_frac) / max(p.full_pixels_frac - p.min_pixels_frac, 1e-9), 0, 1)
        )
        if dist is not None:
            q *= float(np.clip((p.max_range_m - dist) / max(p.max_range_m - p.near_m, 1e-9), 0.0, 1.0))
        return q

    @staticmethod
    def is_target(lab: InstanceLabel, t: Target) -> bool:
        """Whether ``lab`` is what the question asks about (category, room, colour)."""
        if t.category is None or cs.norm_category(lab.category) != t.category:
            return False
        same_room = cs.canonical_room(lab.room_kind) == cs.canonical_room(t.room_kind)
        if t.room_kind and t.type != "location" and lab.room_kind and not same_room:
            return False
        # "the blue towel": a towel of another colour is not the one asked about
        return not (t.color and t.type != "identification" and lab.attributes.get("color", t.color) != t.color)

    @staticmethod
    def is_related(lab: InstanceLabel, t: Target) -> bool:
        """An instance of the asked category that is not the one asked about (another room or colour)."""
        return (t.category is not None and cs.norm_category(lab.category) == t.category
                and not OracleBackend.is_target(lab, t))

    @staticmethod
    def _view(req: ScoreRequest, lab: InstanceLabel) -> View:
        h, w = req.rgb.shape[:2]
        pixels, dist = lab.pixels, None
        if req.instances is not None:
            mask = req.instances == lab.id
            pixels = int(mask.sum()) or pixels
            if req.depth is not None and mask.any():
                d = req.depth[mask]
                d = d[np.isfinite(d) & (d > 0)]
                dist = float(np.median(d)) if d.size else None
        return lab, pixels / float(h * w), dist

    @staticmethod
    def target_views(req: ScoreRequest, t: Target) -> list[View]:
        """The visible instances that could answer the question: (label, image share, median distance)."""
        if t.category is None:
            return []
        return [OracleBackend._view(req, lab) for lab in req.labels if OracleBackend.is_target(lab, t)]

    @staticmethod
    def related_views(req: ScoreRequest, t: Target) -> list[View]:
        """The visible instances of the asked category that are not the one asked about (``miscal_related``)."""
        return [OracleBackend._view(req, lab) for lab in req.labels if OracleBackend.is_related(lab, t)]

    @staticmethod
    def clutter(req: ScoreRequest) -> float:
        """Share of the image covered by furniture and objects (not floor, walls, ceiling, windows)."""
        h, w = req.rgb.shape[:2]
        ids = [lab.id for lab in req.labels if cs.norm_category(lab.category) not in STRUCTURE_CATEGORIES]
        if req.instances is not None:
            return float(np.isin(req.instances, ids).sum()) / float(h * w) if ids else 0.0
        return sum(lab.pixels for lab in req.labels if lab.id in ids) / float(h * w)

    def seen_targets(self, views: list[View]) -> list[tuple[InstanceLabel, float]]:
        """The views with a non-zero quality, best first."""
        seen = [(lab, self.view_quality(frac, dist)) for lab, frac, dist in views]
        return sorted([(lab, q) for lab, q in seen if q > 0], key=lambda x: -x[1])

    def _read_answer(
        self, t: Target, seen: list[tuple[InstanceLabel, float]], choices: list[str]
    ) -> int | None:
        """Index of the choice that what is seen supports (None: the view says nothing about the answer)."""
        if not seen:
            return None
        low = [c.lower() for c in choices]
        best = seen[0][0]
        found: int | None = None
        if t.type == "counting":
            n = len(seen)
            found = next((i for i, c in enumerate(choices) if choice_number(c) == n), None)
        elif t.type == "existence":
            found = next((i for i, c in enumerate(choices) if yes_no(c) == "yes"), None)
        elif t.type == "state":
            state = best.attributes.get(t.attribute or "state", best.attributes.get("state"))
            if state is not None:
                yn = [yes_no(c) for c in choices]
                if any(yn) and t.value is not None:
                    want = "yes" if state.lower() == t.value.lower() else "no"
                    found = next((i for i, v in enumerate(yn) if v == want), None)
                else:
                    found = next((i for i, c in enumerate(low) if state.lower() in _words(c)), None)
        elif t.type == "location":
            if best.room_kind:
                name = cs.room_display(best.room_kind)
                found = next((i for i, c in enumerate(low) if name in c), None)
        else:  # identification: colour (or another asked attribute)
            value = best.attributes.get(t.attribute or "color", best.attributes.get("color"))
            if value is not None:
                found = next((i for i, c in enumerate(low) if value.lower() in c), None)
        if found is None and NOT_LISTED_CHOICE in choices:
            found = choices.index(NOT_LISTED_CHOICE)
        return found

    # ---- the four numbers --------------------------------------------------------------------------------
    def _bias_choice(self, qrng: np.random.Generator, t: Target, choices: list[str], real: list[int]) -> int:
        """The answer the model gives without evidence: for a location question the room the commonsense
        prior favours for the object (a VLM guesses "towel: bathroom"), otherwise a per-question bias."""
        if t.type == "location" and t.category:
            w = np.array([max(cs.prior(t.category, _choice_room(choices[i])), 1e-3) for i in real]) ** 2
            return real[int(qrng.choice(len(real), p=w / w.sum()))]
        return real[int(qrng.integers(len(real)))]

    def _answer(
        self,
        rng: np.random.Generator,
        req: ScoreRequest,
        choices: list[str],
        t: Target,
        seen: list[tuple[InstanceLabel, float]],
    ) -> tuple[list[float], float, bool]:
        p = self.p
        n = len(choices)
        real = [i for i, c in enumerate(choices) if c.strip() != PADDING_CHOICE] or list(range(n))
        read = self._read_answer(t, seen, choices)
        quality = seen[0][1] if seen else 0.0
        evidence_id = seen[0][0].id if seen else -1
        evidence = read is not None and rng.random() < quality
        if evidence:
            assert read is not None
            u = np.random.default_rng([req.seed, _h(req.question.id), _h(req.question.text), evidence_id + 1])
            right = u.random() < p.accuracy
            others = [i for i in real if i != read]
            chosen = read if right or not others else others[int(u.integers(len(others)))]
            top = float(np.clip(rng.normal(p.evidence_confidence, 0.1), 0.3, 0.995))
        else:
            qrng = np.random.default_rng([req.seed, _h(req.question.id), _h(req.question.text)])
            bias = self._bias_choice(qrng, t, choices, real)
            chosen = bias if rng.random() < p.bias_stickiness else real[int(rng.integers(len(real)))]
            top = float(np.clip(rng.normal(p.bias_confidence, 0.12), 0.3, 0.995))
            right = False
        probs = np.zeros(n)
        rest = [i for i in real if i != chosen]
        probs[chosen] = top
        if rest:
            probs[rest] = (1.0 - top) * rng.dirichlet(np.ones(len(rest)))
        else:
            probs[chosen] = 1.0
        probs = np.power(np.maximum(probs, 1e-12), 1.0 / max(p.temperature, 1e-3))
        pad = [i for i in range(n) if i not in real]
        probs[pad] = 0.0
        probs /= probs.sum()
        if pad:
            probs[pad] = p.padding_floor
            probs[real] *= (1.0 - p.padding_floor * len(pad)) / probs[real].sum()
        return probs.tolist(), quality if evidence else 0.0, right

    def _relevance(self, rng: np.random.Generator, quality: float, right: bool) -> float:
        p = self.p
        noise = float(np.exp(rng.normal(0.0, p.relevance_noise)))
        if quality > 0:
            rel = p.relevance_scale * quality * (1.0 if right else 0.8) * noise
        else:
            rel = p.relevance_floor * noise
        return float(np.clip(rel, 0.01, 0.99))

    def _point_features(self, req: ScoreRequest, u: float, v: float) -> list[InstanceLabel]:
        if req.instances is None:
            return []
        h, w = req.instances.shape
        r = max(2, int(self.p.window_frac * min(h, w)))
        ui, vi = int(np.clip(round(u), 0, w - 1)), int(np.clip(round(v), 0, h - 1))
        patch = req.instances[max(0, vi - r) : vi + r + 1, max(0, ui - r) : ui + r + 1]
        ids = set(np.unique(patch).tolist())
        return [lab for lab in req.labels if lab.id in ids]

    def _place_value(self, t: Target, labs: list[InstanceLabel]) -> float:
        """Commonsense worth of a place showing ``labs`` for finding the target."""
        if not labs:
            return 0.2
        rooms = {cs.canonical_room(lab.room_kind) for lab in labs if lab.room_kind}
        wanted = cs.canonical_room(t.room_kind)
        if wanted:
            room_score = 1.0 if wanted in rooms else 0.1
            if t.category and t.type != "location":
                room_score *= 0.5 + 0.5 * max(
                    (cs.prior(t.category, rk) for rk in rooms), default=cs.UNKNOWN_PRIOR
                )
        else:
            room_score = max((cs.prior(t.category or "", rk) for rk in rooms), default=cs.UNKNOWN_PRIOR)
        cats = {cs.norm_category(lab.category) for lab in labs}
        target_bonus = 0.6 if t.category in cats else 0.0
        wanted_here = wanted in rooms if wanted else room_score > 0.5
        connector = 0.3 if (cats & cs.CONNECTORS) and not wanted_here else 0.0
        return room_score + target_bonus + connector

    def _lsv(self, rng: np.random.Generator, req: ScoreRequest, t: Target) -> list[float]:
        pts = req.prompt_points
        if not pts:
            return []
        if len(pts) == 1:
            return [1.0]
        s = np.array([self._place_value(t, self._point_features(req, pt.u, pt.v)) for pt in pts])
        s += rng.normal(0.0, 0.05, size=s.shape)
        if rng.random() > self.p.accuracy:
            s = rng.permutation(s)
        z = s / max(self.p.lsv_temperature, 1e-3)
        e = np.exp(z - z.max())
        return (e / e.sum()).tolist()

    def _gsv(self, rng: np.random.Generator, req: ScoreRequest, t: Target, seen: bool) -> float:
        visible = [lab for lab in req.labels if lab.pixels > 0 or req.instances is not None]
        value = self._place_value(t, visible) if visible else 0.2
        g = 0.1 + 0.45 * min(value, 1.6) / 1.6 + (0.15 if seen else 0.0) + rng.normal(0.0, 0.08)
        return float(np.clip(g, 0.02, 0.98))

    def propose_choices(self, question: Question, t: Target) -> list[str]:
        """Section VI-A for the simulated model: candidates from the question alone (stable over steps)."""
        if t.type == "counting":
            base = ["One", "Two", "Three", "Four"]
        elif t.type in ("existence", "state"):
            base = ["Yes", "No"]
        elif t.type == "location":
            base = [cs.room_display(rk) for rk in cs.likely_rooms(t.category or "", 3)]
        else:
            base = ["White", "Black", "Brown", "Gray"]
        return [*base, NOT_LISTED_CHOICE]

    def score(self, req: ScoreRequest) -> Scores:
        validate_request(req)
        rng = np.random.default_rng([req.seed, _h(req.question.id), req.step])
        t = parse_target(req.question)
        proposed: list[str] = []
        choices = list(req.question.choices)
        if not choices:
            proposed = self.propose_choices(req.question, t)
            choices = proposed
        targets = self.target_views(req, t)
        seen = self.seen_targets(targets)
        probs, quality, right = self._answer(rng, req, choices, t, seen)
        rel = self._relevance(rng, quality, right)
        lsv = self._lsv(rng, req, t)
        gsv = self._gsv(rng, req, t, bool(seen))
        if self.p.miscalibrated:  # the path (LSV, GSV) stays that of level 0; only f and Rel change
            probs, rel = self.miscalibrated_scores(req, choices, t, targets, self.related_views(req, t),
                                                   self.clutter(req))
        out = Scores(probs, rel, lsv, gsv, proposed)
        if req.presence is not None:  # its own generator: the four numbers above do not change
            object_yes, out.in_room = self.presence(req, req.presence.object, req.presence.room)
            # a PRESENCE not asked is not answered; its draws are made all the same, so IN_ROOM does not change
            out.object_yes = object_yes if req.presence.ask_object else None
        return out

    def presence(self, req: ScoreRequest, category: str, room_kind: str | None) -> tuple[float, float | None]:
        """``(P(Yes) to "is there a <category> in this image?", P(Yes) to "is this image taken in the <room>?"
        or None without a room)`` from the frame's labels only (module docstring, presence queries)."""
        p = self.p
        rng = np.random.default_rng([req.seed, _h(req.question.id), req.step, 23])
        cat = cs.norm_category(category)
        seen = False
        for lab in req.labels:
            if cs.norm_category(lab.category) != cat:
                continue
            _, frac, dist = self._view(req, lab)
            quality = self.view_quality(frac, dist)
            missed = np.random.default_rng([req.seed, _h(req.question.id), lab.id + 1, 29]).random() < p.presence_miss
            if quality > 0 and not missed and rng.random() < quality:
                seen = True
        hallucinated = rng.random() < p.presence_false_yes
        object_yes = self._yes_no_prob(rng, seen or hallucinated)
        if not room_kind:
            return object_yes, None
        want = cs.canonical_room(room_kind)
        total = mine = 0
        for lab in req.labels:
            if cs.norm_category(lab.category) not in STRUCTURE_CATEGORIES:
                continue
            n = int((req.instances == lab.id).sum()) if req.instances is not None else lab.pixels
            total += n
            mine += n if cs.canonical_room(lab.room_kind) == want else 0
        in_room = total > 0 and mine >= 0.5 * total
        if rng.random() < p.presence_room_error:
            in_room = not in_room
        return object_yes, self._yes_no_prob(rng, in_room)

    def _yes_no_prob(self, rng: np.random.Generator, yes: bool) -> float:
        c = float(np.clip(rng.normal(self.p.presence_confidence, 0.1), 0.5, 0.99))
        return c if yes else 1.0 - c

    def miscalibrated_scores(self, req: ScoreRequest, choices: list[str], t: Target, targets: list[View],
                             related: list[View], clutter: float) -> tuple[list[float], float]:
        """``(f, Rel)`` of a step under the miscalibration modes (module docstring), drawn from the step's own
        generator as at level 0; every mode's extra draw has a generator of its own. Pure in its arguments,
        so a recorded step (its views and clutter) can be re-scored offline at any level."""
        rng = np.random.default_rng([req.seed, _h(req.question.id), req.step])
        views = list(targets) + self.related_confused(req, related)
        seen = self.seen_targets(views)
        probs, quality, right = self._answer(rng, req, choices, t, seen)
        rel = self._relevance(rng, quality, right)
        return self.confident_when_irrelevant(probs, quality), self.biased_relevance(rel, t.type, clutter)

    def confident_when_irrelevant(self, probs: list[float], quality: float) -> list[float]:
        """``miscal_irrelevant``: on a view without evidence (``quality == 0``) the top probability moves
        towards :data:`IRRELEVANT_TOP`, the others shrink in proportion."""
        level = self.p.miscal_irrelevant
        if level <= 0 or quality != 0:
            return probs
        f = np.asarray(probs)
        top = int(np.argmax(f))
        new_top = f[top] + level * max(IRRELEVANT_TOP - f[top], 0.0)
        rest = f.sum() - f[top]
        if rest > 0:
            f = f * ((1.0 - new_top) / rest)
        f[top] = new_top
        return (f / f.sum()).tolist()

    def biased_relevance(self, rel: float, qtype: str, clutter: float) -> float:
        """``miscal_category`` and ``miscal_view``: ``Rel * exp(level_c * b_category + level_v * (2 c - 1))``."""
        p = self.p
        log_bias = 0.0
        if p.miscal_category > 0:
            log_bias += p.miscal_category * CATEGORY_RELEVANCE_BIAS.get(qtype, 0.0)
        if p.miscal_view > 0:
            log_bias += p.miscal_view * (2.0 * min(max(clutter / CLUTTER_FULL, 0.0), 1.0) - 1.0)
        if log_bias:
            rel = float(np.clip(rel * np.exp(log_bias), 0.01, 0.99))
        return rel

    def related_confused(self, req: ScoreRequest, related: list[View]) -> list[View]:
        """``miscal_related``: the related-but-wrong instances taken for the target in this request (a draw per
        question and instance, so a level's confusions include the lower levels')."""
        level = self.p.miscal_related
        if level <= 0:
            return []
        return [v for v in related
                if np.random.default_rng([req.seed, _h(req.question.id), v[0].id + 1, 15]).random() < level]


def _choice_room(choice: str) -> str:
    """The room a location choice names: "In the living room" -> "living_room"."""
    words = _words(choice)
    if words[:2] == ["in", "the"]:
        words = words[2:]
    return "_".join(words)


def _h(text: str) -> int:
    return zlib.crc32(text.encode("utf-8"))
