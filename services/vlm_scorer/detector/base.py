"""The detector interface behind the scorer pool: :class:`eqa.messages.DetectRequest` in, detections out.

A detector backend returns :class:`eqa.messages.Detection` objects (class, score, box, mask cropped to the
box) whose score is at or above the request's threshold for their class (``DetectRequest.thresholds``; the
HELIOS defaults od_g 0.25 object, od_a 0.35 start receptacle, od_b 0.45 goal receptacle are filled in by the
caller from ``EQA_HELIOS_OD_*``). At most ``MAX_DETECTIONS`` are returned, the highest scores first.
"""

from __future__ import annotations

import abc

import numpy as np

from eqa.messages import MAX_DETECTIONS, Detection, DetectRequest
from services.vlm_scorer.backends.base import BadRequest

MIN_IMAGE_SIDE = 8
MAX_IMAGE_SIDE = 8192
DEFAULT_THRESHOLD = 0.45  # HomeRobot's DETIC default, when a request gives no thresholds


def validate_detect_request(req: DetectRequest) -> None:
    """:class:`BadRequest` with the reason for a request no detector can serve."""
    rgb = req.rgb
    if not isinstance(rgb, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise BadRequest(f"rgb must be an HxWx3 uint8 image, got {getattr(rgb, 'shape', None)}")
    h, w = rgb.shape[:2]
    if not (MIN_IMAGE_SIDE <= h <= MAX_IMAGE_SIDE and MIN_IMAGE_SIDE <= w <= MAX_IMAGE_SIDE):
        raise BadRequest(f"rgb is {w}x{h}; each side must be {MIN_IMAGE_SIDE}..{MAX_IMAGE_SIDE} pixels")
    if any(not c.strip() for c in req.classes):
        raise BadRequest("a detection class is blank")
    if len({c.strip().lower() for c in req.classes}) != len(req.classes):
        raise BadRequest(f"detection classes must be distinct: {req.classes}")
    if req.instances is not None and req.instances.shape != (h, w):
        raise BadRequest(f"instances has shape {req.instances.shape}, expected {(h, w)} like rgb")
    if req.depth is not None and req.depth.shape != (h, w):
        raise BadRequest(f"depth has shape {req.depth.shape}, expected {(h, w)} like rgb")


def thresholds(req: DetectRequest) -> dict[str, float]:
    return dict(zip(req.classes, req.thresholds or [DEFAULT_THRESHOLD] * len(req.classes), strict=True))


def make_detection(cls: str, score: float, mask: np.ndarray) -> Detection | None:
    """A :class:`Detection` of a full-image boolean ``mask`` (None when the mask is empty)."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return None
    x0, x1, y0, y1 = int(xs.min()), int(xs.max()) + 1, int(ys.min()), int(ys.max()) + 1
    return Detection(cls=cls, score=float(np.clip(score, 0.0, 1.0)), box=(x0, y0, x1, y1), mask=mask[y0:y1, x0:x1])


def finish(dets: list[Detection], req: DetectRequest) -> list[Detection]:
    """Per-class thresholds, highest score first, at most ``MAX_DETECTIONS``."""
    th = thresholds(req)
    kept = [d for d in dets if d.score >= th.get(d.cls, DEFAULT_THRESHOLD)]
    return sorted(kept, key=lambda d: -d.score)[:MAX_DETECTIONS]


class Detector(abc.ABC):
    name: str = "detector"
    model_name: str = ""

    @abc.abstractmethod
    def detect(self, req: DetectRequest) -> list[Detection]:
        """Detections of ``req.classes`` (see the module docstring). :class:`BadRequest` for bad input."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release resources."""
