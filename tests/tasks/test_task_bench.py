"""HELIOS benchmark scoring (eqa_app/task_bench.py): pick limits enforced or derived, standard errors, paired sign
test; task traces through the services and the tables replayed from them."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from eqa_app.task_bench import TaskResult, limited, mean_se, sign_test, summarise


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
    # every phase is paired too: Pick helios 1 / 0 on a, 0 / 0 on b -> one win; FindObj ties everywhere
    by = {(c["metric"], c["picks"]): c for c in t["paired"]}
    assert (by[("Pick", "unlimited")]["helios_wins"], by[("Pick", "unlimited")]["helios_losses"]) == (1, 0)
    assert (by[("FindObj", "unlimited")]["helios_wins"], by[("FindObj", "unlimited")]["helios_losses"]) == (0, 0)
    assert {m for m, _ in by} == {"FindObj", "Pick", "FindRec", "Place", "SR"}


def test_a_limit_run_enforced_is_read_from_its_runs_else_derived_post_hoc() -> None:
    def r(tid: str, v: str, limit: int | None, **m: float) -> TaskResult:
        return TaskResult(tid, "pick_place", v, 30, dict(m), "stopped", "", 1.0, limit)

    res = [r("a", "helios", None, FindObj=1.0, pick_attempts=3.0), r("a", "trusting", None, FindObj=1.0),
           # limit 1 enforced: the run ended at its failed pick, FindObj kept (post hoc zeroing would give 0)
           r("a", "helios", 1, FindObj=1.0, pick_attempts=1.0), r("a", "trusting", 1, FindObj=0.0)]
    t = summarise("pick_place", res, ("trusting", "helios"))
    rows = {(x["variant"], x["picks"]): x for x in t["rows"]}
    assert rows[("helios", 1)]["FindObj"][0] == 1.0 and rows[("helios", 1)]["post_hoc"] is False
    assert rows[("helios", 5)]["FindObj"][0] == 1.0 and rows[("helios", 5)]["post_hoc"] is True
    assert rows[("helios", "unlimited")]["post_hoc"] is False and t["n"] == 1
    # without the enforced runs the same row is the paper's post hoc zeroing of the unlimited run
    t = summarise("pick_place", res[:2], ("trusting", "helios"))
    assert {(x["variant"], x["picks"]): x for x in t["rows"]}[("helios", 1)]["FindObj"][0] == 0.0


def test_a_few_stray_unlimited_runs_do_not_shrink_the_table_of_an_enforced_limit() -> None:
    def r(tid: str, v: str, limit: int | None, **m: float) -> TaskResult:
        return TaskResult(tid, "pick_place", v, 30, dict(m), "stopped", "", 1.0, limit)

    res = [r(t, v, 1, SR=float(t == "a" and v == "helios")) for t in "abcd" for v in ("trusting", "helios")]
    res += [r("a", "trusting", None, SR=0.0), r("a", "helios", None, SR=1.0)]  # one task also run unlimited
    t = summarise("pick_place", res, ("trusting", "helios"))
    rows = {(x["variant"], x["picks"]): x for x in t["rows"]}
    assert t["n"] == 4 and rows[("helios", 1)]["SR"][0] == 0.25 and rows[("helios", 1)]["post_hoc"] is False
    assert ("helios", "unlimited") not in rows  # 1 of 4 tasks run unlimited: no row rather than a row of n 1


def test_enforced_limits_traces_and_replay_through_the_services(tmp_path: Path, redis_url: str,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """The first tuning-seed task on a real fleet, with pick limit 1 enforced and unlimited: each run carries
    its per-step trace from the store (phase, decision numbers, pose, flags), the metrics replayed from the
    trace are the simulator's, and ``eqa bench ovmm --replay`` rebuilds the same table from the exported
    traces without a fleet."""
    import json

    from support.fleet import fleet_settings

    from eqa.task_traces import replay_metrics
    from eqa_app.cli import main
    from eqa_app.task_bench import format_table, run_tasks, traces_path
    from services.sim.tasks import task_benchmark

    s = fleet_settings(tmp_path / "fleet", redis_url)
    task = task_benchmark(11, pick_place=1, find=0, scenes_dir=s.scenes_path).tasks[0]
    runs = run_tasks(s, [(task, "trusting", 8, 1), (task, "trusting", 8, None)], robots=2, progress=False)
    assert sorted(r.pick_limit or 0 for r in runs) == [0, 1]
    for r in runs:
        assert r.state == "stopped" and r.trace is not None, r
        steps = r.trace["steps"]
        assert [e["step"] for e in steps] == list(range(len(steps))) and 2 <= len(steps) <= 8
        assert r.trace["task"]["object_ids"] == task.object_ids and r.trace["pick_limit"] == r.pick_limit
        assert all(e["phase"] in (None, "searching", "local_search", "looking", "picking", "placing") for e in steps)
        assert any("F0" in e["numbers"] for e in steps[1:])  # the decision's numbers came with the goals
        assert replay_metrics(r.kind, r.trace, r.pick_limit) == r.metrics
        assert r.metrics["pick_attempts"] <= (r.pick_limit or 8)
    out = tmp_path / "out"
    out.mkdir()
    with traces_path(out, "ovmm", 11).open("w") as f:
        for r in runs:
            f.write(json.dumps(r.__dict__) + "\n")
    live = format_table("pick_place", summarise("pick_place", runs, ("trusting",)), 11, 8)
    capsys.readouterr()
    assert main(["bench", "ovmm", "--replay", str(out), "--seeds", "11", "--variants", "trusting",
                 "--pick-limits", "1", "unlimited", "--max-steps", "8", "--out", str(tmp_path / "replayed")]) == 0
    printed = capsys.readouterr().out
    assert live in printed, (live, printed)
    assert "first failure" in printed and (tmp_path / "replayed" / "ovmm-failures.png").stat().st_size > 1000
