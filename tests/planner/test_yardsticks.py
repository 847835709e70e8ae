"""Exploration yardsticks: target_oracle walks to the target through the true house, the evidence ceiling, and
the exploration figure over any set of strategies."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from eqa.messages import EpisodeStart, Frontier, GridSpec, Pose2D, Question, TargetPaths, decode, encode
from services.mapper.frontiers import path_distances, target_weights
from services.planner.sampling import step_rng
from services.planner.step import Memory, PlannerParams, plan_step
from services.sim.meshbuild import MeshBuilder
from services.sim.paths import geodesic_field, target_paths
from services.sim.scene import InstanceInfo, Room, Scene

BOX = (5.6, 1.0)  # the target, in room B just behind the dividing wall


def _two_rooms() -> Scene:
    """A 10 x 6 m house: room A (x 0..5) and room B (x 5..10) divided by a wall at x = 5 with a 1 m door at
    y 4.5..5.5; a 0.6 m box (the evidence) in room B at (5.6, 1.0), 0.55 m behind the wall."""
    mb = MeshBuilder()
    inst = {
        0: InstanceInfo(0, "floor", "a", "living_room", is_structure=True, position=(5, 3, 0), size=(10, 6, 0)),
        1: InstanceInfo(1, "wall", "a", "living_room", is_structure=True, position=(5, 3, 1.35), size=(10, 6, 2.7)),
        2: InstanceInfo(2, "box", "b", "bedroom", position=(BOX[0], BOX[1], 0.3), size=(0.6, 0.6, 0.6)),
    }
    mb.quad_z(0, 0, 10, 6, 0.0, 0, (200, 200, 200))
    walls = [((0, 0, 0), (10, 0.1, 2.7)), ((0, 5.9, 0), (10, 6, 2.7)), ((0, 0, 0), (0.1, 6, 2.7)),
             ((9.9, 0, 0), (10, 6, 2.7)), ((4.95, 0, 0), (5.05, 4.5, 2.7)), ((4.95, 5.5, 0), (5.05, 6, 2.7))]
    for lo, hi in walls:
        mb.box(lo, hi, 1, (220, 220, 220))
    mb.box((BOX[0] - 0.3, BOX[1] - 0.3, 0), (BOX[0] + 0.3, BOX[1] + 0.3, 0.6), 2, (200, 40, 40))
    v, t, ti, tc = mb.arrays()
    return Scene(id="two-rooms", seed=None, vertices=v, triangles=t, triangle_instance=ti, triangle_colors=tc,
                 instances=inst, rooms=[Room("a", "living_room", (0, 0, 5, 6)), Room("b", "bedroom", (5, 0, 10, 6))])


@pytest.fixture(scope="module")
def house() -> Scene:
    return _two_rooms()


def _robot_map() -> tuple[GridSpec, np.ndarray, np.ndarray]:
    """The robot's own map after exploring room A: all of it free, the dividing wall occupied, room B unknown."""
    res = 0.1
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=res, rows=60, cols=100)
    free = np.zeros((60, 100), dtype=bool)
    occ = np.zeros((60, 100), dtype=bool)
    free[2:-2, 2:48] = True
    occ[:, 49:51] = True
    occ[45:55, 49:51] = False  # the doorway
    free[45:55, 48:51] = True
    return grid, free, occ


def test_target_oracle_walks_around_the_wall_the_straight_line_misses(house: Scene) -> None:
    paths = target_paths(house, [BOX])
    by_wall = Frontier(x=4.6, y=1.0, nx=1.0, ny=0.0, size=10)  # nearest the box in a straight line (1.0 m)
    by_door = Frontier(x=4.9, y=5.0, nx=1.0, ny=0.0, size=10)  # the doorway, 4.1 m from the box
    walked = path_distances(paths, np.array([by_wall.x, by_door.x]), np.array([by_wall.y, by_door.y]))
    assert walked[0] > 6.0 and walked[1] < 5.5  # through the door from both; the wall frontier is the long way
    grid, free, occ = _robot_map()
    pose = Pose2D(x=2.5, y=3.0, yaw=0.0)
    params = PlannerParams()

    def chosen(frontiers: list[Frontier]) -> int:
        plan = plan_step(grid, free, occ, pose, frontiers, "target_oracle", Memory(), step_rng(0, 0), params)
        assert plan.kind == "move" and plan.frontier_index is not None
        return plan.frontier_index

    straight = chosen(target_weights([by_wall, by_door], [BOX]))
    through = chosen(target_weights([by_wall, by_door], [BOX], paths))
    assert straight == 0 and through == 1
    # the whole walk robot -> chosen frontier -> target through the true house: the house-graph choice is shorter
    reach = np.isfinite(paths.distance_m)
    i0, j0 = int(pose.y / 0.1), int(pose.x / 0.1)
    from_robot = geodesic_field(reach, 0.1, [(i0, j0, 0.0)])
    fr = [by_wall, by_door]
    total = [from_robot[int(f.y / 0.1), int(f.x / 0.1)] + walked[k] for k, f in enumerate(fr)]
    assert total[through] < total[straight] - 3.0


def test_target_paths_travel_only_with_the_yardstick(house: Scene) -> None:
    paths = target_paths(house, [BOX])
    q = Question(text="Is there a box in the bedroom?", choices=["Yes", "No"], scene="gen-00001", answer="A",
                 targets=[BOX])
    start = EpisodeStart(episode_id="ep-y", robot="r0", question=q, max_steps=20, strategy="target_oracle",
                         target_paths=paths)
    back = decode(encode(start), EpisodeStart)
    assert back.target_paths is not None and np.array_equal(back.target_paths.distance_m, paths.distance_m)
    assert EpisodeStart.model_validate(start.model_dump(mode="json")).target_paths is not None  # mapper snapshots
    with pytest.raises(ValidationError, match="target_oracle yardstick only"):
        EpisodeStart(episode_id="ep-y", robot="r0", question=q, max_steps=20, strategy="semantic", target_paths=paths)
    g = paths.grid
    with pytest.raises(ValidationError, match="float32"):
        TargetPaths(grid=g, distance_m=np.zeros((g.rows, g.cols + 1), np.float32))
    with pytest.raises(ValidationError, match="non-negative"):
        TargetPaths(grid=g, distance_m=np.full((g.rows, g.cols), np.nan, np.float32))


def test_the_runners_give_the_paths_to_target_oracle_only(house: Scene) -> None:
    from eqa_app.benchmark_runner import yardstick_paths

    q = Question(text="Is there a box?", choices=["Yes", "No"], scene="gen-00001", targets=[BOX])
    assert yardstick_paths(q, "semantic", Path("/nonexistent"), house) is None
    got = yardstick_paths(q, "target_oracle", Path("/nonexistent"), house)
    assert got is not None and math.isfinite(float(got.distance_m.min()))


def _question(evidence: list[int], targets: list[tuple[float, float]], T: int) -> Question:
    return Question(id="q-ceil", text="Is there a box in the bedroom?", choices=["Yes", "No"], scene="gen-00001",
                    answer="A", evidence_ids=evidence, targets=targets, start_pose=Pose2D(x=1.0, y=3.0, yaw=0.0),
                    max_steps=T, category="existence")


def test_evidence_ceiling_on_a_hand_built_house(house: Scene) -> None:
    from eqa_app.ceiling import ceiling_cdf, question_ceiling
    from services.sim.render import Renderer
    from services.vlm_scorer.backends.oracle import OracleBackend

    renderer, oracle = Renderer(house), OracleBackend()
    # the box is seen from the doorway at the earliest: ~4.5 m of walking from (1, 3), i.e. 2 moves of 3 m
    c = question_ceiling(_question([2], [BOX], 20), house, renderer, oracle, 320, 240, 3.0)
    assert c.step == 2 and c.reason == "perceivable" and math.isclose(c.first_at or 0, 3 / 20)
    # with 1 m moves it takes longer; with 2 frames (steps 0 and 1) of 3 m moves it is out of reach
    slow = question_ceiling(_question([2], [BOX], 20), house, renderer, oracle, 320, 240, 1.0)
    assert slow.step is not None and slow.step >= 4
    short = question_ceiling(_question([2], [BOX], 2), house, renderer, oracle, 320, 240, 3.0)
    assert short.step is None and short.first_at is None
    # the evidence is a room (no object): standing inside room B, 4 m of walking away -> 2 moves
    room = question_ceiling(_question([], [(7.5, 3.0)], 20), house, renderer, oracle, 320, 240, 3.0)
    assert room.step == 2 and room.views == 0
    assert ceiling_cdf([c, short], [0.1, 0.15, 1.0]) == [0.0, 0.5, 0.5]


def _trace(qid: str, category: str, first: int | None, right_from: int | None, T: int = 10):
    from services.stopper.calibration import Trace, TraceStep

    steps = [TraceStep(answer_probs=[0.8, 0.2] if right_from is not None and k >= right_from else [0.2, 0.8],
                       relevance=0.6 if first is not None and k == first else 0.1) for k in range(T)]
    return Trace(question_id=qid, scene="gen-00001", category=category, choices=["Yes", "No"], answer="A",
                 max_steps=T, strategy="x", steps=steps)


def test_the_figure_draws_every_strategy_of_the_results(tmp_path: Path) -> None:
    from eqa_app import evaluation as ev
    from eqa_app.bench_cli import CDF_BUDGETS, PAIRED_BUDGETS
    from eqa_app.plots import evidence_and_success_figure, plot_explore

    cats = ["existence", "counting"]
    qids = [f"q{i}" for i in range(12)]
    sizes = {q: ev.SIZE_CLASSES[i % 3] for i, q in enumerate(qids)}
    # a strategy the plots have never heard of, better than both baselines
    runs = {"fbe": [_trace(q, cats[i % 2], 8, 8 if i % 2 else None) for i, q in enumerate(qids)],
            "semantic": [_trace(q, cats[i % 2], 6, 6 if i % 3 else None) for i, q in enumerate(qids)],
            "someone_new": [_trace(q, cats[i % 2], 1, 1) for i, q in enumerate(qids)]}

    def part(ts: list) -> dict:
        return {"n": len(ts), "success": ev.success_at_budgets(ts), "evidence_cdf": ev.evidence_cdf(ts, CDF_BUDGETS)}

    results = {"scorer": "scorer: oracle (simulated perception model, not a VLM)", "size": "320x240", "seeds": [1],
               "runner": "cores", "budgets": list(ev.BUDGETS), "cdf_budgets": list(CDF_BUDGETS),
               "size_cuts_m2": [80.0, 140.0],
               "strategies": {k: {**part(ts), "success_ci95": [[0, 1]] * len(ev.BUDGETS), "bound": False,
                                  "by_category": {c: part(g) for c, g in ev.by_group(ts, "category").items()},
                                  "by_size": {c: part(g) for c, g in ev.by_group(ts, groups=sizes).items()},
                                  "by_area": {}} for k, ts in runs.items()},
               "paired_vs_semantic": {k: [vars(p) for p in ev.paired_comparison(runs["semantic"], runs[k],
                                                                                PAIRED_BUDGETS)]
                                      for k in ("fbe", "someone_new")},
               "paired_vs_fbe": {k: [vars(p) for p in ev.paired_comparison(runs[k], runs["fbe"], PAIRED_BUDGETS)]
                                 for k in ("semantic", "someone_new")},
               "ceiling": {"n": 12, "cdf": [1.0] * len(CDF_BUDGETS),
                           "by_category": {c: {"n": 6, "cdf": [1.0] * len(CDF_BUDGETS)} for c in cats},
                           "by_size": {c: {"n": 4, "cdf": [1.0] * len(CDF_BUDGETS)} for c in ev.SIZE_CLASSES}}}
    fig = evidence_and_success_figure(results)
    axes = fig.axes
    assert len(axes) == 2 * (1 + len(cats) + 3)  # all, per category, per size class; CDF and success each
    titles = [a.get_title() for a in axes]
    assert any("size: large (> 140 m²)" in t for t in titles) and any("category: counting" in t for t in titles)
    cdf_labels = [ln.get_label() for ln in axes[0].get_lines()]
    assert sum(lbl.startswith(("fbe", "semantic", "someone_new")) for lbl in cdf_labels) == 3
    assert any(lbl.startswith("ceiling") for lbl in cdf_labels)
    succ = {ln.get_label().split(" ")[0]: ln for ln in axes[1].get_lines()}
    assert set(succ) == set(runs)
    new_label = succ["someone_new"].get_label()
    # its paired differences at T against both baselines: 12 right against semantic's 8 and fbe's 6
    assert "sem +0.333" in new_label and "fbe +0.500" in new_label
    assert list(succ["someone_new"].get_ydata()) == results["strategies"]["someone_new"]["success"]
    colors = {ln.get_color() for ln in succ.values()}
    assert len(colors) == 3  # a colour of its own
    paths = plot_explore(results, tmp_path)
    assert (tmp_path / "explore_evidence_and_success.png") in paths
    assert all(p.is_file() and p.stat().st_size > 1000 for p in paths)


def test_sets_read_from_other_result_directories_are_used_not_copied(settings, tmp_path: Path) -> None:
    """``eqa bench explore --traces DIR``: stored runs kept elsewhere join the figures without being run again, and
    are not exported into ``--out`` (one copy of each set); a set of ``--out`` itself is exported as before."""
    import argparse

    from eqa_app.bench_cli import _collect
    from services.stopper.calibration import read_jsonl, write_jsonl

    kept = tmp_path / "kept"
    qs = [Question(id=f"q{i}", text="Is there a box?", choices=["Yes", "No"], scene="gen-00001", max_steps=10)
          for i in range(3)]
    write_jsonl(kept / "set-a.jsonl.gz", [_trace(q.id, "existence", 1, 1) for q in qs])
    args = argparse.Namespace(out=str(tmp_path / "out"), traces=[str(kept)], no_progress=True, runner="cores",
                              workers=1)
    got = _collect(qs, settings, "fbe", "set-a", args)
    assert [t.question_id for t in got] == ["q0", "q1", "q2"]
    assert not (tmp_path / "out" / "traces" / "set-a.jsonl.gz").exists()
    write_jsonl(tmp_path / "out" / "traces" / "set-b.jsonl.gz", [_trace(q.id, "existence", 1, 1) for q in qs[:2]])
    write_jsonl(kept / "set-b.jsonl.gz", [_trace(qs[2].id, "existence", 2, 2)])
    got = _collect(qs, settings, "fbe", "set-b", args)
    assert len(got) == 3 and got[2].steps[2].relevance == 0.6  # the third from the other directory
    assert len(list(read_jsonl(tmp_path / "out" / "traces" / "set-b.jsonl.gz"))) == 3  # --out's own set, exported


def test_explore_printout_pairs_with_every_named_base(capsys: pytest.CaptureFixture[str]) -> None:
    """``--versus``: the paired rows against each extra base strategy are printed after semantic's and fbe's."""
    from eqa_app.bench_cli import _print_explore

    row = {"budget": 0.5, "a_only": 7, "b_only": 2, "p_value": 0.18, "ci_low": -0.01, "ci_high": 0.1}
    strategy = {"n": 9, "success": [0.5], "evidence_share": 0.4, "first_evidence_at": 0.3}
    results = {"scorer": "oracle", "size": "320x240", "budgets": [0.5], "seeds": [1],
               "strategies": {"gain": strategy, "perfect_gain": strategy},
               "paired_bases": ["gain"], "paired_vs_gain": {"perfect_gain": [row]}}
    _print_explore(results)
    out = capsys.readouterr().out
    assert "each run against gain" in out and "  7 / 2" in out
