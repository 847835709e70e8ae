"""Helpers every ``eqa bench`` command shares: the settings a run uses and the label its figures carry."""

from __future__ import annotations

import argparse
from typing import Any


def scorer_label(settings: Any) -> str:
    if settings.scorer_backend == "oracle":
        return "scorer: oracle (simulated perception model, not a VLM)"
    model = settings.hf_model_path if settings.scorer_backend == "hf" else settings.remote_model
    return f"scorer: {settings.scorer_backend} ({model})"


def _settings(args: argparse.Namespace) -> Any:
    from eqa_app.cli import UsageError, check_scorer, load_settings

    settings = load_settings()
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must look like 640x480, got {args.size!r}") from None
    if not (16 <= w <= 4096 and 12 <= h <= 4096):
        raise UsageError(f"--size {args.size} is out of range")
    if args.limit is not None and args.limit < 1:
        raise UsageError("--limit must be at least 1")
    update: dict[str, Any] = {"sim_width": w, "sim_height": h, "record": False}
    if args.scorer is not None:
        update["scorer_backend"] = args.scorer
    settings = settings.model_copy(update=update)
    check_scorer(settings)
    if args.robots < 1 or args.scorers < 1:
        raise UsageError("--robots and --scorers must be at least 1")
    return settings


def _quantile_defined(n: int, eps: float) -> bool:
    from services.stopper.conformal import CalibrationError, quantile_rank

    try:
        quantile_rank(n, eps)
    except CalibrationError:
        return False
    return True
