"""Guarantees that survive deployment: per-category (Mondrian) calibration with per-category
coverage, and the staleness check of a table against new labelled episodes (``eqa calibrate --check``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from eqa.messages import EpisodeStart, Question, StepScores, StopConfig
from eqa_app.calibrate import main as calibrate_main
from services.stopper import synthetic
from services.stopper.calibration import calibrate
from services.stopper.conformal import relevance_weighted_confidence, sequence_set
from services.stopper.exchangeability import check_exchangeable
from services.stopper.state import KEEP_ALL_Q_HAT, EpisodeRecord, decide, resolve_calibration

# Two kinds of question for one model: on "easy" ones it is mostly right; on "hard" ones (counting from a
# partial view: Explore-EQA appendix C) it deems its views highly relevant yet is often wrong.
EASY = synthetic.SyntheticConfig(relevant_rel=(4.0, 3.0), accuracy=0.9, p_relevant=0.3)
HARD = synthetic.SyntheticConfig(relevant_rel=(8.0, 2.0), accuracy=0.5, p_relevant=0.3)


def _traces(n: int, seed: int, cfg: synthetic.SyntheticConfig, category: str) -> list:
    return [synthetic.to_trace(e, f"{category}-{seed}-{i}").model_copy(update={"category": category})
            for i, e in enumerate(synthetic.episodes(n, seed, cfg))]


def _covered(trace, q_hat: float) -> bool:
    f, rel = trace.arrays()
    return bool(sequence_set(relevance_weighted_confidence(f, rel), q_hat)["ABCD".index(trace.answer)])


def _q_hat(table, eps: float, category: str | None) -> float:
    choice, why = resolve_calibration(table, "test", eps, "t", category)
    assert choice is not None, why
    return choice.q_hat


def test_mondrian_calibration_holds_coverage_within_each_category_where_marginal_does_not() -> None:
    eps = 0.2
    cal = _traces(400, 1, EASY, "easy") + _traces(100, 2, HARD, "hard")
    test = {"easy": _traces(800, 3, EASY, "easy"), "hard": _traces(800, 4, HARD, "hard")}
    table = calibrate(cal, [eps], name="t", by_category=True)
    assert set(table.groups) == {"easy", "hard"} and table.groups["hard"].n == 100
    marginal = table.model_copy(update={"groups": {}})
    cov = {c: (np.mean([_covered(t, _q_hat(marginal, eps, c)) for t in ts]),
               np.mean([_covered(t, _q_hat(table, eps, c)) for t in ts])) for c, ts in test.items()}
    # marginal CP: the guarantee holds on the calibration mix, but the hard category falls short
    assert cov["hard"][0] < 1 - eps - 0.05, cov
    # Mondrian: at least 1 - eps within each category (up to sampling noise of 800 test episodes)
    assert cov["hard"][1] >= 1 - eps - 0.03 and cov["easy"][1] >= 1 - eps - 0.03, cov


def test_the_stopper_uses_the_questions_category_and_says_so() -> None:
    cal = _traces(200, 1, EASY, "easy") + _traces(10, 2, HARD, "hard")
    table = calibrate(cal, [0.05, 0.2], name="t", by_category=True)
    easy, _ = resolve_calibration(table, "test", 0.2, "t", "easy")
    assert easy is not None and easy.q_hat == table.groups["easy"].lookup(0.2)[0].q_hat and easy.category == "easy"
    small, _ = resolve_calibration(table, "test", 0.05, "t", "hard")  # 10 episodes cannot certify eps 0.05
    assert small is not None and small.q_hat == KEEP_ALL_Q_HAT and "too few" in small.note
    other, _ = resolve_calibration(table, "test", 0.2, "t", "location")
    assert other is not None and other.q_hat == table.lookup(0.2)[0].q_hat and "marginal" in other.note
    q = Question(text="?", choices=["a", "b", "c", "d"], scene="s", category="easy")
    rec = EpisodeRecord.from_start(EpisodeStart(episode_id="e", robot="r", question=q, max_steps=5,
                                                stop=StopConfig(rule="cp", eps=0.2)), "r")
    rec.calibration = easy
    d = decide(rec, StepScores(episode_id="e", step=0, answer_probs=[0.97, 0.01, 0.01, 0.01], relevance=0.9))
    assert d is not None and "of easy" in d.reason


def test_staleness_check_flags_another_model_and_passes_the_same_one() -> None:
    table = calibrate(_traces(300, 1, EASY, "x"), [0.1, 0.2, 0.3], name="t")
    same = check_exchangeable(table, [t.kappa() for t in _traces(80, 7, EASY, "x")])
    assert not same.stale and same.message.startswith("ok"), same.message
    # "the scorer pointed at another model": relevance runs low and answers are often wrong
    other_model = replace(EASY, relevant_rel=(2.0, 5.0), accuracy=0.6)
    stale = check_exchangeable(table, [t.kappa() for t in _traces(80, 8, other_model, "x")])
    assert stale.stale and stale.message.startswith("STALE") and stale.rank_p < 0.05, stale.message
    few = check_exchangeable(table, [t.kappa() for t in _traces(3, 9, EASY, "x")])
    assert not few.enough and "too few" in few.message


def test_eqa_calibrate_check_end_to_end(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("EQA_DATA_DIR", str(tmp_path / "var"))
    monkeypatch.delenv("EQA_REDIS_URL", raising=False)

    def write(path: Path, traces: list) -> Path:
        path.write_text("".join(t.model_dump_json() + "\n" for t in traces))
        return path

    cal = write(tmp_path / "cal.jsonl", _traces(300, 1, EASY, "easy") + _traces(100, 2, HARD, "hard"))
    assert calibrate_main(["calibrate", "--from-traces", str(cal), "--name", "mine", "--eps", "0.1,0.2,0.3",
                           "--by-category", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "per category (Mondrian)" in out and "easy" in out and "hard" in out
    fresh = write(tmp_path / "fresh.jsonl", _traces(60, 5, EASY, "easy") + _traces(15, 6, HARD, "hard"))
    assert calibrate_main(["calibrate", "--check", "--from-traces", str(fresh), "--name", "mine"]) == 0
    assert "ok:" in capsys.readouterr().out
    other = write(tmp_path / "other.jsonl", _traces(75, 7, replace(HARD, accuracy=0.3), "easy"))
    assert calibrate_main(["calibrate", "--check", "--from-traces", str(other), "--name", "mine"]) == 3
    assert "STALE" in capsys.readouterr().out
