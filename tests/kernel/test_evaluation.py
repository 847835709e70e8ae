"""Benchmark replay: budgets and stopping rules read from recorded traces, checked by hand."""

from __future__ import annotations

import numpy as np
import pytest

from eqa.messages import StopConfig
from eqa_app.evaluation import answer_within, cp_curve, replay, success_at_budgets, threshold_curve
from services.stopper.calibration import Trace, TraceStep, calibrate
from services.stopper.state import CalibrationChoice

CHOICES = ["a", "b", "c", "d"]


def _trace(steps: list[tuple[list[float], float]], answer: str = "B", qid: str = "q", max_steps: int | None = None):
    return Trace(question_id=qid, scene="gen-00001", category="state", choices=CHOICES, answer=answer,
                 max_steps=max_steps or len(steps), strategy="semantic",
                 steps=[TraceStep(answer_probs=f, relevance=r) for f, r in steps])


UNIFORM = [0.25, 0.25, 0.25, 0.25]
SURE_B = [0.05, 0.85, 0.05, 0.05]
SURE_D = [0.05, 0.05, 0.05, 0.85]


def test_answer_at_a_budget_is_argmax_f_at_the_most_relevant_step_so_far():
    t = _trace([(SURE_D, 0.1), (UNIFORM, 0.05), (SURE_D, 0.2), (UNIFORM, 0.1), (SURE_B, 0.9),
                (UNIFORM, 0.1), (UNIFORM, 0.1), (UNIFORM, 0.1), (UNIFORM, 0.1), (UNIFORM, 0.1)])
    assert answer_within(t, 1) == "D" and answer_within(t, 4) == "D" and answer_within(t, 5) == "B"
    # budgets 0.1..1.0 of T=10 steps -> 1..10 steps: wrong (D) until step 5 is included
    assert success_at_budgets([t]) == [0, 0, 0, 0, 1, 1, 1, 1, 1, 1]


def test_cp_replay_stops_when_one_answer_is_left_and_matches_the_rule_by_hand():
    q_hat = 1.3  # keep y at step t iff Rel * (f_y - 1) >= -0.3
    cal = CalibrationChoice(q_hat=q_hat, eps=0.2, asked_eps=0.2, n=50, source="test")
    t = _trace([(UNIFORM, 0.1), (SURE_B, 0.5), (SURE_B, 0.9), (UNIFORM, 0.1)])
    r = replay(t, StopConfig(rule="cp", eps=0.2), cal)
    # step 0: rho = -0.075 for all -> keep all; step 1: rho_B = -0.075, others -0.475 -> {B}: stop
    assert (r.answer, r.steps, r.correct, r.prediction_set) == ("B", 2, True, ("B",))


def test_threshold_rules_and_fallback_when_nothing_fires():
    t = _trace([(UNIFORM, 0.1), (SURE_D, 0.2), (SURE_B, 0.7), (UNIFORM, 0.1)], max_steps=6)
    rel = replay(t, StopConfig(rule="relevance", threshold=0.5))
    assert (rel.answer, rel.steps) == ("B", 3)
    ent = replay(t, StopConfig(rule="entropy", threshold=0.7))
    assert ent.answer == "D" and ent.steps == 2 and not ent.correct
    never = replay(t, StopConfig(rule="relevance", threshold=0.95))
    # the run ended at 4 of 6 steps (nothing left to explore): answer of the most relevant step
    assert (never.answer, never.steps, never.normalized_steps) == ("B", 4, pytest.approx(4 / 6))


def test_curves_report_success_steps_and_cp_coverage():
    rng = np.random.default_rng(0)
    traces = []
    for i in range(60):
        steps = []
        for _ in range(8):
            f = rng.dirichlet(np.ones(4)).tolist()
            steps.append((f, float(rng.uniform(0, 1))))
        traces.append(_trace(steps, answer="ABCD"[i % 4], qid=f"q{i:03d}"))
    table = calibrate(traces[:40], [0.2, 0.5], name="t")
    points = cp_curve(table, traces[40:])
    assert [p.parameter for p in points] == [0.2, 0.5]
    for p in points:
        assert 0 <= p.success <= 1 and 0 < p.mean_normalized_steps <= 1 and 0 <= p.coverage <= 1
    assert points[0].coverage >= points[1].coverage  # smaller eps, larger sets
    th = threshold_curve("relevance", [0.99, 0.1], traces[40:])
    assert th[0].mean_normalized_steps > th[1].mean_normalized_steps


def test_paired_comparison_counts_discordant_questions_and_exact_sign_test():
    from eqa_app.evaluation import evidence_share, first_evidence, paired_comparison
    right, wrong = [(SURE_B, 0.9)], [(SURE_D, 0.9)]
    # q0: both right, q1: only a right, q2: only a right, q3: only b right, q4: only b right at the full budget
    a = [_trace(right, qid="q0"), _trace(right, qid="q1"), _trace(right, qid="q2"), _trace(wrong, qid="q3"),
         _trace([(SURE_D, 0.9), (UNIFORM, 0.1)], qid="q4"), _trace(right, qid="only-in-a")]
    b = [_trace(right, qid="q0"), _trace(wrong, qid="q1"), _trace(wrong, qid="q2"), _trace(right, qid="q3"),
         _trace([(SURE_D, 0.1), (SURE_B, 0.9)], qid="q4")]
    half, full = paired_comparison(a, b, (0.5, 1.0))
    assert (half.a_only, half.b_only) == (2, 1)  # q4 at 1 of 2 steps: both answer D
    assert (full.a_only, full.b_only) == (2, 2) and full.p_value == 1.0
    assert evidence_share(a, 0.3) == pytest.approx(1.0) and evidence_share([_trace([(UNIFORM, 0.1)])]) == 0.0
    late = _trace([(UNIFORM, 0.1), (UNIFORM, 0.1), (SURE_B, 0.5), (UNIFORM, 0.1)])  # first at step 2 of T = 4
    assert first_evidence([late, _trace([(UNIFORM, 0.1)])]) == pytest.approx(0.5)


def test_category_round_robin_keeps_the_mix():
    from eqa.messages import Question
    from services.sim.questions import category_round_robin

    qs = [Question(id=f"{c}{i}", text="q?", scene="gen-00001", category=c) for c, i in
          [("b", 0), ("b", 1), ("b", 2), ("a", 0)]]
    assert [q.id for q in category_round_robin(qs, 3)] == ["a0", "b0", "b1"]
    assert [q.id for q in category_round_robin(qs, None)] == ["a0", "b0", "b1", "b2"]
    assert [q.id for q in category_round_robin(qs, 99)] == ["a0", "b0", "b1", "b2"]


def test_category_round_robin_over_named_categories_alternates_in_their_order():
    import itertools

    from eqa.messages import Question
    from services.sim.questions import category_round_robin

    qs = [Question(id=f"{c}{i}", text="q?", scene="gen-00001", category=c) for c, i in
          [("counting", 0), ("existence", 0), ("room", 0), ("existence", 1), ("existence", 2), ("counting", 1)]]
    both = ("existence", "counting")
    assert [q.id for q in category_round_robin(qs, None, both)] == [
        "existence0", "counting0", "existence1", "counting1", "existence2"]  # room questions are not taken
    # the same as alternating the two lists and going on with the longer one, for every n
    by = {c: [q for q in qs if q.category == c] for c in both}
    alternating = [q for pair in itertools.zip_longest(*by.values()) for q in pair if q is not None]
    for n in range(7):
        assert category_round_robin(qs, n, both) == alternating[:n]
    assert category_round_robin(qs, 3, ()) == []
