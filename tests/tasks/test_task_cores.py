"""The in-process task runner (:mod:`eqa_app.task_cores`) against the fleet: with the same episode id and seed a
tuning-seed task gives the same per-step trace, metrics and end through both."""

from __future__ import annotations

from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(900)


def _same_steps(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b), (len(a), len(b))
    for x, y in zip(a, b, strict=True):
        for k in ("step", "phase", "skill", "target", "reason", "collided", "skill_result", "collisions",
                  "pick_attempts", "FindObj", "Pick", "FindRec", "Place", "found"):
            assert x[k] == y[k], (x["step"], k, x[k], y[k])
        assert x["pose"] == pytest.approx(y["pose"], abs=1e-3), x["step"]
        assert x["path_m"] == pytest.approx(y["path_m"], abs=1e-3), x["step"]
        assert x["numbers"].keys() == y["numbers"].keys(), x["step"]
        for k in x["numbers"]:
            assert x["numbers"][k] == pytest.approx(y["numbers"][k], rel=1e-4, abs=1e-5), (x["step"], k)


def test_in_process_tasks_trace_as_the_fleet(tmp_path: Path, redis_url: str) -> None:
    from support.fleet import fleet_settings

    from eqa_app.task_bench import run_tasks
    from eqa_app.task_cores import run_tasks_cores
    from services.sim.tasks import task_benchmark

    s = fleet_settings(tmp_path / "fleet", redis_url)
    bench = task_benchmark(11, pick_place=2, find=1, scenes_dir=s.scenes_path)
    pp0, pp1 = bench.of_kind("pick_place")[:2]
    fo0 = bench.of_kind("find_object")[0]
    jobs = [(pp0, "helios", 14, None), (pp1, "trusting", 14, 1), (fo0, "helios", 10, None)]
    ids = ["task-cores-a", "task-cores-b", "task-cores-c"]
    fleet = {r.task_id: r for r in run_tasks(s, jobs, robots=2, progress=False, episode_ids=ids)}
    cores = {r.task_id: r for r in run_tasks_cores(s, jobs, progress=False, episode_ids=ids)}
    assert fleet.keys() == cores.keys() == {pp0.id, pp1.id, fo0.id}
    moved = 0
    for tid, f in fleet.items():
        c = cores[tid]
        assert f.state == c.state == "stopped", (f.reason, c.reason)
        assert f.reason == c.reason
        assert f.metrics == c.metrics
        assert f.trace is not None and c.trace is not None
        assert f.trace["end_reason"] == c.trace["end_reason"]
        _same_steps(f.trace["steps"], c.trace["steps"])
        moved += sum(1 for e in c.trace["steps"] if e["path_m"] > 0)
    assert moved > 0  # the robots went somewhere: the traces compare decisions, not a standstill
