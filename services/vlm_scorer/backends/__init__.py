"""Scorer backends behind one interface (:class:`services.vlm_scorer.backends.base.Backend`)."""

from __future__ import annotations

from eqa.settings import Settings
from services.vlm_scorer.backends.base import Backend, BackendUnavailable


def make_backend(settings: Settings) -> Backend:
    """The backend chosen by ``settings.scorer_backend`` (``EQA_SCORER_BACKEND``)."""
    if settings.scorer_backend == "oracle":
        from services.vlm_scorer.backends.oracle import OracleBackend

        return OracleBackend.from_settings(settings)
    if settings.scorer_backend == "hf":
        from services.vlm_scorer.backends.hf import HFBackend

        if settings.hf_model_path is None:
            raise BackendUnavailable("scorer_backend=hf needs a model directory: set EQA_HF_MODEL_PATH")
        return HFBackend(settings.hf_model_path, device=settings.hf_device)
    if settings.scorer_backend == "remote":
        from services.vlm_scorer.backends.remote import RemoteBackend

        return RemoteBackend.from_settings(settings)
    raise BackendUnavailable(f"unknown scorer backend {settings.scorer_backend!r}")


__all__ = ["Backend", "BackendUnavailable", "make_backend"]
