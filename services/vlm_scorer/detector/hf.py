"""Local transformers zero-shot detector (``detector_backend=hf``), loaded from a directory.

Supported families (by ``config.model_type``): ``owlvit`` (OWL-ViT) and ``owlv2`` (OWLv2), loaded with
``AutoModelForZeroShotObjectDetection``, ``AutoTokenizer`` and ``AutoImageProcessor`` from the directory only
(``local_files_only``; nothing is downloaded). Each class is queried with the OWL-ViT prompt "a photo of a
{class}"; the processor's ``post_process_object_detection`` gives boxes, scores and the best class per box;
the request's per-class thresholds are applied after it. Grounding-DINO-class models are refused with a
clear message (their text-span post-processing is another code path, not built here).

OWL-ViT and OWLv2 predict boxes, not masks: a detection's mask is its box, filled. Such masks bleed by
construction over the object's border; the object layer's mask erosion and its re-observation test (the
depth must match) are what keep the background out.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from eqa.messages import Detection, DetectRequest
from services.vlm_scorer.backends.base import BackendUnavailable
from services.vlm_scorer.detector.base import Detector, finish, make_detection, thresholds, validate_detect_request

log = logging.getLogger(__name__)

FAMILIES = {"owlvit", "owlv2"}
PROMPT = "a photo of a {}"


def check_detector_dir(path: str | Path | None) -> Path:
    """``path`` if it looks like a saved transformers model, else :class:`BackendUnavailable` saying what to
    set (cheap: no torch)."""
    if path is None:
        raise BackendUnavailable("detector_backend=hf needs a model directory: set EQA_DETECTOR_MODEL_PATH")
    p = Path(path)
    if not p.is_dir():
        raise BackendUnavailable(f"detector model directory {str(p)!r} does not exist (set EQA_DETECTOR_MODEL_PATH)")
    if not (p / "config.json").is_file():
        raise BackendUnavailable(f"{str(p)!r} has no config.json: not a transformers model directory")
    return p


class HFDetector(Detector):
    name = "hf"

    def __init__(self, path: str | Path, device: str = "cpu") -> None:
        import torch
        from transformers import AutoConfig, AutoImageProcessor, AutoModelForZeroShotObjectDetection, AutoTokenizer

        self.path = check_detector_dir(path)
        try:
            config = AutoConfig.from_pretrained(self.path, local_files_only=True)
        except Exception as exc:
            raise BackendUnavailable(f"cannot read the model config in {str(self.path)!r}: {exc}") from exc
        model_type = getattr(config, "model_type", "?")
        if model_type not in FAMILIES:
            raise BackendUnavailable(
                f"{str(self.path)!r} holds a {model_type!r} model, not a supported zero-shot detector "
                f"(supported: {', '.join(sorted(FAMILIES))})"
            )
        self.torch = torch
        self.device = torch.device(device)
        self.tokenizer = AutoTokenizer.from_pretrained(self.path, local_files_only=True)
        self.image_processor = AutoImageProcessor.from_pretrained(self.path, local_files_only=True)
        self.net = AutoModelForZeroShotObjectDetection.from_pretrained(self.path, local_files_only=True)
        self.net.to(self.device).eval()
        self.max_text = int(getattr(config.text_config, "max_position_embeddings", 16))
        self.model_name = f"{model_type}:{self.path.name}"
        self._lock = threading.Lock()
        log.info("hf detector: %s (%s) on %s", self.path, model_type, self.device)

    def detect(self, req: DetectRequest) -> list[Detection]:
        from PIL import Image

        validate_detect_request(req)
        h, w = req.rgb.shape[:2]
        texts = [PROMPT.format(c.strip()) for c in req.classes]
        enc = self.tokenizer(
            texts, padding="max_length", max_length=self.max_text, truncation=True, return_tensors="pt"
        )
        vis = self.image_processor(images=[Image.fromarray(req.rgb)], return_tensors="pt")
        inputs = {
            "input_ids": enc["input_ids"].to(self.device),
            "attention_mask": enc["attention_mask"].to(self.device),
            "pixel_values": vis["pixel_values"].to(self.device),
        }
        with self._lock, self.torch.inference_mode():
            out = self.net(**inputs)
        floor = min(thresholds(req).values())
        # OWLv2 pads the image to a square: boxes are relative to the padded side
        side = max(h, w) if self.net.config.model_type == "owlv2" else None
        size = [(side, side)] if side else [(h, w)]
        res = self.image_processor.post_process_object_detection(out, threshold=floor, target_sizes=size)[0]
        dets = []
        rows = zip(res["scores"].tolist(), res["labels"].tolist(), res["boxes"].tolist(), strict=True)
        for score, label, box in rows:
            x0, y0 = int(np.clip(np.floor(box[0]), 0, w - 1)), int(np.clip(np.floor(box[1]), 0, h - 1))
            x1, y1 = int(np.clip(np.ceil(box[2]), x0 + 1, w)), int(np.clip(np.ceil(box[3]), y0 + 1, h))
            mask = np.zeros((h, w), dtype=bool)
            mask[y0:y1, x0:x1] = True
            det = make_detection(req.classes[int(label)], float(score), mask)
            if det is not None:
                dets.append(det)
        return finish(dets, req)
