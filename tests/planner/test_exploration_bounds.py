"""Benchmark-only yardsticks: target_oracle and the perfect-value ones (perfect_sv, perfect_vlfm, perfect_gain)
read ground truth, the product refuses them, and the tuning tools refuse the evaluation seeds."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from eqa.messages import BOUND_STRATEGIES, EpisodeStart, Frontier, GridSpec, Pose2D, PromptPoint, Question
from services.mapper.episode_map import EpisodeMap
from services.mapper.frontiers import target_weights, weigh_frontiers
from services.mapper.semantic_map import QUESTION_LAYER, ground_truth_scores
from services.planner import frontier_rules, sampling
from services.planner.step import Memory, PlannerParams, plan_step


def _start(strategy: str, targets: list[tuple[float, float]]) -> EpisodeStart:
    q = Question(text="Is there a mug in the kitchen?", choices=["Yes", "No"], scene="gen-00001",
                 answer="A", targets=targets)
    return EpisodeStart(episode_id="ep-bound", robot="r0", question=q, max_steps=20, strategy=strategy)  # type: ignore[arg-type]


def test_ground_truth_scores_favour_the_point_nearest_the_target() -> None:
    lsv, gsv = ground_truth_scores([(0.0, 0.0), (5.0, 0.0), (0.0, 5.0)], [(6.0, 0.5)], (0.0, -2.0))
    assert int(np.argmax(lsv)) == 1 and lsv[1] > 0.9 and math.isclose(sum(lsv), 1.0)
    assert gsv == 1.0  # a prompt point is nearer the target than the camera
    lsv, gsv = ground_truth_scores([(0.0, 0.0), (1.0, 0.0)], [(-6.0, 0.0)], (-1.0, 0.0))
    assert gsv == 0.0  # everything in view leads away from the target
    assert ground_truth_scores([(0.0, 0.0), (1.0, 0.0)], [], (0.0, 0.0)) == ([0.5, 0.5], 0.0)


def test_target_oracle_goes_for_the_reachable_frontier_nearest_the_target() -> None:
    fr = [Frontier(x=float(x), y=0.0, nx=1.0, ny=0.0, size=5) for x in (0, 4, 8, 12)]
    w = target_weights(fr, [(11.0, 0.0), (-30.0, 0.0)])
    assert [round(f.sv, 1) for f in w] == [-11.0, -7.0, -3.0, -1.0]
    cand = [True, True, True, False]  # the nearest one is not reachable
    i, p, note = sampling.choose("target_oracle", [f.weight for f in w], cand, [1.0, 2.0, 3.0, np.inf],
                                 np.random.default_rng(0), decay_m=3.0)
    assert i == 2 and p[2] == 1.0 and "bound" in note
    # the same frontiers under fbe with the distance decay mostly go to the nearest one
    _, p_fbe, _ = sampling.choose("fbe", [1.0] * 4, cand, [1.0, 2.0, 3.0, np.inf], np.random.default_rng(0), 3.0)
    assert p_fbe[0] > p_fbe[2]


def test_perfect_sv_writes_ground_truth_values_not_the_scorers() -> None:
    episode_map = EpisodeMap(_start("perfect_sv", [(6.0, 0.0)]))
    episode_map.pose = Pose2D(x=0.0, y=0.0, yaw=0.0)
    episode_map.volume.ensure(-8.0, 8.0, -8.0, 8.0)
    episode_map.prompts = [PromptPoint(label="A", x=0.0, y=4.0, u=10, v=10),
                           PromptPoint(label="B", x=5.0, y=0.0, u=20, v=10)]
    sv = episode_map.apply_scores([0.99, 0.01], 0.0)  # the scorer says A; the ground truth says B
    assert sv[1] > sv[0]
    assert sv[1] > math.exp(1.5)  # GSV = 1: a point nearer the target than the camera is in view
    em2 = EpisodeMap(_start("semantic", [(6.0, 0.0)]))
    em2.pose, em2.prompts = episode_map.pose, episode_map.prompts
    em2.volume.ensure(-8.0, 8.0, -8.0, 8.0)
    sv2 = em2.apply_scores([0.99, 0.01], 0.0)
    assert sv2[0] > sv2[1]  # semantic keeps the scorer's values


def _valued_frontiers(strategy: str) -> list[Frontier]:
    """Two frontiers valued by the mapper of a ``strategy`` episode from one view where the scorer favours the
    prompt point A (0, 4) and the ground truth, a target at (6, 0), the point B (5, 0): frontier 0 lies beyond
    A, frontier 1 beyond B."""
    em = EpisodeMap(_start(strategy, [(6.0, 0.0)]))
    em.pose = Pose2D(x=0.0, y=0.0, yaw=0.0)
    em.volume.ensure(-10.0, 10.0, -10.0, 10.0)
    em.prompts = [PromptPoint(label="A", x=0.0, y=4.0, u=10, v=10), PromptPoint(label="B", x=5.0, y=0.0, u=20, v=10)]
    em.apply_scores([0.99, 0.01], 0.0)
    fs = [Frontier(x=0.0, y=4.5, nx=0.0, ny=1.0, size=10), Frontier(x=5.5, y=0.0, nx=1.0, ny=0.0, size=10)]
    c = em.config
    return weigh_frontiers(fs, em.layer(QUESTION_LAYER), em.origin, em.resolution, c.tau_sv, c.tau_sv_normal,
                           c.frontier.d_sv, c.frontier.normal_scored_only, c.frontier.unscored_sv)


def test_perfect_value_rules_go_for_the_frontier_nearest_the_target() -> None:
    # an open, fully explored 20 m x 20 m map: no unknown area, so gain's exploration term is 0 for both
    res = 0.1
    grid = GridSpec(origin_x=-10.0, origin_y=-10.0, resolution=res, rows=200, cols=200)
    free = np.ones((200, 200), dtype=bool)
    occ = np.zeros_like(free)
    params = PlannerParams().rule_params()
    geo = np.array([4.0, 5.0])  # the frontier nearest the target is the farther one
    cand = np.ones(2, dtype=bool)
    for rule, perfect in (("vlfm", "perfect_vlfm"), ("gain", "perfect_gain")):
        assert frontier_rules.rule_of(perfect) == rule and frontier_rules.rule_of(rule) == rule
        fs = _valued_frontiers(perfect)
        assert fs[1].sv > fs[0].sv  # the ground truth's values, not the scorer's
        i, probs, note, fresh = frontier_rules.choose(perfect, fs, cand, geo, grid, free, occ, free, (0.0, 0.0),
                                                      params, None, 1.0)
        assert i == 1 and probs.tolist() == [0.0, 1.0] and fresh and note.startswith(perfect)
        # the same rule on the scorer's values goes the other way: the yardstick differs by its values only
        scored = _valued_frontiers(rule)
        assert scored[0].sv > scored[1].sv
        assert frontier_rules.choose(rule, scored, cand, geo, grid, free, occ, free, (0.0, 0.0), params, None,
                                     1.0)[0] == 0
        # through the planner's step: the yardstick plans exactly as its rule does on the same values
        pose = Pose2D(x=1.0, y=1.0, yaw=0.0)
        a = plan_step(grid, free, occ, pose, fs, perfect, Memory(), sampling.step_rng(0, 0), explored=free)  # type: ignore[arg-type]
        b = plan_step(grid, free, occ, pose, fs, rule, Memory(), sampling.step_rng(0, 0), explored=free)  # type: ignore[arg-type]
        assert a.kind == b.kind == "move" and a.frontier_index == b.frontier_index == 1
        assert a.pose == b.pose and a.probabilities == b.probabilities
    assert frontier_rules.rule_of("perfect_sv") is None and frontier_rules.rule_of("semantic") is None


def test_the_product_refuses_the_yardsticks() -> None:
    from gateway.schemas import QuestionRequest

    assert {"target_oracle", "perfect_sv", "perfect_vlfm", "perfect_gain"} <= BOUND_STRATEGIES
    for s in sorted(BOUND_STRATEGIES):
        with pytest.raises(ValidationError, match="yardstick"):
            QuestionRequest(question="Where is the mug?", scene="gen-00001", strategy=s)  # type: ignore[arg-type]
    assert QuestionRequest(question="Where is the mug?", scene="gen-00001", strategy="semantic").strategy == "semantic"


def _tune_explore() -> Any:
    from eqa_app.benches import tune_explore

    return tune_explore


def test_tuning_tool_refuses_evaluation_seeds(capsys: pytest.CaptureFixture[str]) -> None:
    from eqa.seeds import EVALUATION_SEEDS

    mod = _tune_explore()
    for seed in (*EVALUATION_SEEDS, 0):
        with pytest.raises(SystemExit) as exc:
            mod.main(["--seed", str(seed), "--limit", "1"])
        assert exc.value.code == 2
    assert "tuning seed 11" in capsys.readouterr().err


def test_evidence_ceiling_diagnosis() -> None:
    mod = _tune_explore()
    half = math.radians(60)
    # the field of view: a target 2 m ahead is in it, one behind the robot is not, the nearest target counts
    d, infov, px = mod._geometry(Pose2D(x=0, y=0, yaw=0), [(2.0, 0.0), (9.0, 9.0)], half, 5)
    assert math.isclose(d, 2.0) and infov and px == 5
    assert not mod._geometry(Pose2D(x=0, y=0, yaw=math.pi), [(2.0, 0.0)], half, 0)[1]
    assert mod._geometry(Pose2D(x=0, y=0, yaw=math.radians(55)), [(1.0, 0.0)], half, 0)[1]
    assert mod._geometry(Pose2D(x=0, y=0, yaw=0), [], half, 0)[0] == math.inf

    def ep(quality: list[float], geo: list[tuple[float, bool, int]], objects: int = 1, T: int = 4) -> Any:
        return mod.Episode("q", "location", T, "A", [[1.0, 0.0]] * len(quality), [0.1] * len(quality), quality,
                           geo=geo, objects=objects)

    far = (8.0, True, 0)
    assert mod.ceiling_reason(ep([0, 0, 0.4, 0], [far] * 4)) == "seen"
    assert mod.ceiling_reason(ep([0] * 4, [far] * 4, objects=0)) == "room"
    assert mod.ceiling_reason(ep([0] * 4, [far, (6.0, True, 20), far, far])) == "small"
    assert mod.ceiling_reason(ep([0] * 4, [far, (2.5, True, 0), far, far])) == "near, faced"
    assert mod.ceiling_reason(ep([0] * 4, [far, (2.5, False, 0), far, far])) == "near, not faced"
    assert mod.ceiling_reason(ep([0] * 4, [far, (3.5, True, 0), far, far])) == "never near"
    # within T only: evidence seen at step 5 of T = 4 counts within 2 T, not within T
    late = ep([0] * 5 + [0.5, 0, 0], [far] * 8)
    assert mod.ceiling_reason(late, 1.0) == "never near" and mod.ceiling_reason(late, 2.0) == "seen"


def _trace(qid: str, rels: list[float], right_from: int | None, T: int = 10):
    from services.stopper.calibration import Trace, TraceStep

    steps = []
    for k, r in enumerate(rels):
        good = right_from is not None and k >= right_from
        steps.append(TraceStep(answer_probs=[0.8, 0.2] if good else [0.2, 0.8], relevance=r))
    return Trace(question_id=qid, scene="gen-00001", category="existence", choices=["Yes", "No"], answer="A",
                 max_steps=T, strategy="x", steps=steps)


def test_seed_pooled_statistics() -> None:
    from eqa_app import evaluation as ev
    from eqa_app import stats

    lo, hi = stats.wilson_ci(5, 10)
    assert lo < 0.5 < hi and lo > 0.2 and hi < 0.8
    d, lo, hi = stats.paired_diff_ci(10, 2, 100)
    assert math.isclose(d, 0.08) and lo > 0 and hi < 0.2
    assert stats.paired_diff_ci(3, 3, 50)[0] == 0.0

    # a sees the evidence at step 2 (and is right from then), b only at step 7
    a = [_trace(f"q{i}", [0.1, 0.1, 0.5] + [0.1] * 7, 2) for i in range(6)]
    b = [_trace(f"q{i}", [0.1] * 7 + [0.5, 0.1, 0.1], 7) for i in range(6)]
    assert ev.evidence_cdf(a, [0.2, 0.3, 1.0]) == [0.0, 1.0, 1.0]
    assert ev.evidence_cdf(b, [0.3, 0.8]) == [0.0, 1.0]
    assert ev.median_first_evidence(a) == 0.3 and ev.median_first_evidence(b) == 0.8
    assert ev.median_first_evidence([_trace("n", [0.1] * 10, None)]) is None
    p = ev.paired_first_evidence(a, b)
    assert (p.a_only, p.b_only, p.n) == (6, 0, 6) and math.isclose(p.diff, 0.5)
    rows = ev.paired_comparison(a, b, (0.5, 1.0))
    assert (rows[0].a_only, rows[0].b_only, rows[1].a_only) == (6, 0, 0)
    pooled = ev.pool_paired([rows, rows])
    assert (pooled[0].a_only, pooled[0].n) == (12, 12) and pooled[0].p_value < 0.001
    assert pooled[0].ci_low <= pooled[0].diff <= pooled[0].ci_high


def test_success_split_by_evidence() -> None:
    from eqa_app import evaluation as ev

    # 3 episodes see the evidence at step 2 and are right from then; 1 sees it only at step 8 (after 0.5 T) and
    # is right from then; 2 never see it and stay wrong
    traces = [_trace(f"s{i}", [0.1, 0.1, 0.5] + [0.1] * 7, 2) for i in range(3)]
    traces += [_trace("late", [0.1] * 8 + [0.6, 0.1], 8)]
    traces += [_trace(f"n{i}", [0.1] * 10, None) for i in range(2)]
    full = ev.success_by_evidence(traces, 1.0)
    assert (full.n_seen, full.success_seen, full.n_unseen, full.success_unseen) == (4, 1.0, 2, 0.0)
    assert full.lift == 1.0
    half = ev.success_by_evidence(traces, 0.5)
    assert (half.n_seen, half.success_seen, half.n_unseen, half.success_unseen) == (3, 1.0, 3, 0.0)


def test_oracle_tuning_tool_refuses_evaluation_seeds(capsys: pytest.CaptureFixture[str]) -> None:
    from eqa_app.benches import tune_oracle as mod

    for seed in (1, 2, 3, 0):
        with pytest.raises(SystemExit) as exc:
            mod.main(["--seed", str(seed)])
        assert exc.value.code == 2
    assert "evaluation seed" in capsys.readouterr().err


@pytest.mark.xfail(strict=True, reason="known limitation (docs/status.md): a frontier just behind a doorway the map "
                   "narrows is 'reached' from this side at 0.3 m clearance; the trial fix (every clearance searched "
                   "per frontier) lowered fbe's coverage in tests/planner/test_planner_explore.py (0.93 -> 0.88) "
                   "and was withdrawn")
def test_planner_enters_a_room_behind_a_narrowed_doorway() -> None:
    """Two rooms joined by a doorway the map narrows to 0.5 m: a frontier inside the far room should be approached
    through the door at the reduced clearance, not 'reached' from this side of the wall (rooms behind
    such doors were never entered, even by target_oracle)."""
    from eqa.messages import GridSpec
    from services.planner.sampling import step_rng
    from services.planner.step import Memory, plan_step

    res = 0.1
    rows, cols = 40, 100  # 4 m x 10 m
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=res, rows=rows, cols=cols)
    free = np.zeros((rows, cols), dtype=bool)
    occ = np.zeros((rows, cols), dtype=bool)
    free[1:-1, 1:49] = True  # room A: x 0.1 .. 4.9
    occ[:, 49:51] = True  # wall at x 4.9 .. 5.1
    free[1:-1, 51:-1] = True  # room B: x 5.1 .. 9.9
    occ[18:23, 49:51] = False
    free[18:23, 49:51] = True  # doorway 0.5 m wide at y 1.8 .. 2.3
    far = Frontier(x=5.65, y=2.05, nx=1.0, ny=0.0, size=10)  # inside room B, 1 m from room A's reach
    near = Frontier(x=1.0, y=3.5, nx=-1.0, ny=0.0, size=10)  # in room A
    pose = Pose2D(x=2.0, y=2.0, yaw=0.0)
    frontiers = target_weights([far, near], [(8.0, 2.0)])
    plan = plan_step(grid, free, occ, pose, frontiers, "target_oracle", Memory(), step_rng(0, 0))
    assert plan.kind == "move" and plan.frontier_index == 0
    assert plan.full_path[-1][0] > 5.1, f"approach point {plan.full_path[-1]} is not inside room B"
    assert plan.clearance_m is not None and plan.clearance_m < 0.3
