"""The miscalibration sweep's fast replay is the stopper's decide(), and its statistics."""

from __future__ import annotations

import numpy as np
import pytest

from eqa.messages import StopConfig
from eqa_app import evaluation as ev
from eqa_app.stop_sensitivity import Episode, Outcome, choose_operating_point, paired_steps, params_at, replay_fast
from services.stopper import synthetic
from services.stopper.calibration import calibrate
from services.stopper.state import CalibrationChoice


def _traces(n: int, seed: int) -> list:
    out = []
    rng = np.random.default_rng(seed)
    for i, ep in enumerate(synthetic.episodes(n, seed)):
        tr = synthetic.to_trace(ep, f"q{seed}-{i}")
        if rng.random() < 0.3:  # a run that ended before its step limit (nothing left to explore)
            tr = tr.model_copy(update={"max_steps": tr.max_steps + 5})
        out.append(tr)
    return out


def test_fast_replay_agrees_with_the_stoppers_decisions() -> None:
    cal, test = _traces(60, 1), _traces(40, 2)
    table = calibrate(cal, [0.1, 0.2, 0.4, 0.6], name="t")
    tie = table.kappas[3]  # a q_hat exactly at a calibration score
    checks = [("cp", e.q_hat) for e in table.entries] + [("cp", tie)]
    checks += [("relevance", r) for r in (0.1, 0.3, 0.6)] + [("entropy", h) for h in (0.05, 0.3, 0.9)]
    checks += [("max_steps", 0.0)]
    for rule, p in checks:
        for tr in test:
            cal_choice = CalibrationChoice(q_hat=p, eps=0.2, asked_eps=0.2, n=60, source="t") if rule == "cp" else None
            stop = StopConfig(rule=rule, eps=0.2) if rule in ("cp", "max_steps") else StopConfig(rule=rule, threshold=p)
            slow = ev.replay(tr, stop, cal_choice)
            fast = replay_fast(Episode.of(tr), rule, p)
            assert (fast.correct, fast.norm_steps) == (slow.correct, pytest.approx(slow.normalized_steps)), (rule, p)


def test_operating_point_is_the_cheapest_that_reaches_the_target() -> None:
    runs = {0.1: [Outcome(True, 0.9)] * 4, 0.2: [Outcome(True, 0.5)] * 3 + [Outcome(False, 0.5)],
            0.3: [Outcome(False, 0.2)] * 4}
    assert choose_operating_point(runs, 0.75) == 0.2
    assert choose_operating_point(runs, 0.8) == 0.1
    assert choose_operating_point(runs, 1.1) == 0.1  # nothing reaches it: the most successful


def test_paired_steps_sees_a_real_difference_and_not_a_fake_one() -> None:
    a = [Outcome(True, 0.5)] * 30
    b = [Outcome(True, 0.7)] * 30
    r = paired_steps(a, b)
    assert r["mean_diff"] == pytest.approx(-0.2) and r["ci_high"] < 0 and r["steps_sign_p"] < 1e-6
    same = paired_steps(a, a)
    assert same["mean_diff"] == 0 and same["steps_sign_p"] == 1.0 and same["success_sign_p"] == 1.0


def test_modes() -> None:
    assert params_at("all", 0.5).miscal_view == 0.5 and params_at("view", 0.5).miscal_category == 0.0
    with pytest.raises(ValueError):
        params_at("bogus", 0.5)


def test_recorded_perceptions_rescore_exactly_at_every_level() -> None:
    """Record one short episode with the pure cores; the level-0 re-score is what the scorer computed live,
    and the fast re-score equals the full one in every mode (the sweep's numbers are the oracle's)."""
    from eqa.settings import Settings
    from eqa_app import stop_sensitivity as ss
    from services.sim.questions import benchmark_candidates

    cands = benchmark_candidates(11, 3, Settings().scenes_path)  # one house of the tuning seed
    q = next(qs[0] for qs in cands.values() if qs)
    ep = ss.run_episode((q.model_copy(update={"max_steps": 8}), "semantic", 160, 120))
    assert len(ep.steps) == 8
    ss.rescore(ep, params_at("all", 0.0), check_level0=True)
    for mode in ("category", "view", "related", "irrelevant", "all"):
        for level in (0.3, 1.0):
            f, rel = ss.rescore(ep, params_at(mode, level)).arrays()
            f2, rel2 = ss.rescore_arrays(ep, params_at(mode, level))
            assert np.array_equal(f, f2) and np.array_equal(rel, rel2), (mode, level)


def test_eqa_bench_stop_takes_the_sensitivity_options() -> None:
    import argparse

    from eqa_app import bench_cli

    p = argparse.ArgumentParser()
    bench_cli.register(p.add_subparsers(dest="command"))
    a = p.parse_args(["bench", "stop", "--miscalibration", "category", "all", "--levels", "0", "0.5", "--limit", "6"])
    assert a.miscalibration == ["category", "all"] and a.levels == [0.0, 0.5] and not a.cp_guided
    assert p.parse_args(["bench", "stop", "--cp-guided"]).cp_guided
    with pytest.raises(SystemExit):
        p.parse_args(["bench", "stop", "--miscalibration", "bogus"])
