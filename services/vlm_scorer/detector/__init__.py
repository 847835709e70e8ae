"""Open-vocabulary detectors behind the scorer pool (HELIOS: DETIC with per-class thresholds).

Backends (``EQA_DETECTOR_BACKEND``):

* ``oracle`` -- the simulated detector (:mod:`.oracle`), a stand-in for DETIC in the simulator; never a real
  detector, always labelled so.
* ``hf`` -- a local transformers zero-shot detector, OWL-ViT / OWLv2 (:mod:`.hf`), from
  ``EQA_DETECTOR_MODEL_PATH``.
* ``remote`` -- refused: unlike chat-completions for VLMs, there is no well-known HTTP protocol for
  open-vocabulary detection that servers share (each hosted detector has its own request and response
  shapes), so there is nothing standard to speak. Run the ``hf`` backend on a GPU replica of the pool instead.
"""

from __future__ import annotations

from eqa.settings import SettingsGroup
from services.vlm_scorer.backends.base import BackendUnavailable
from services.vlm_scorer.detector.base import Detector

REMOTE_REFUSAL = (
    "detector_backend=remote is not available: there is no well-known HTTP protocol for open-vocabulary "
    "detection to speak (hosted detectors each define their own API). Use EQA_DETECTOR_BACKEND=hf with a "
    "local OWL-ViT/OWLv2 directory (EQA_DETECTOR_MODEL_PATH) on a GPU scorer replica, or oracle in the simulator"
)


def check_detector_settings(settings: SettingsGroup) -> None:
    """Cheap checks of the detector settings (no model loaded); :class:`BackendUnavailable` says what to set."""
    if settings.detector_backend == "hf":
        from services.vlm_scorer.detector.hf import check_detector_dir

        check_detector_dir(settings.detector_model_path)
    elif settings.detector_backend == "remote":
        raise BackendUnavailable(REMOTE_REFUSAL)


def make_detector(settings: SettingsGroup) -> Detector:
    """The detector chosen by ``EQA_DETECTOR_BACKEND``."""
    check_detector_settings(settings)
    if settings.detector_backend == "oracle":
        from services.vlm_scorer.detector.oracle import OracleDetector

        return OracleDetector.from_settings(settings)
    if settings.detector_backend == "hf":
        from services.vlm_scorer.detector.hf import HFDetector

        return HFDetector(settings.detector_model_path, device=settings.hf_device)  # type: ignore[arg-type]
    raise BackendUnavailable(f"unknown detector backend {settings.detector_backend!r}")


__all__ = ["REMOTE_REFUSAL", "Detector", "check_detector_settings", "make_detector"]
