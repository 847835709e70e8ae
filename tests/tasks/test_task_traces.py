"""Task traces (eqa/task_traces.py): metrics replayed from the per-step entries, the first failure of a run
(HELIOS Fig. 5 / 6), the outcome a user reads; the simulator's ground truth of a task typed in words."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from eqa.messages import Pose2D, Task
from eqa.task_traces import (
    PICK_PLACE_CAUSES,
    TraceError,
    breakdown,
    failure_cause,
    format_breakdown,
    replay_metrics,
    task_outcome,
)


def entry(step: int, phase: str | None = "searching", **kw: Any) -> dict[str, Any]:
    e: dict[str, Any] = {"step": step, "pose": [0.0, 0.0, 0.0], "phase": phase, "skill": "move", "target": None,
                         "reason": "", "numbers": {}, "collided": False, "skill_result": None, "collisions": 0,
                         "pick_attempts": 0, "path_m": 0.0, "FindObj": False, "Pick": False, "FindRec": False,
                         "Place": False, "found": False}
    e.update(kw)
    return e


def trace(*steps: dict[str, Any], shortest: float | None = None, end: str | None = None) -> dict[str, Any]:
    return {"task": {"shortest_path_m": shortest}, "pick_limit": None, "end_reason": end, "steps": list(steps)}


DONE = {"FindObj": True, "Pick": True, "FindRec": True, "Place": True}


def test_replayed_metrics_follow_the_simulators_rule() -> None:
    ok = trace(entry(0, None), entry(1, "picking", FindObj=True, Pick=True, pick_attempts=2),
               entry(2, "placing", **DONE, pick_attempts=2))
    assert replay_metrics("pick_place", ok) == {**dict.fromkeys((*DONE, "SR"), 1.0), "collisions": 0.0,
                                                "pick_attempts": 2.0}
    # a collision keeps every phase but fails SR; a pick limit exceeded zeroes everything (paper section 4.1)
    hit = trace(entry(0, None), entry(1, collided=True, collisions=1), entry(2, **DONE, collisions=1, pick_attempts=2))
    assert replay_metrics("pick_place", hit)["SR"] == 0.0 and replay_metrics("pick_place", hit)["Place"] == 1.0
    assert replay_metrics("pick_place", ok, pick_limit=1)["FindObj"] == 0.0
    assert replay_metrics("pick_place", ok, pick_limit=2)["SR"] == 1.0
    # object search: SPL = shortest / max(shortest, travelled) on success (2.0 / 4.0 by hand)
    found = trace(entry(0, None), entry(1, "looking", found=True, path_m=4.0), shortest=2.0)
    assert replay_metrics("find_object", found) == {"SR": 1.0, "SPL": 0.5, "collisions": 0.0}
    with pytest.raises(TraceError):
        replay_metrics("pick_place", {"steps": [{"no": "step"}]})


def test_first_failure_of_a_run() -> None:
    m = {"SR": 0.0}
    searched = trace(entry(0, None), entry(1), entry(2))
    assert failure_cause("pick_place", searched, m, max_steps=3).cause == "object not found: out of steps"
    gave_up = trace(entry(0, None), entry(1), end="no frontier left to explore")
    assert failure_cause("pick_place", gave_up, m, max_steps=50).cause == "object not found: search ended"
    limit = trace(entry(0, None), entry(1, "picking", skill_result={"skill": "pick", "success": False}),
                  end="pick failed (no target object in frame); pick limit 1 used up")
    assert failure_cause("pick_place", limit, m, max_steps=50).cause == "object not found: pick limit used up"
    # the collision comes first, whatever failed after it; its phase is the planner's at that step
    hit = trace(entry(0, None), entry(1, "local_search", collided=True, collisions=1), entry(2, collisions=1))
    f = failure_cause("pick_place", hit, m, max_steps=3)
    assert (f.cause, f.phase, f.step) == ("collision", "local_search", 1)
    unpicked = trace(entry(0, None), entry(1, "picking", FindObj=True, skill="pick",
                                           skill_result={"skill": "pick", "success": False}), entry(2, FindObj=True))
    assert failure_cause("pick_place", unpicked, m, max_steps=3).cause == "pick failed"
    no_rec = trace(entry(0, None), entry(1, "searching", FindObj=True, Pick=True))
    assert failure_cause("pick_place", no_rec, m, max_steps=2).cause == "receptacle not found: out of steps"
    dropped = trace(entry(0, None), entry(1, "placing", FindObj=True, Pick=True, FindRec=True,
                                          skill_result={"skill": "place", "success": False}))
    assert failure_cause("pick_place", dropped, m, max_steps=9).cause == "place failed"
    assert failure_cause("pick_place", trace(entry(0, None), entry(1, **DONE)), {"SR": 1.0}).cause == "success"
    assert failure_cause("pick_place", None, {}, "failed", "no progress for 300 s").cause == "run failed"
    away = trace(entry(0, None), entry(1, "looking", skill_result={"skill": "stop", "success": False}))
    assert failure_cause("find_object", away, m).cause == "stopped away from the object"
    assert failure_cause("find_object", None, m, reason="task ended: stopped (not near a target object)").cause \
        == "stopped away from the object"
    # no trace at hand (the gateway): the final metrics and the end say as much as they can
    f = failure_cause("pick_place", None, {"FindObj": 1.0, "Pick": 0.0, "SR": 0.0, "collisions": 0.0},
                      reason="step limit reached (9 steps)", max_steps=9, steps_run=9)
    assert f.cause == "pick failed"


def test_breakdown_table_and_outcome_text() -> None:
    rows = [("helios", failure_cause("pick_place", trace(entry(0, None), entry(1)), {}, max_steps=2)),
            ("helios", failure_cause("pick_place", trace(entry(0, None), entry(1, **DONE)), {"SR": 1.0})),
            ("trusting", failure_cause("pick_place", None, {}, "failed"))]
    table = breakdown(rows, "pick_place")
    assert list(table["helios"]) == list(PICK_PLACE_CAUSES)
    assert table["helios"]["success"] == 1 and table["helios"]["object not found: out of steps"] == 1
    assert table["trusting"]["run failed"] == 1
    text = format_breakdown(table, "pick_place", ["trusting", "helios"])
    assert "helios (n=2)" in text and "50.0 %" in text and "collision" not in text  # empty causes left out
    out = task_outcome("pick_place", {"FindObj": 0.0, "SR": 0.0}, "stopped", "step limit reached (5 steps)", 5, 5)
    assert out == {"success": False, "cause": "object not found: out of steps", "phase": None, "step": None,
                   "text": "failed: object not found (out of steps)"}
    assert task_outcome("find_object", {"SR": 1.0}, "stopped", "stopped (within reach)", 4, 90)["text"] == "success"


def test_a_task_in_words_gets_its_ground_truth_from_the_scene(tmp_path: Path) -> None:
    """``eqa task "Find a potted plant" --scene gen-115001`` through the gateway carries no object ids: the sim
    fills them from the scene graph, so the stop next to potted plant #51 succeeds (0.35 m from its box)."""
    from services.sim.library import load_or_generate
    from services.sim.task_episode import TaskEpisode
    from services.sim.tasks import with_ground_truth

    scene = load_or_generate("gen-115001", tmp_path)
    typed = Task(kind="find_object", text="Find a potted plant", scene="gen-115001", object="potted_plant")
    start = Pose2D(x=8.5, y=6.0, yaw=0.0)
    gt = with_ground_truth(typed, scene, start)
    plants = sorted(i.id for i in scene.objects() if i.category == "potted_plant")
    assert gt.object_ids == plants and 51 in plants
    assert gt.shortest_path_m is not None and gt.shortest_path_m > 0
    ep = TaskEpisode(gt)
    assert ep.stop(scene, Pose2D(x=8.88, y=10.25, yaw=0.0)) is True
    assert TaskEpisode(typed).stop(scene, Pose2D(x=8.88, y=10.25, yaw=0.0)) is False  # what the ids were for
    # pick and place: the objects of the class on a start receptacle of the class, every goal instance
    mugs = [i for i in scene.objects() if i.category == "mug" and i.support is not None]
    mug = next(i for i in mugs if scene.instances[i.support].category == "dining_table")
    start_cls = scene.instances[mug.support].category
    pp = Task(kind="pick_place", text="x", scene="gen-115001", object="mug", start_receptacle=start_cls,
              goal_receptacle="bed")
    g = with_ground_truth(pp, scene, start)
    assert g.object_ids == [mug.id] and g.start_receptacle_ids == [mug.support]  # not the mug on the island
    assert g.goal_receptacle_ids == sorted(i.id for i in scene.objects() if i.category == "bed")
    assert with_ground_truth(g, scene, start) is g  # a benchmark task (ids given) is left as it is


def test_eqa_task_report_names_the_failure(capsys: pytest.CaptureFixture[str]) -> None:
    from eqa.settings import Settings
    from eqa_app.task import report

    status = {"episode_id": "ep-1", "state": "stopped", "steps": 145, "max_steps": 145,
              "stop_reason": "step limit reached (145 steps)", "task": {"kind": "pick_place"},
              "metrics": {"FindObj": 1.0, "Pick": 0.0, "FindRec": 0.0, "Place": 0.0, "SR": 0.0, "collisions": 0.0,
                          "pick_attempts": 2.0}}
    report(status, Settings(scorer_backend="oracle"), as_json=False)
    out = capsys.readouterr().out
    assert "ep-1: task failed after 145 of 145 steps" in out and "outcome: failed: pick failed" in out, out
    assert "answering" not in out
