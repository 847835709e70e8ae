"""HELIOS benchmark scoring (eqa/app/task_bench.py): pick-limit derivation, standard errors, paired sign test."""

from __future__ import annotations

import math

import pytest

from eqa.app.task_bench import TaskResult, limited, mean_se, sign_test, summarise


def _r(tid: str, variant: str, **m: float) -> TaskResult:
    return TaskResult(tid, "pick_place", variant, 30, dict(m), "stopped", "", 1.0)


def test_pick_limits_zero_runs_that_used_more_attempts() -> None:
    run = {"FindObj": 1.0, "Pick": 1.0, "FindRec": 1.0, "Place": 1.0, "SR": 1.0, "pick_attempts": 3.0}
    assert limited(run, None)["SR"] == 1.0 and limited(run, 5)["SR"] == 1.0
    assert limited(run, 1) == dict.fromkeys(("FindObj", "Pick", "FindRec", "Place", "SR"), 0.0)
    assert limited({**run, "pick_attempts": 1.0}, 1)["Pick"] == 1.0


def test_mean_se_and_sign_test() -> None:
    mu, se = mean_se([1.0, 0.0, 0.0, 1.0])
    assert mu == 0.5 and se == pytest.approx(math.sqrt(0.25 / 4))
    mu, se = mean_se([0.2, 0.4], binary=False)
    assert mu == pytest.approx(0.3) and se == pytest.approx(math.sqrt(0.02 / 2))
    assert sign_test(5, 0) == pytest.approx(2 / 32) and sign_test(0, 0) == 1.0 and sign_test(3, 3) == 1.0


def test_summarise_pairs_variants_on_common_tasks() -> None:
    res = [_r("a", "helios", SR=1.0, Pick=1.0, pick_attempts=2.0), _r("a", "trusting", SR=0.0, pick_attempts=1.0),
           _r("b", "helios", SR=0.0, pick_attempts=0.0), _r("b", "trusting", SR=0.0, pick_attempts=1.0),
           _r("c", "helios", SR=1.0, pick_attempts=1.0)]  # c lacks a trusting run: not in the table
    t = summarise("pick_place", res, ("trusting", "helios"))
    assert t["n"] == 2
    rows = {(r["variant"], r["picks"]): r for r in t["rows"]}
    assert rows[("helios", "unlimited")]["SR"][0] == 0.5 and rows[("helios", 1)]["SR"][0] == 0.0
    unl = next(c for c in t["paired_SR"] if c["picks"] == "unlimited")
    assert (unl["helios_wins"], unl["helios_losses"]) == (1, 0)
