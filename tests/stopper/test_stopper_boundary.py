"""A test score equal to q_hat keeps its label (the boundary of Eq. 10 in floating point)."""

from __future__ import annotations

import numpy as np
import pytest
from support.factories import episode_start

from eqa.messages import StepScores, StopConfig
from services.stopper import conformal
from services.stopper.calibration import Trace, TraceStep, calibrate
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide

F = [0.1, 0.9]
REL = 0.7


def _trace(i: int) -> Trace:
    return Trace(question_id=f"q{i}", scene="s", choices=["yes", "no"], answer="A", max_steps=1,
                 strategy="semantic", steps=[TraceStep(answer_probs=F, relevance=REL)])


def test_the_naive_comparison_really_drops_this_tie() -> None:
    """The example is a real floating-point trap (else the test below proves nothing)."""
    rho = conformal.relevance_weighted_confidence(np.array(F), REL)[0]
    q_hat = 1.0 - rho
    assert not rho >= 1.0 - q_hat


@pytest.mark.parametrize("eps", [0.1, 0.2, 0.5])
def test_ten_identical_calibration_episodes_then_the_same_episode_keeps_its_true_answer(eps: float) -> None:
    table = calibrate([_trace(i) for i in range(10)], [eps], name="tie")
    entry = table.entries[0]
    assert entry.q_hat == table.kappas[0]
    start = episode_start(max_steps=1, stop=StopConfig(rule="cp", eps=eps))
    rec = EpisodeRecord.from_start(start, "r")
    rec.calibration = CalibrationChoice(q_hat=entry.q_hat, eps=eps, asked_eps=eps, n=table.n, source="test")
    d = decide(rec, StepScores(episode_id="e", step=0, answer_probs=F, relevance=REL))
    assert d is not None and d.stop
    # before the fix: set {B}, answer B; now the true answer stays (B too: Rel * (1 - 0.9) <= q_hat - 1)
    assert d.step_set == ["A", "B"] and d.prediction_set == ["A", "B"], d.reason
    # the sequence-level set (Claim 1) agrees
    rhos = conformal.relevance_weighted_confidence(np.array([F]), np.array([REL]))
    assert conformal.sequence_set(rhos, entry.q_hat)[0]
    assert conformal.running_intersection(rhos, entry.q_hat)[-1][0]
