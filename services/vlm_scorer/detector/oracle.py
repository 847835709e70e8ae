"""SIMULATED DETECTOR (``detector_backend=oracle``) - not a real detector.

Stands in for an open-vocabulary instance-segmentation detector of the DETIC class (Zhou et al. 2022, as used
by HomeRobot OVMM and HELIOS) in the simulator. Every result is labelled ``backend == "oracle"``, ``model ==
"simulated-detector"``; every figure made with it says "simulated detector, not a real detector".

What it reads: the simulator's instance-id image of the *current frame* (``DetectRequest.instances``), the
labels of the instances visible in it (``labels``) and the depth. It never sees an instance that has no pixel
in the frame. It needs the instance ids (a real image without them is refused with a clear error).

Behaviour, with the documented failure modes of such detectors (HomeRobot OVMM reports wrong and missed
detections as the main cause of failure; DETIC's recall on small / rare LVIS categories is low; masks of
two-stage detectors bleed over object borders), each a knob of :class:`OracleDetectorParams`
(settings ``EQA_DETECTOR_ORACLE_*``):

* Missed small or far objects: an instance of a requested class is detected with probability
  ``recall * Q``, Q in [0, 1] the view quality: 0 below ``min_pixels_frac`` of the image, 1 from
  ``full_pixels_frac``, times a range factor 1 up to ``near_m`` falling to 0 at ``max_range_m``.
* Per-class confidences: each class has its own base confidence drawn once per class name in
  [``score_lo``, ``score_hi``] (a detector is surer of some categories than others); a detection's score is
  base x (0.55 + 0.45 Q) plus normal noise of sd ``score_sd``.
* Class confusions between similar categories (the groups in :data:`SIMILAR`: seats, tables, cabinets,
  containers, screens...): a detected instance is reported as a similar requested class with probability
  ``confusion``; an instance of a non-requested class similar to a requested one is reported as it with
  probability ``similar_fp * Q`` (the "vase detected as a mug" false positive). Confused scores are scaled by
  ``confusion_score``.
* False positives on background: per requested class and frame, with probability ``background_fp`` a blob
  on a random visible surface (walls and floors included, weighted by area) of radius ``fp_radius_frac`` of
  the image's short side, score uniform in [``fp_score_lo``, ``fp_score_hi``].
* Masks that bleed: each mask is dilated by 0 .. ``bleed_frac`` x the short side pixels over its border.
* Per-class thresholds from the request (HELIOS od_a 0.35 / od_g 0.25 / od_b 0.45).

``EQA_DETECTOR_GROUND_TRUTH=true`` turns it into the paper's ground-truth-semantics yardstick (Table 4):
every visible pixel of a requested class, score 1, no error of any kind (``model == "ground-truth-semantics"``).

Draws come from generators seeded by (``seed``, draw key, step[, instance id]), the draw key being the episode id
unless the request names one (``DetectRequest.draws``, a repeatable run): the same request gives the
same detections, and errors are view-dependent (a different step is a different draw), which is what
multi-view fusion can correct. The defaults are set by hand to plausible rates; they were not tuned on
results.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, fields

import numpy as np
from scipy import ndimage

from eqa.messages import Detection, DetectRequest, InstanceLabel
from eqa.settings import SettingsGroup, SimulatedDetectorSettings
from services.vlm_scorer import commonsense as cs
from services.vlm_scorer.backends.base import BadRequest
from services.vlm_scorer.detector.base import Detector, finish, make_detection, validate_detect_request

MODEL_LABEL = "simulated-detector"
GROUND_TRUTH_LABEL = "ground-truth-semantics"  # EQA_DETECTOR_GROUND_TRUTH: a yardstick, not a detector
STRUCTURE = frozenset({"floor", "wall", "ceiling", "door frame", "door_frame"})

SIMILAR: tuple[frozenset[str], ...] = tuple(
    frozenset(cs.norm_category(c) for c in group)
    for group in (
        ("chair", "armchair", "office_chair", "sofa", "bench"),
        ("dining_table", "coffee_table", "side_table", "console_table", "desk", "kitchen_island", "table"),
        ("cabinet", "dresser", "sideboard", "tv_stand", "filing_cabinet", "nightstand", "wardrobe"),
        ("bookshelf", "storage_shelf", "laundry_shelf", "shelf"),
        ("kitchen_counter", "kitchen_island", "workbench", "counter"),
        ("washing_machine", "dryer", "stove", "microwave", "refrigerator"),
        ("mug", "cup", "vase", "kettle", "fruit_bowl", "bowl"),
        ("backpack", "suitcase", "box", "toolbox", "laundry_basket", "trash_can", "bag"),
        ("television", "monitor", "laptop"),
        ("towel", "blanket", "cushion", "pillow"),
        ("bed", "sofa"),
        ("toilet", "bathroom_sink", "bathtub", "sink"),
    )
)


@dataclass(frozen=True)
class OracleDetectorParams:
    """The knobs of the simulated detector (documented in the module docstring)."""

    recall: float = 0.9
    min_pixels_frac: float = 0.0003
    full_pixels_frac: float = 0.004
    near_m: float = 2.5
    max_range_m: float = 7.0
    score_lo: float = 0.45
    score_hi: float = 0.85
    score_sd: float = 0.08
    confusion: float = 0.12
    similar_fp: float = 0.15
    confusion_score: float = 0.8
    background_fp: float = 0.08
    fp_radius_frac: float = 0.05
    fp_score_lo: float = 0.2
    fp_score_hi: float = 0.5
    bleed_frac: float = 0.015

    @classmethod
    def ground_truth(cls) -> OracleDetectorParams:
        """The paper's "with ground-truth semantics" yardstick (Table 4): every visible pixel of an instance of
        a requested class, at any size and range, with score 1, no confusion, no false positive, no bleeding."""
        return cls(recall=1.0, min_pixels_frac=0.0, full_pixels_frac=1e-9, near_m=1e9, max_range_m=2e9,
                   score_lo=1.0, score_hi=1.0, score_sd=0.0, confusion=0.0, similar_fp=0.0, background_fp=0.0,
                   bleed_frac=0.0)

    @classmethod
    def from_settings(cls, settings: SettingsGroup) -> OracleDetectorParams:
        if settings.detector_ground_truth:
            return cls.ground_truth()
        kw = {}
        for f in fields(cls):  # those with a setting of their own (the others keep their defaults)
            if (name := f"detector_oracle_{f.name}") in SimulatedDetectorSettings.model_fields:
                kw[f.name] = float(getattr(settings, name))
        return cls(**kw)


def _h(text: str) -> int:
    return zlib.crc32(text.encode("utf-8"))


def matches(requested: str, category: str) -> bool:
    """Does a detector asked for ``requested`` name an instance of ``category`` so? The same normalised name,
    or a hypernym by head word ("table" names a coffee table, "counter" a kitchen counter)."""
    r, c = cs.norm_category(requested), cs.norm_category(category)
    return r == c or c.split(" ")[-1] == r


def similar(requested: str, category: str) -> bool:
    """Could a detector mistake an instance of ``category`` for ``requested``? (a shared group of SIMILAR)"""
    r, c = cs.norm_category(requested), cs.norm_category(category)
    if r == c:
        return False
    rh, ch = r.split(" ")[-1], c.split(" ")[-1]
    return any((r in g or rh in g) and (c in g or ch in g) for g in SIMILAR)


class OracleDetector(Detector):
    """SIMULATED DETECTOR standing in for DETIC (see the module docstring)."""

    name = "oracle"
    model_name = MODEL_LABEL

    def __init__(self, params: OracleDetectorParams | None = None) -> None:
        self.p = params or OracleDetectorParams()
        if self.p == OracleDetectorParams.ground_truth():
            self.model_name = GROUND_TRUTH_LABEL

    @classmethod
    def from_settings(cls, settings: SettingsGroup) -> OracleDetector:
        return cls(OracleDetectorParams.from_settings(settings))

    def class_confidence(self, cls_name: str) -> float:
        """The per-class base confidence (fixed per class name)."""
        u = np.random.default_rng(_h("class:" + cs.norm_category(cls_name))).random()
        return self.p.score_lo + (self.p.score_hi - self.p.score_lo) * float(u)

    def quality(self, frac: float, dist: float | None) -> float:
        p = self.p
        q = float(np.clip((frac - p.min_pixels_frac) / max(p.full_pixels_frac - p.min_pixels_frac, 1e-9), 0, 1))
        if dist is not None:
            q *= float(np.clip((p.max_range_m - dist) / max(p.max_range_m - p.near_m, 1e-9), 0.0, 1.0))
        return q

    def _bleed(self, rng: np.random.Generator, mask: np.ndarray) -> np.ndarray:
        h, w = mask.shape
        b = int(rng.integers(0, round(self.p.bleed_frac * min(h, w)) + 1))
        if b == 0:
            return mask
        ys, xs = np.nonzero(mask)
        y0, y1 = max(0, ys.min() - b), min(h, ys.max() + b + 1)
        x0, x1 = max(0, xs.min() - b), min(w, xs.max() + b + 1)
        out = mask.copy()
        out[y0:y1, x0:x1] = ndimage.binary_dilation(mask[y0:y1, x0:x1], iterations=b)
        return out

    def _score(self, rng: np.random.Generator, cls_name: str, q: float, factor: float = 1.0) -> float:
        s = self.class_confidence(cls_name) * (0.55 + 0.45 * q) * factor + rng.normal(0.0, self.p.score_sd)
        return float(np.clip(s, 0.0, 1.0))

    def detect(self, req: DetectRequest) -> list[Detection]:
        validate_detect_request(req)
        if req.instances is None:
            raise BadRequest(
                "the simulated detector reads the simulator's instance ids and this frame has none; "
                "use EQA_DETECTOR_BACKEND=hf (a real detector) for real images"
            )
        p = self.p
        inst = np.asarray(req.instances)
        h, w = inst.shape
        area = float(h * w)
        depth = np.asarray(req.depth) if req.depth is not None else None
        base = [req.seed, _h(req.draw_key), req.step]
        dets: list[Detection] = []
        labels: list[InstanceLabel] = sorted(req.labels, key=lambda lab: lab.id)
        for lab in labels:
            cat = cs.norm_category(lab.category)
            if cat in STRUCTURE:
                continue
            mask = inst == lab.id
            pixels = int(mask.sum())
            if pixels == 0:
                continue  # not in this frame: never seen
            dist = None
            if depth is not None:
                d = depth[mask]
                d = d[np.isfinite(d) & (d > 0)]
                dist = float(np.median(d)) if d.size else None
            q = self.quality(pixels / area, dist)
            true_cls = next((c for c in req.classes if matches(c, cat)), None)
            sims = [c for c in req.classes if c != true_cls and similar(c, cat)]
            r = np.random.default_rng([*base, lab.id + 1])
            if true_cls is not None:
                if r.random() >= p.recall * q:
                    continue  # missed (small, far, or just missed)
                reported, factor = true_cls, 1.0
                if sims and r.random() < p.confusion:
                    reported, factor = sims[int(r.integers(len(sims)))], p.confusion_score
            elif sims and r.random() < p.similar_fp * q:
                reported, factor = sims[int(r.integers(len(sims)))], p.confusion_score
            else:
                continue
            det = make_detection(reported, self._score(r, reported, q, factor), self._bleed(r, mask))
            if det is not None:
                dets.append(det)
        dets.extend(self._background(np.random.default_rng([*base, 0]), req, inst, labels))
        return finish(dets, req)

    def _background(
        self, rng: np.random.Generator, req: DetectRequest, inst: np.ndarray, labels: list[InstanceLabel]
    ) -> list[Detection]:
        """False positives on background surfaces (walls, floors, other furniture), one chance per class."""
        p = self.p
        h, w = inst.shape
        visible = [lab for lab in labels if lab.pixels > 0]
        out: list[Detection] = []
        if not visible:
            return out
        weights = np.array([lab.pixels for lab in visible], dtype=np.float64)
        for cls_name in req.classes:
            if rng.random() >= p.background_fp:
                continue
            lab = visible[int(rng.choice(len(visible), p=weights / weights.sum()))]
            ys, xs = np.nonzero(inst == lab.id)
            if ys.size == 0:
                continue
            k = int(rng.integers(ys.size))
            radius = max(2.0, p.fp_radius_frac * min(h, w) * float(rng.uniform(0.6, 1.4)))
            yy, xx = np.ogrid[:h, :w]
            blob = ((yy - ys[k]) ** 2 + (xx - xs[k]) ** 2 <= radius**2) & (inst == lab.id)
            det = make_detection(cls_name, float(rng.uniform(p.fp_score_lo, p.fp_score_hi)), blob)
            if det is not None:
                out.append(det)
        return out
