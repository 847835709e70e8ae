"""The CP miscoverage level eps is bounded in one place (eqa.messages.EPS_GT / EPS_LT); the bus message, the
gateway's request schema, the calibration and the CLI all accept and refuse the same values."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from eqa.messages import EPS_GT, EPS_LT, StopConfig, eps_in_bounds
from gateway.schemas import QuestionRequest
from services.stopper.conformal import CalibrationError, check_eps

SPAN = EPS_LT - EPS_GT
VALUES = [EPS_GT, EPS_LT, EPS_GT - 0.1, EPS_LT + 0.5, EPS_GT + 1e-9, EPS_LT - 1e-9, EPS_GT + SPAN / 2,
          math.nan, math.inf, -math.inf]


def _accepts(fn, value: float) -> bool:
    try:
        fn(value)
    except (ValidationError, CalibrationError):
        return False
    return True


@pytest.mark.parametrize("value", VALUES)
def test_every_eps_check_agrees_with_the_kernel_bounds(value: float) -> None:
    want = eps_in_bounds(value)
    assert want == (math.isfinite(value) and EPS_GT < value < EPS_LT)
    assert _accepts(lambda v: StopConfig(eps=v), value) is want
    assert _accepts(lambda v: QuestionRequest(question="Where is the mug?", scene="gen-00001", eps=v), value) is want
    assert _accepts(check_eps, value) is want


def test_the_schemas_publish_the_kernel_bounds() -> None:
    for schema in (StopConfig.model_json_schema(), QuestionRequest.model_json_schema()):
        eps = schema["properties"]["eps"]
        assert (eps["exclusiveMinimum"], eps["exclusiveMaximum"]) == (EPS_GT, EPS_LT)


def test_the_cli_refuses_what_the_kernel_refuses() -> None:
    import argparse

    from eqa_app.ask import AskError, _body, register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    for value, ok in ((EPS_GT, False), (EPS_LT, False), (EPS_GT + SPAN / 2, True)):
        args = parser.parse_args(["ask", "--scene", "gen-00001", f"--eps={value!r}", "Where is the mug?"])
        try:
            _body(args, scenes_dir=None)  # type: ignore[arg-type]
        except AskError as exc:
            assert not ok and "--eps" in str(exc)
        else:
            assert ok
