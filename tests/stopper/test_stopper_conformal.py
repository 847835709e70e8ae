"""The conformal stopping rule (Explore-EQA Eq. 7-10, Claim 1, Prop. 1) and the baselines, pure functions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eqa.messages import EpisodeStart, Question, StepScores, StopConfig
from services.stopper import baselines, conformal, synthetic
from services.stopper.calibration import calibrate
from services.stopper.conformal import CalibrationError, ScoreError
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide


def _random_rhos(rng: np.random.Generator, t: int, k: int) -> np.ndarray:
    probs = rng.dirichlet(np.full(k, 0.5), size=t)
    rel = rng.random(t)
    return conformal.relevance_weighted_confidence(probs, rel)


def test_rho_matches_eq8_and_lies_in_minus_rel_zero() -> None:
    f = np.array([0.7, 0.2, 0.1, 0.0])
    rho = conformal.relevance_weighted_confidence(f, 0.5)
    np.testing.assert_allclose(rho, [0.5 * (0.7 - 1), 0.5 * (0.2 - 1), 0.5 * (0.1 - 1), -0.5])
    rng = np.random.default_rng(1)
    rhos = _random_rhos(rng, 50, 5)
    assert rhos.max() <= 0.0 and rhos.min() >= -1.0


def test_claim1_intersection_of_causal_sets_equals_sequence_set() -> None:
    rng = np.random.default_rng(7)
    for _ in range(500):
        t, k = int(rng.integers(1, 30)), int(rng.integers(2, 7))
        rhos = _random_rhos(rng, t, k)
        # thresholds everywhere in [1, 2], including exactly at observed scores (ties)
        q_hat = float(1.0 - rhos[rng.integers(t), rng.integers(k)]) if rng.random() < 0.3 else 1 + rng.random()
        causal = np.ones(k, bool)
        for step in range(t):
            c_t = conformal.step_set(rhos[step], q_hat)
            seq = conformal.sequence_set(rhos, q_hat)
            assert np.all(c_t[seq]), "Claim 1: every C^t contains the sequence-level set"
            causal &= c_t
        np.testing.assert_array_equal(causal, conformal.sequence_set(rhos, q_hat))
        np.testing.assert_array_equal(conformal.running_intersection(rhos, q_hat)[-1], causal)


def _direct_quantile(kappas: list[float], eps: float) -> float:
    """The definition, spelled out: the smallest s with #{kappa_i <= s} >= ceil((N+1)(1-eps))."""
    n = len(kappas)
    need = math.ceil((n + 1) * (1 - eps) - 1e-9)
    for s in sorted(kappas):
        if sum(1 for k in kappas if k <= s) >= need:
            return s
    raise AssertionError("undefined")


@pytest.mark.parametrize("n", [9, 10, 19, 20, 37, 100, 300])
def test_q_hat_matches_the_quantile_formula(n: int) -> None:
    rng = np.random.default_rng(n)
    kappas = list(1.0 + rng.random(n))
    kappas[3] = kappas[5]  # a tie
    for eps in (0.05, 0.1, 0.2, 0.25, 0.5, 0.9):
        if n < math.ceil(1 / eps) - 1:
            with pytest.raises(CalibrationError, match="undefined"):
                conformal.conformal_quantile(kappas, eps)
            continue
        q = conformal.conformal_quantile(kappas, eps)
        assert q == _direct_quantile(kappas, eps)
        k = math.ceil((n + 1) * (1 - eps) - 1e-9)
        assert q == float(np.quantile(kappas, k / n, method="inverted_cdf"))
        assert q == sorted(kappas)[k - 1]


def test_quantile_boundary_n_equals_ceil_inverse_eps_minus_one() -> None:
    # eps = 0.1: N = 9 is the smallest N with a defined quantile (k = ceil(10 * 0.9) = 9 = N) -> the maximum
    kappas = [1.0 + i / 10 for i in range(9)]
    assert conformal.conformal_quantile(kappas, 0.1) == max(kappas)
    with pytest.raises(CalibrationError, match=r"at least ceil\(1/eps\) - 1 = 9"):
        conformal.conformal_quantile(kappas[:8], 0.1)


@pytest.mark.parametrize("eps", [0.0, 1.0, -0.1, 1.5, float("nan"), float("inf"), "x"])
def test_bad_eps_is_refused(eps: object) -> None:
    with pytest.raises(CalibrationError, match=r"\(0, 1\)"):
        conformal.conformal_quantile([1.1, 1.2, 1.3], eps)  # type: ignore[arg-type]
    with pytest.raises(CalibrationError):
        calibrate([], [eps])  # type: ignore[list-item]


def test_nan_scores_are_refused() -> None:
    with pytest.raises(ScoreError, match="NaN"):
        conformal.check_scores([0.5, float("nan"), 0.5], 0.3)
    with pytest.raises(ScoreError, match="relevance"):
        conformal.check_scores([0.5, 0.5], float("nan"))
    with pytest.raises(ScoreError, match="sum to 1"):
        conformal.check_scores([0.5, 0.6], 0.3)
    with pytest.raises(ScoreError, match="choices"):
        conformal.check_scores([0.5, 0.5], 0.3, n_choices=4)
    with pytest.raises(CalibrationError, match="NaN"):
        conformal.conformal_quantile([1.2, float("nan"), 1.3], 0.5)


def _calibrate_synthetic(n: int, seed: int, eps_grid: list[float]) -> dict[float, float]:
    eps_list = synthetic.episodes(n, seed)
    traces = [synthetic.to_trace(e, f"q{i}") for i, e in enumerate(eps_list)]
    table = calibrate(traces, eps_grid)
    return {e.eps: e.q_hat for e in table.entries}


def test_coverage_on_held_out_synthetic_episodes_over_many_seeds() -> None:
    """Prop. 1: P(y_test in the running intersection at every step) >= 1 - eps.

    Per seed: calibrate on N episodes, test on M fresh ones. Coverage conditional on the calibration set is
    Beta-distributed with mean in [1 - eps, 1 - eps + 1/(N+1)); the mean over R seeds has standard deviation
    sigma <= sqrt((eps(1-eps)/(N+2) + eps(1-eps)/M) / R). Stated slack: 4 sigma.
    """
    n, m, r = 60, 60, 120
    eps_grid = (0.1, 0.2, 0.4)
    covs: dict[float, list[float]] = {e: [] for e in eps_grid}
    wrong_stops: dict[float, list[float]] = {e: [] for e in eps_grid}
    early_stops: dict[float, list[float]] = {e: [] for e in eps_grid}
    for seed in range(r):
        rng = np.random.default_rng(10_000 + seed)
        cal = [synthetic.episode(rng) for _ in range(n)]
        test = [synthetic.episode(rng) for _ in range(m)]
        kappas = [conformal.nonconformity(e.probs, e.relevance, e.answer) for e in cal]
        for eps in eps_grid:
            q_hat = conformal.conformal_quantile(kappas, eps)
            hits = wrong = early = 0
            for e in test:
                running = conformal.running_intersection(e.rhos(), q_hat)
                hits += bool(running[-1, e.answer])
                # the robot stops at the first step with one answer left; is that answer wrong?
                single = np.flatnonzero(running.sum(axis=1) == 1)
                wrong += bool(single.size and not running[single[0], e.answer])
                early += bool(single.size and single[0] < len(running) - 1)
            covs[eps].append(hits / m)
            early_stops[eps].append(early / m)
            wrong_stops[eps].append(wrong / m)
    for eps in eps_grid:
        sigma = math.sqrt((eps * (1 - eps) / (n + 2) + eps * (1 - eps) / m) / r)
        mean = float(np.mean(covs[eps]))
        assert mean >= 1 - eps - 4 * sigma, (eps, mean, sigma)
        assert mean <= 1 - eps + 1 / (n + 1) + 4 * sigma, "coverage should be tight, not trivially conservative"
        # a wrong single-answer stop implies the true answer left the set: at most eps of the episodes
        assert float(np.mean(wrong_stops[eps])) <= eps + 4 * sigma
        # and the rule does stop before the limit in a share of episodes (not the trivial all-labels set)
        assert float(np.mean(early_stops[eps])) > 0.1


def _record(rule: str = "cp", q_hat: float = 1.5, max_steps: int = 10, threshold: float | None = None) -> EpisodeRecord:
    q = Question(text="What colour is the sofa?", choices=["red", "blue", "green", "grey"], scene="gen-1", answer="B")
    start = EpisodeStart(
        episode_id="ep1",
        robot="r0",
        question=q,
        max_steps=max_steps,
        stop=StopConfig(rule=rule, threshold=threshold),
    )  # type: ignore[arg-type]
    rec = EpisodeRecord.from_start(start, "r0")
    rec.threshold = threshold
    if rule == "cp":
        rec.calibration = CalibrationChoice(q_hat=q_hat, eps=0.2, asked_eps=0.2, n=100, source="test")
    return rec


def test_irrelevant_views_never_stop_early_even_when_confident() -> None:
    q_hats = _calibrate_synthetic(300, seed=3, eps_grid=[0.05, 0.2, 0.5, 0.8])
    rng = np.random.default_rng(5)
    for eps, q_hat in q_hats.items():
        assert q_hat - 1 > 0.02, f"eps={eps}: calibrated margin {q_hat - 1} too small for this check"
        for _ in range(20):
            rec = _record(q_hat=q_hat, max_steps=15)
            for t in range(15):
                probs = rng.dirichlet([0.05, 0.05, 30.0, 0.05])  # confident, biased towards C
                d = decide(
                    rec,
                    StepScores(
                        episode_id="ep1",
                        step=t,
                        answer_probs=probs.tolist(),
                        relevance=float(rng.uniform(0, 0.02)),
                    ),
                )
                assert d is not None
                assert d.prediction_set == ["A", "B", "C", "D"]
                assert d.stop == (t == 14), "only the step limit may stop it"
            assert "step limit" in d.reason
    # the entropy baseline, by contrast, stops at once on such a view (paper section VII-F)
    rec = _record(rule="entropy")
    d = decide(rec, StepScores(episode_id="ep1", step=0, answer_probs=[0.001, 0.001, 0.997, 0.001], relevance=0.01))
    assert d is not None and d.stop and d.answer == "C"


def test_cp_decisions_singleton_empty_and_limit() -> None:
    rec = _record(q_hat=1.3)  # m = 0.3: a label survives iff Rel * (1 - f) <= 0.3
    d0 = decide(rec, StepScores(episode_id="ep1", step=0, answer_probs=[0.4, 0.4, 0.1, 0.1], relevance=0.4))
    assert d0 and d0.step_set == ["A", "B"] and d0.prediction_set == ["A", "B"] and not d0.stop
    assert decide(rec, StepScores(episode_id="ep1", step=0, answer_probs=[1, 0, 0, 0], relevance=1)) is None
    d1 = decide(rec, StepScores(episode_id="ep1", step=1, answer_probs=[0.05, 0.9, 0.04, 0.01], relevance=0.9))
    assert d1 and d1.stop and d1.answer == "B" and d1.prediction_set == ["B"] and "one answer left" in d1.reason
    assert d1.scores["B"] == pytest.approx(0.9 * (0.9 - 1))

    rec = _record(q_hat=1.3)
    decide(rec, StepScores(episode_id="ep1", step=0, answer_probs=[0.4, 0.4, 0.1, 0.1], relevance=0.4))
    d = decide(rec, StepScores(episode_id="ep1", step=1, answer_probs=[0.02, 0.02, 0.95, 0.01], relevance=0.95))
    assert d and d.stop and d.prediction_set == [] and "empty" in d.reason
    assert d.answer == "C"  # argmax f at the most relevant step (step 1)

    rec = _record(q_hat=1.9, max_steps=3)
    for t, rel in enumerate([0.5, 0.8, 0.3]):
        d = decide(
            rec,
            StepScores(
                episode_id="ep1",
                step=t,
                answer_probs=[0.1, 0.2, 0.6, 0.1] if t == 1 else [0.7, 0.1, 0.1, 0.1],
                relevance=rel,
            ),
        )
    assert d and d.stop and d.answer == "C" and "step limit" in d.reason and len(d.prediction_set) == 4


def test_invalid_scores_leave_the_record_untouched() -> None:
    rec = _record()
    decide(rec, StepScores(episode_id="ep1", step=0, answer_probs=[0.25] * 4, relevance=0.1))
    before = rec.model_dump()
    with pytest.raises(ScoreError):
        decide(
            rec,
            StepScores(episode_id="ep1", step=1, answer_probs=[0.25, 0.25, float("nan"), 0.25], relevance=0.1),
        )
    with pytest.raises(ScoreError):
        decide(rec, StepScores(episode_id="ep1", step=1, answer_probs=[0.5, 0.5], relevance=0.1))
    assert rec.model_dump() == before


def test_baselines_entropy_relevance_max_steps() -> None:
    assert baselines.entropy([0.25] * 4) == pytest.approx(math.log(4))
    assert baselines.entropy([1.0, 0.0]) == 0.0
    rec = _record(rule="relevance", threshold=0.5)
    d = decide(rec, StepScores(episode_id="ep1", step=0, answer_probs=[0.1, 0.6, 0.2, 0.1], relevance=0.5))
    assert d and not d.stop and d.scores["relevance"] == 0.5
    d = decide(rec, StepScores(episode_id="ep1", step=1, answer_probs=[0.1, 0.2, 0.6, 0.1], relevance=0.51))
    assert d and d.stop and d.answer == "C"
    rec = _record(rule="max_steps", max_steps=2)
    d = decide(rec, StepScores(episode_id="ep1", step=0, answer_probs=[0.97, 0.01, 0.01, 0.01], relevance=0.99))
    assert d and not d.stop
    d = decide(rec, StepScores(episode_id="ep1", step=1, answer_probs=[0.1, 0.7, 0.1, 0.1], relevance=0.2))
    assert d and d.stop and d.answer == "A"  # argmax at the most relevant step (0)
    with pytest.raises(ValueError, match="relevance threshold"):
        baselines.threshold_for("relevance", 1.5)
    assert baselines.threshold_for("entropy", None) == 0.1
