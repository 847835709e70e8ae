"""The deterministic frontier rules ``vlfm``, ``gain`` and ``topo`` (services/planner/frontier_rules.py) on
hand-built frontier sets and maps: each case is built so that a wrong rule (Eq. A6's largest weight, the
nearest frontier, a missing term, a sign error) picks another frontier."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner import frontier_rules as fr
from services.planner.sampling import step_rng
from services.planner.step import Memory, PlannerParams, plan_step

RES = 0.1


def _sv_for(value: float) -> float:
    """SV_p = SV_p,normal giving ``frontier_value == value``."""
    return math.exp(value)


def _frontier(x: float, y: float, value: float, nx: float = 1.0) -> Frontier:
    sv = _sv_for(value)
    return Frontier(x=x, y=y, nx=nx, ny=0.0, size=10, sv=sv, sv_normal=sv, weight=math.exp(2 * sv))


def _params(**kw: float) -> fr.RuleParams:
    base = dict(cost_per_m=0.1, commit_margin=0.1, gain_weight=0.5, gain_radius_m=1.0, topo_core_m=0.5,
                topo_hop_cost=0.3)
    base.update(kw)
    return fr.RuleParams(**base)  # type: ignore[arg-type]


def _open_map(rows: int = 40, cols: int = 100) -> tuple[GridSpec, np.ndarray, np.ndarray, np.ndarray]:
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=RES, rows=rows, cols=cols)
    free = np.zeros((rows, cols), dtype=bool)
    free[1:-1, 1:-1] = True
    occ = ~free
    return grid, free, occ, free.copy()


def test_frontier_value_is_the_log_of_eq3() -> None:
    assert fr.frontier_value(_frontier(0, 0, 0.7)) == pytest.approx(0.7)
    f = Frontier(x=0, y=0, nx=1, ny=0, size=3, sv=math.e**2, sv_normal=1.0)
    assert fr.frontier_value(f) == pytest.approx(math.log((math.e**2 + 1) / 2))
    assert fr.frontier_value(Frontier(x=0, y=0, nx=1, ny=0, size=3, sv=0.0, sv_normal=0.0)) == 0.0  # unscored
    assert fr.frontier_value(Frontier(x=0, y=0, nx=1, ny=0, size=3, sv=math.nan, sv_normal=1.0)) == 0.0


def test_vlfm_maximises_value_minus_distance_cost() -> None:
    grid, free, occ, explored = _open_map()
    # values 1.0, 0.8, 0.3 at 9, 4, 1 m: scores 0.1, 0.4, 0.2 -> the middle one (neither the largest Eq. A6
    # weight, frontier 0, nor the nearest, frontier 2)
    fs = [_frontier(9.0, 2.0, 1.0), _frontier(5.0, 2.0, 0.8), _frontier(2.0, 2.0, 0.3)]
    geo = np.array([9.0, 4.0, 1.0])
    cand = np.ones(3, dtype=bool)
    i, p, note, fresh = fr.choose("vlfm", fs, cand, geo, grid, free, occ, explored, (1.0, 2.0), _params(), None, 1.0)
    assert (i, fresh) == (1, True) and p.tolist() == [0.0, 1.0, 0.0] and "vlfm" in note
    # no distance cost: the largest value; a high one: the nearest
    assert fr.choose("vlfm", fs, cand, geo, grid, free, occ, explored, (1, 2), _params(cost_per_m=0.0), None,
                     1.0)[0] == 0
    assert fr.choose("vlfm", fs, cand, geo, grid, free, occ, explored, (1, 2), _params(cost_per_m=1.0), None,
                     1.0)[0] == 2
    # a non-candidate or unreachable frontier is never chosen, whatever its score
    cand2 = np.array([True, False, True])
    assert fr.choose("vlfm", fs, cand2, geo, grid, free, occ, explored, (1, 2), _params(), None, 1.0)[0] == 2
    geo2 = np.array([9.0, np.inf, 1.0])
    assert fr.choose("vlfm", fs, cand, geo2, grid, free, occ, explored, (1, 2), _params(), None, 1.0)[0] == 2
    # nothing to choose
    assert fr.choose("vlfm", fs, np.zeros(3, bool), geo, grid, free, occ, explored, (1, 2), _params(), None,
                     1.0)[0] is None


def test_ties_go_to_the_shorter_path_then_the_lower_index() -> None:
    grid, free, occ, explored = _open_map()
    fs = [_frontier(5.0, 1.0, 0.5), _frontier(5.0, 3.0, 0.5), _frontier(3.0, 2.0, 0.5)]
    cand = np.ones(3, dtype=bool)
    p0 = _params(cost_per_m=0.0)
    assert fr.choose("vlfm", fs, cand, np.array([4.0, 4.0, 2.0]), grid, free, occ, explored, (1, 2), p0, None,
                     1.0)[0] == 2
    assert fr.choose("vlfm", fs, cand, np.array([4.0, 4.0, 6.0]), grid, free, occ, explored, (1, 2), p0, None,
                     1.0)[0] == 0


def test_commitment_is_kept_until_its_value_drops_or_another_frontier_is_clearly_better() -> None:
    grid, free, occ, explored = _open_map()
    geo = np.array([6.0, 3.0])
    cand = np.ones(2, dtype=bool)
    committed = _frontier(7.0, 2.0, 0.6)  # chosen earlier at value 0.6

    def pick(v_target: float, v_other: float) -> tuple[int | None, bool]:
        fs = [_frontier(7.05, 2.0, v_target), _frontier(4.0, 2.0, v_other)]
        i, _, _, fresh = fr.choose("vlfm", fs, cand, geo, grid, free, occ, explored, (1, 2), _params(), committed,
                                   1.0)
        return i, fresh

    # scores: target 0.6 - 0.6 = 0.0, other 0.05 - 0.3 ... kept while within the margin of the best
    assert pick(0.6, 0.35) == (0, False)  # other 0.05 > 0.0, but by less than 0.1: kept
    assert pick(0.6, 0.45) == (1, True)  # other 0.15: better by more than the margin, re-plan
    assert pick(0.45, 0.0) == (0, True)  # value fell 0.15 (> margin) since chosen: re-plan (the best is itself)
    assert pick(0.55, 0.0) == (0, False)  # fell 0.05: kept
    far_away = _frontier(2.0, 2.0, 0.6)  # no candidate within the commit radius of it: a fresh choice
    fs = [_frontier(7.05, 2.0, 0.6), _frontier(4.0, 2.0, 0.0)]
    assert fr.choose("vlfm", fs, cand, geo, grid, free, occ, explored, (1, 2), _params(), far_away, 1.0)[3]


def test_unknown_share_counts_the_unexplored_disk() -> None:
    grid, free, occ, explored = _open_map()
    explored[:, 50:] = False  # the right half is unknown (not occupied)
    free[:, 50:] = False
    occ[:, 50:] = False
    occ[0, :] = occ[-1, :] = False  # borders unknown rather than walls, so the disks are not clipped by them
    f_mid = _frontier(5.0, 2.0, 0.0)  # on the boundary: about half of its disk is unknown
    f_in = _frontier(2.0, 2.0, 0.0)  # deep in the explored half: nothing unknown within 1 m
    f_edge = _frontier(0.05, 2.0, 0.0)  # at the map's edge: the outside counts as unknown
    share = fr.unknown_share([f_mid, f_in, f_edge], grid, explored, occ, 1.0)
    assert share[0] == pytest.approx(0.5, abs=0.06)
    assert share[1] == 0.0
    assert 0.35 < share[2] < 0.6


def test_gain_prefers_the_frontier_that_opens_more_unknown_area() -> None:
    grid, free, occ, explored = _open_map()
    explored[:, 70:] = False  # a big unknown region on the right
    explored[5:10, 10:15] = False  # a small unknown pocket on the left
    fa = _frontier(7.0, 2.0, 0.3)  # at the big region, 6 m away
    fb = _frontier(1.0, 0.7, 0.35)  # at the pocket, 1.5 m away: vlfm's choice
    geo = np.array([6.0, 1.5])
    cand = np.ones(2, dtype=bool)
    p = _params(gain_weight=2.0, gain_radius_m=1.0)
    assert fr.choose("vlfm", [fa, fb], cand, geo, grid, free, occ, explored, (1, 2), p, None, 1.0)[0] == 1
    share = fr.unknown_share([fa, fb], grid, explored, occ, 1.0)
    assert share[0] > share[1] + 0.3
    assert fr.choose("gain", [fa, fb], cand, geo, grid, free, occ, explored, (1, 2), p, None, 1.0)[0] == 0
    # without an explored plane, free space stands for it (the pocket is free, so it is not unknown then)
    assert fr.choose("gain", [fa, fb], cand, geo, grid, free & explored, occ, None, (1, 2), p, None, 1.0)[0] == 0


def _two_rooms() -> tuple[GridSpec, np.ndarray, np.ndarray]:
    """Room A x 0.1..4.9, wall, room B x 5.1..9.9, joined by a 0.8 m doorway at y 1.6..2.4."""
    rows, cols = 40, 100
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=RES, rows=rows, cols=cols)
    free = np.zeros((rows, cols), dtype=bool)
    free[1:-1, 1:49] = True
    free[1:-1, 51:-1] = True
    free[16:24, 49:51] = True
    return grid, free, ~free


def test_regions_split_the_free_space_at_the_doorway() -> None:
    grid, free, _ = _two_rooms()
    labels, n = fr.regions(free, RES, 0.5)
    assert n == 2
    a, b = fr.room_of(labels, grid, 2.0, 2.0), fr.room_of(labels, grid, 8.0, 2.0)
    assert a > 0 and b > 0 and a != b
    assert (labels[free] > 0).all() and (labels[~free] == 0).all()  # every free cell has a room
    hops = fr.region_hops(labels, n, a)
    assert hops[a] == 0 and hops[b] == 1
    one_room = np.zeros_like(free)
    one_room[1:-1, 1:-1] = True
    assert fr.regions(one_room, RES, 0.5)[1] == 1
    fs = [_frontier(3.0, 3.0, 0.0), _frontier(8.0, 3.0, 0.0)]
    assert fr.doorways(fs, grid, free, (2.0, 2.0), 0.5).tolist() == [0.0, 1.0]


def test_topo_finishes_the_room_before_crossing_a_doorway() -> None:
    grid, free, occ = _two_rooms()
    fa = _frontier(1.0, 3.5, 0.5, nx=-1.0)  # in the robot's room, 4 m away
    fb = _frontier(6.0, 2.0, 0.55)  # through the doorway, 3 m away: vlfm's choice (0.25 vs 0.1)
    geo = np.array([4.0, 3.0])
    cand = np.ones(2, dtype=bool)
    p = _params(topo_hop_cost=0.3)
    assert fr.choose("vlfm", [fa, fb], cand, geo, grid, free, occ, free, (4.0, 2.0), p, None, 1.0)[0] == 1
    assert fr.choose("topo", [fa, fb], cand, geo, grid, free, occ, free, (4.0, 2.0), p, None, 1.0)[0] == 0
    # a much better value next door is still worth the doorway
    fb2 = _frontier(6.0, 2.0, 1.2)
    assert fr.choose("topo", [fa, fb2], cand, geo, grid, free, occ, free, (4.0, 2.0), p, None, 1.0)[0] == 1


def test_the_rules_through_plan_step_are_deterministic_and_commit() -> None:
    grid, free, occ = _two_rooms()
    fs = [_frontier(1.0, 3.5, 0.2, nx=-1.0), _frontier(9.5, 2.0, 0.9)]
    pose = Pose2D(x=2.0, y=2.0, yaw=0.0)
    for strategy in ("vlfm", "gain", "topo"):
        plans = [plan_step(grid, free, occ, pose, fs, strategy, Memory(), step_rng(s, 0), explored=free)
                 for s in (0, 1, 2)]  # the random generator is not used: the same plan for every seed
        assert all(p.kind == "move" for p in plans), [p.reason for p in plans]
        assert len({(p.frontier_index, p.pose.x, p.pose.y, p.pose.yaw) for p in plans if p.pose}) == 1, strategy
        first = plans[0]
        if first.frontier_index == 1:  # 7.5 m away: not reached in one 3 m step, so the plan commits
            assert first.memory.target is not None and first.sampled
            assert first.pose is not None
            again = plan_step(grid, free, occ, first.pose, fs, strategy, first.memory, step_rng(0, 1), explored=free)
            assert again.frontier_index == 1 and not again.sampled and "kept" in again.reason
    # vlfm goes for the valuable far frontier (0.9 - 0.75 > 0.2 - 0.15); topo pays a doorway for it and stays
    assert plan_step(grid, free, occ, pose, fs, "vlfm", Memory(), step_rng(0, 0)).frontier_index == 1
    p_topo = PlannerParams(topo_hop_cost=0.8)
    assert plan_step(grid, free, occ, pose, fs, "topo", Memory(), step_rng(0, 0), p_topo).frontier_index == 0
    bad = plan_step(grid, free, occ, pose, fs, "gain", Memory(), step_rng(0, 0), explored=free[:-1])
    assert bad.done and "explored" in bad.reason


def test_rule_knobs_are_bounded_and_the_gateway_accepts_the_rules() -> None:
    from gateway.schemas import QuestionRequest

    with pytest.raises(ValidationError):
        PlannerParams(rule_cost_per_m=-1.0)
    with pytest.raises(ValidationError):
        PlannerParams(gain_radius_m=0.0)
    for s in sorted(fr.RULES):
        assert QuestionRequest(question="Where is the mug?", scene="gen-00001", strategy=s).strategy == s
    with pytest.raises(ValueError, match="not a frontier rule"):
        fr.scores("semantic", [], np.zeros(0, bool), np.zeros(0), *_open_map()[:3], None, (0, 0), _params())
