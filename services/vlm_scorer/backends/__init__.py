"""Scorer backends behind one interface (:class:`services.vlm_scorer.backends.base.Backend`)."""

from __future__ import annotations

from eqa.settings import SettingsGroup
from services.vlm_scorer.backends.base import Backend, BackendUnavailable


def check_settings(settings: SettingsGroup) -> None:
    """Cheap checks of the chosen backend's settings and of the detector's (no model is loaded), for the
    command line to refuse a fleet whose scorer could only answer errors. :class:`BackendUnavailable` says
    what to set."""
    if settings.scorer_backend == "hf":
        from services.vlm_scorer.backends.hf import check_model_dir

        check_model_dir(settings.hf_model_path)
    elif settings.scorer_backend == "remote":
        from services.vlm_scorer.backends.remote import check_endpoint

        check_endpoint(settings.remote_base_url, settings.remote_model)
    from services.vlm_scorer.detector import check_detector_settings  # HELIOS detector

    check_detector_settings(settings)


def make_backend(settings: SettingsGroup) -> Backend:
    """The backend chosen by ``settings.scorer_backend`` (``EQA_SCORER_BACKEND``)."""
    if settings.scorer_backend == "oracle":
        from services.vlm_scorer.backends.oracle import OracleBackend

        return OracleBackend.from_settings(settings)
    if settings.scorer_backend == "hf":
        from services.vlm_scorer.backends.hf import HFBackend, check_model_dir

        return HFBackend(check_model_dir(settings.hf_model_path), device=settings.hf_device)
    if settings.scorer_backend == "remote":
        from services.vlm_scorer.backends.remote import RemoteBackend

        return RemoteBackend.from_settings(settings)
    raise BackendUnavailable(f"unknown scorer backend {settings.scorer_backend!r}")


__all__ = ["Backend", "BackendUnavailable", "check_settings", "make_backend"]
