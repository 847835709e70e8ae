"""The array-form replay of the stop rules (services/stopper/replay.py) decides exactly as the stopper's
decide() stepping through the same scores: stop step, answer, prediction set and sequence-level set, for every
rule, under every answer rule, on random episodes with ties, short runs and runs past the budget."""

from __future__ import annotations

import numpy as np
import pytest

from eqa.messages import EpisodeStart, Question, StepScores, StopConfig, letters
from services.stopper.answer_memory import AnswerRule, transform
from services.stopper.conformal import nonconformity
from services.stopper.replay import replay_arrays
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide

RULES = (AnswerRule(), AnswerRule(2, "loglinear"), AnswerRule(3, "linear"))


def _episode(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(f, rel, max_steps, truth): coarse probabilities and relevances half the time, so ties happen."""
    t, k = int(rng.integers(1, 11)), int(rng.integers(2, 6))
    f = rng.dirichlet(np.full(k, 0.5), size=t)
    rel = rng.beta(1.0, 2.0, size=t)
    if rng.random() < 0.5:
        f = np.round(f * 4) + 1e-3
        f /= f.sum(axis=1, keepdims=True)
        rel = np.round(rel * 4) / 4
    max_steps = max(1, t + int(rng.integers(-2, 4)))  # past the budget, at it, or a run that ended before it
    return f, rel, max_steps, int(rng.integers(k))


def _decide_all(f: np.ndarray, rel: np.ndarray, max_steps: int, stop: StopConfig, q_hat: float | None,
                rule: AnswerRule) -> tuple[int, str | None, list[str], list[str] | None]:
    """decide() on every recorded step: (stop step, answer, prediction set there, running set at the end)."""
    q = Question(id="q", text="Which one?", choices=[f"c{i}" for i in range(f.shape[1])], scene="s", answer="A")
    rec = EpisodeRecord.from_start(EpisodeStart(episode_id="e", robot="r", question=q, max_steps=max_steps,
                                                stop=stop), "r")
    rec.answer_memory, rec.answer_fusion = rule.k, rule.fusion
    rec.threshold = stop.threshold
    if q_hat is not None:
        rec.calibration = CalibrationChoice(q_hat=q_hat, eps=0.2, asked_eps=0.2, n=50, source="t",
                                            answer_rule=rule.name)
    first = None
    for t in range(f.shape[0]):
        d = decide(rec, StepScores(episode_id="e", step=t, answer_probs=f[t].tolist(), relevance=float(rel[t])))
        assert d is not None
        if d.stop and first is None:
            first = (t, d.answer, list(d.prediction_set))
    if first is None:  # the run ended before its budget without the rule firing: the fallback answer
        first = (f.shape[0] - 1, rec.fallback(), list(rec.running or []))
    return (*first, rec.running)


@pytest.mark.parametrize("rule", RULES, ids=lambda r: r.name)
def test_replay_arrays_decides_as_decide_on_random_episodes(rule: AnswerRule) -> None:
    rng = np.random.default_rng(7 + rule.k)
    episodes = [_episode(rng) for _ in range(60)]
    kappas = sorted(nonconformity(*transform(f, rel, rule), truth) for f, rel, _, truth in episodes)
    q_hats = [kappas[len(kappas) // 4], kappas[len(kappas) // 2], kappas[-3]]  # each a tie with some episode
    checks: list[tuple[StopConfig, float | None]] = [(StopConfig(rule="cp"), q) for q in q_hats]
    checks += [(StopConfig(rule="entropy", threshold=h), h) for h in (0.1, 0.6)]
    checks += [(StopConfig(rule="entropy"), None), (StopConfig(rule="relevance"), None)]
    checks += [(StopConfig(rule="relevance", threshold=r), r) for r in (0.25, 0.5)]
    checks += [(StopConfig(rule="max_steps"), None)]
    fired = 0
    for stop, p in checks:
        for f, rel, max_steps, _ in episodes:
            labels = letters(f.shape[1])
            step, answer, pset, running = _decide_all(f, rel, max_steps, stop, p if stop.rule == "cp" else None, rule)
            got = replay_arrays(f, rel, max_steps, stop.rule, p, rule)
            case = (stop.rule, p, f.shape, max_steps)
            assert got.step == step, case
            assert labels[got.answer] == answer, case
            if stop.rule == "cp":
                assert [labels[i] for i in got.prediction_set] == pset, case
                assert got.sequence_set is not None and [labels[i] for i in got.sequence_set] == running, case
            else:
                assert got.prediction_set == () and got.sequence_set is None
            fired += step < min(f.shape[0], max_steps) - 1
    assert fired > 50  # the rules stopped early often, not only at the budget


def test_bad_input_is_refused() -> None:
    f, rel = np.full((3, 2), 0.5), np.ones(3)
    with pytest.raises(ValueError, match="q_hat"):
        replay_arrays(f, rel, 3, "cp")
    with pytest.raises(ValueError, match="unknown stop rule"):
        replay_arrays(f, rel, 3, "bogus", 0.1)
    with pytest.raises(ValueError, match="relevances"):
        replay_arrays(f, rel[:2], 3, "max_steps")
    with pytest.raises(ValueError, match="max_steps"):
        replay_arrays(f, rel, 0, "max_steps")
