"""The HELIOS object layer in a question episode (issue 22, item 2): track the question's target class.

For an existence or counting question (``question.query`` names the ``category`` and maybe a ``room_kind``) the
mapper keeps an :class:`~services.mapper.object_map.ObjectMap` with the one target class (detector threshold
od_g, HELIOS Table 3), fuses each frame's detections into it (the layer is used as is, not restructured) and
reports, per step, an :class:`~services.stopper.object_evidence.ObjectEvidence`: the ``Psi`` (HELIOS Eq. 7) of
the target-class instances whose centre lies in the asked region, and the explored share of that region.

The region is the rooms of the asked kind (or the whole house) as rectangles in world coordinates. The robot
needs a room layout for that; here it is the scene's floor plan (:attr:`services.sim.scene.Scene.rooms`), i.e.
the robot is assumed to know the floor plan (not the objects). That is a simplification: a real robot would
segment rooms from its own map, with errors this evaluation does not have.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from eqa.messages import MAX_EVIDENCE_INSTANCES, DetectRequest, DetectResult, Frame, GridSpec, ObjectEvidence, Question

CATEGORIES = ("counting", "existence")  # the question categories the class-level layer can answer (not colours)

Rect = tuple[float, float, float, float]  # x0, y0, x1, y1


def question_target(question: Question) -> tuple[str, str, str | None] | None:
    """``(question category, target class, room kind or None)`` for a question the layer can help with."""
    q = {str(k).lower(): v for k, v in question.query.items()}
    category = question.category or q.get("type")
    cls = q.get("category")
    if category not in CATEGORIES or not cls:
        return None
    return str(category), str(cls), (str(q["room_kind"]) if q.get("room_kind") else None)


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
        self.om = ObjectMap([self.cls], [cfg.od_object], cfg)

    def detect_request(self, frame: Frame, seed: int = 0) -> DetectRequest:
        return self.om.detect_request(frame, seed)

    def integrate(self, frame: Frame, result: DetectResult) -> None:
        self.om.integrate(frame, result)

    def evidence(self, explored: np.ndarray | None, grid: GridSpec | None) -> ObjectEvidence:
        """The step's evidence: target-class instances in the region (best first, at most MAX_TRACKED) and
        the explored share of the region (of the house's floor area when no room is asked). ``explored``: the
        mapper's 2D cells seen by the camera (``Maps2D.observed``: the detector sees the whole frame, not only
        Explore-EQA's narrow view)."""
        psi = []
        for inst in self.om.layer.instances():
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
