"""Answer memory: pooling, bounds, causality, calibration with the same rule, decide()."""

from __future__ import annotations

import numpy as np
import pytest

from eqa.messages import EpisodeStart, Question, StepScores, StopConfig
from services.stopper import synthetic
from services.stopper.answer_memory import (
    MAX_K,
    AnswerRule,
    memory_answer,
    pool,
    rule_mismatch,
    top_k,
    transform,
)
from services.stopper.calibration import calibrate
from services.stopper.conformal import conformal_quantile, sequence_set
from services.stopper.replay import replay_arrays
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide


def test_loglinear_and_linear_pooling_by_hand() -> None:
    f = np.array([[0.5, 0.5], [0.9, 0.1]])
    rel = np.array([0.2, 0.6])  # weights 1/4, 3/4
    a = 0.5**0.25 * 0.9**0.75
    b = 0.5**0.25 * 0.1**0.75
    assert pool(f, rel, "loglinear") == pytest.approx([a / (a + b), b / (a + b)])
    assert pool(f, rel, "linear") == pytest.approx([0.25 * 0.5 + 0.75 * 0.9, 0.25 * 0.5 + 0.75 * 0.1])
    # geometric pooling of agreeing views does not sharpen beyond them (errors of one VLM are shared)
    same = np.array([[0.8, 0.2]] * 5)
    assert pool(same, np.ones(5)) == pytest.approx([0.8, 0.2])
    assert pool(f, np.zeros(2), "linear") == pytest.approx([0.7, 0.3])  # no relevance: uniform weights


def test_top_k_ties_and_transform_is_causal_and_k0_is_the_paper() -> None:
    assert top_k(np.array([0.3, 0.5, 0.5, 0.1]), 2).tolist() == [1, 2]
    assert top_k(np.array([0.5, 0.5, 0.5]), 2).tolist() == [0, 1]
    ep = synthetic.episodes(1, seed=3)[0]
    f, r = ep.probs, ep.relevance
    same_f, same_r = transform(f, r, AnswerRule(0))
    assert same_f is not None and np.array_equal(same_f, f) and np.array_equal(same_r, r)
    rule = AnswerRule(3, "loglinear")
    full_f, full_r = transform(f, r, rule)
    for t in (0, 4, len(r) - 1):
        pf, pr = transform(f[: t + 1], r[: t + 1], rule)
        assert np.array_equal(pf, full_f[: t + 1]) and np.array_equal(pr, full_r[: t + 1])  # step t sees <= t
        assert full_r[t] == r[: t + 1].max()
    # K = 1 answers like the paper's fallback: argmax f at the most relevant step
    assert memory_answer(f, r, AnswerRule(1)) == memory_answer(f, r, AnswerRule(0)) == int(np.argmax(f[np.argmax(r)]))


def test_rule_bounds_and_names() -> None:
    for bad in (-1, MAX_K + 1):
        with pytest.raises(ValueError, match="answer memory K"):
            AnswerRule(bad)
    with pytest.raises(ValueError, match="fusion"):
        AnswerRule(2, "product")  # type: ignore[arg-type]
    assert AnswerRule.from_name(AnswerRule(4, "linear").name) == AnswerRule(4, "linear")
    assert AnswerRule.from_name(None) == AnswerRule()
    assert rule_mismatch(None, AnswerRule()) == ""
    assert "eqa calibrate --answer-memory 3" in rule_mismatch("single", AnswerRule(3))


@pytest.mark.parametrize("eps", [0.2])
def test_calibrating_the_memory_rule_holds_coverage_on_exchangeable_episodes(eps: float) -> None:
    """Eq. 6 for the pooled scores: calibrate on N synthetic episodes with the rule, test on fresh ones;
    mean coverage over repetitions >= 1 - eps (minus the Monte-Carlo error)."""
    rule = AnswerRule(3, "loglinear")
    covered, total = 0, 0
    for rep in range(8):
        eps_all = synthetic.episodes(200, seed=100 + rep)
        cal, test = eps_all[:100], eps_all[100:]
        traces = [synthetic.to_trace(e, f"q{i}") for i, e in enumerate(cal)]
        table = calibrate(traces, [eps], answer_rule=rule)
        assert table.provenance["answer_rule"] == "memory-3-loglinear"
        q_hat = table.lookup(eps)[0].q_hat  # type: ignore[index]
        for e in test:
            f, r = transform(e.probs, e.relevance, rule)
            from services.stopper.conformal import relevance_weighted_confidence

            covered += bool(sequence_set(relevance_weighted_confidence(f, r), q_hat)[e.answer])
            total += 1
    assert covered / total >= 1 - eps - 0.03  # ~2 standard errors of 800 test episodes


def test_calibration_uses_the_rule_not_the_raw_scores() -> None:
    """A planted bug (calibrating the raw scores for a memory episode) gives other kappas: the table's scores
    must be those of the rule."""
    eps_all = synthetic.episodes(60, seed=7)
    traces = [synthetic.to_trace(e, f"q{i}") for i, e in enumerate(eps_all)]
    rule = AnswerRule(4, "linear")
    with_rule = calibrate(traces, [0.2], answer_rule=rule)
    raw = calibrate(traces, [0.2])
    assert raw.provenance["answer_rule"] == "single"
    assert with_rule.kappas == [t.kappa(rule) for t in traces]
    assert with_rule.kappas != raw.kappas
    assert with_rule.entries[0].q_hat == conformal_quantile(with_rule.kappas, 0.2)


def _record(k: int, q_hat: float, probs: np.ndarray) -> EpisodeRecord:
    q = Question(id="q1", text="Which one?", choices=[f"c{i}" for i in range(probs.shape[1])], scene="s",
                 answer="A")
    start = EpisodeStart(episode_id="e1", robot="r", question=q, max_steps=probs.shape[0],
                         stop=StopConfig(rule="cp", eps=0.2))
    rec = EpisodeRecord.from_start(start, "r")
    rec.answer_memory = k
    rec.calibration = CalibrationChoice(q_hat=q_hat, eps=0.2, asked_eps=0.2, n=100, source="test",
                                        answer_rule=AnswerRule(k).name)
    return rec


@pytest.mark.parametrize("k", [0, 3])
def test_decide_with_memory_matches_the_array_replay(k: int) -> None:
    """The stopper's decide() with the answer memory stops at the step and with the answer the offline
    benchmarks replay (services/stopper/replay.py; so the benchmarks' figures are the service's behaviour)."""
    rule = AnswerRule(k)
    cal = synthetic.episodes(120, seed=31)
    q_hat = calibrate([synthetic.to_trace(e, f"q{i}") for i, e in enumerate(cal)], [0.2],
                      answer_rule=rule).entries[0].q_hat
    n_stop_early = 0
    for e in synthetic.episodes(25, seed=32):
        rec = _record(k, q_hat, e.probs)
        d = None
        for t in range(e.probs.shape[0]):
            d = decide(rec, StepScores(episode_id="e1", step=t, answer_probs=e.probs[t].tolist(),
                                       relevance=float(e.relevance[t])))
            assert d is not None
            if d.stop:
                break
        assert d is not None and d.stop
        out = replay_arrays(e.probs, e.relevance, e.probs.shape[0], "cp", q_hat, rule)
        assert "ABCDEFGH"[out.answer] == d.answer
        assert out.step == d.step
        n_stop_early += d.step + 1 < e.probs.shape[0]
        if k:
            assert "answer memory memory-3-loglinear" in d.reason
    assert n_stop_early > 0  # the CP path was exercised, not only the budget fallback


def test_incremental_memory_equals_the_top_k_definition() -> None:
    rng = np.random.default_rng(5)
    f = rng.dirichlet(np.ones(4), size=30)
    rel = np.round(rng.random(30), 1)  # many ties
    for rule in (AnswerRule(1), AnswerRule(3, "linear"), AnswerRule(5, "loglinear")):
        pf, pr = transform(f, rel, rule)
        for t in range(30):
            idx = top_k(rel[: t + 1], rule.k)
            assert pf[t] == pytest.approx(pool(f[idx], rel[idx], rule.fusion), abs=1e-12)
            assert pr[t] == rel[idx].max()
