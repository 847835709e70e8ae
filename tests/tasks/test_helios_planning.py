"""HELIOS planning cores against hand-computed cases: Eq. 8-10 (services/planner/helios.py), Eq. 11 and the
pick-attempt limits (services/planner/decisions.py), the gaze-point filters (services/mapper/gaze.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eqa.messages import GridSpec
from services.mapper.gaze import contour_points, gaze_points
from services.planner import helios
from services.planner.decisions import PickBudget, Scored, decide, decide_one, pick_limit
from services.planner.helios import (
    CandidateObservation,
    ChosenFrontier,
    FrontierOption,
    SearchMemory,
    StoredCandidate,
    f0_association,
    v0,
)

A1 = StoredCandidate(1, S0=0.6, IG0=10.0, x=0.0, y=0.0)
A2 = StoredCandidate(2, S0=0.4, IG0=20.0, x=10.0, y=0.0)


# ---- Eq. 8 -------------------------------------------------------------------------------------------------


def test_eq8_v0_is_the_best_stored_candidate_minus_distance() -> None:
    # a1: 0.6*10 - 0.001*5 = 5.995 ; a2: 0.4*20 - 0.001*sqrt(65) = 7.99193774...
    assert v0(3.0, 4.0, [A1, A2], 0.001) == pytest.approx(8.0 - 0.001 * math.sqrt(65.0), abs=1e-12)
    assert v0(3.0, 4.0, [A1], 0.001) == pytest.approx(5.995, abs=1e-12)
    # a large distance weight flips the choice to the nearer candidate: a1 6 - 5 = 1 > a2 8 - 8.06 < 0
    assert v0(3.0, 4.0, [A1, A2], 1.0) == pytest.approx(1.0, abs=1e-12)
    assert v0(0.0, 0.0, [], 0.001) is None


# ---- Eq. 9 -------------------------------------------------------------------------------------------------


def test_eq9_f0_averages_the_ratio_over_previous_frontiers() -> None:
    chosen = [ChosenFrontier(3.0, 4.0, 2.0), ChosenFrontier(10.0, 0.0, 0.0), ChosenFrontier(0.0, 0.0, 4.0)]
    # V0(3,4) = 7.99193774 / 2 ; the zero-score frontier adds nothing but counts ; V0(0,0) = max(6, 8 - 0.01) / 4
    expected = ((8.0 - 0.001 * math.sqrt(65.0)) / 2.0 + 7.99 / 4.0) / 3.0
    assert f0_association(chosen, [A1, A2], 0.001) == pytest.approx(expected, abs=1e-12)
    assert f0_association([], [A1], 0.001) == 1.0  # no previous frontier: the value map's own scale
    assert f0_association(chosen, [], 0.001) == 1.0  # no candidate: frontiers alone


# ---- Eq. 10 ------------------------------------------------------------------------------------------------


def _memory() -> SearchMemory:
    m = SearchMemory()
    m.stored = {1: A1, 2: A2}
    m.chosen = [ChosenFrontier(3.0, 4.0, 2.0), ChosenFrontier(10.0, 0.0, 0.0), ChosenFrontier(0.0, 0.0, 4.0)]
    return m


def test_eq10_values_of_candidates_and_frontiers() -> None:
    F0 = ((8.0 - 0.001 * math.sqrt(65.0)) / 2.0 + 7.99 / 4.0) / 3.0  # 1.99782...
    cand = CandidateObservation(7, S=0.5, IG=4.0, x=3.0, y=4.0)  # V = 2 - 0.005 = 1.995
    front = FrontierOption(0, x=0.0, y=1.0, F=1.0)  # V = 1 * F0 - 0.001 = 1.99682...
    ranked = helios.values((0.0, 0.0), [front], [cand], _memory(), 0.001)
    assert [(c.kind, c.ref) for c in ranked] == [("frontier", 0), ("candidate", 7)]
    assert ranked[0].value == pytest.approx(F0 - 0.001, abs=1e-12)
    assert ranked[1].value == pytest.approx(1.995, abs=1e-12)


def test_ablations_choose_differently_on_the_same_state() -> None:
    cand = CandidateObservation(7, S=0.5, IG=4.0, x=3.0, y=4.0)
    front = FrontierOption(0, x=0.0, y=1.0, F=1.0)
    m = _memory()
    assert helios.choose((0.0, 0.0), [front], [cand], m, 0.001, 0.3, "helios").kind == "frontier"
    assert m.chosen == _memory().chosen  # F' grows when the planner sets out for it, not when it is chosen
    assert 7 in m.stored and m.stored[7].S0 == 0.5  # the first detection is stored
    assert helios.choose((0.0, 0.0), [front], [cand], _memory(), 0.001, 0.3, "no_global").kind == "candidate"
    assert helios.choose((0.0, 0.0), [front], [cand], _memory(), 0.001, 0.3, "trusting").kind == "frontier"
    # a more valuable candidate wins the full objective too
    rich = CandidateObservation(8, S=0.9, IG=40.0, x=3.0, y=4.0)
    assert helios.choose((0.0, 0.0), [front], [rich], _memory(), 0.001, 0.3).ref == 8


def test_candidates_need_cs_a_and_not_visited() -> None:
    low = CandidateObservation(3, S=0.29, IG=100.0, x=0.0, y=0.0)
    ok = CandidateObservation(4, S=0.3, IG=1.0, x=0.0, y=0.0)
    assert [c.instance_id for c in helios.candidates_of([low, ok], 0.3)] == [4]
    assert helios.candidates_of([low, ok], 0.3, visited={4}) == []
    m = SearchMemory()
    assert helios.choose((0.0, 0.0), [], [low], m, 0.001, 0.3) is None
    assert 3 not in m.stored  # below cs_a: not a member of A
    m2 = SearchMemory.from_json(_memory().to_json())
    assert m2.stored == _memory().stored and m2.chosen == _memory().chosen


# ---- Eq. 11 decisions --------------------------------------------------------------------------------------


def test_eq11_pick_look_or_global() -> None:
    tau, inc = 0.5, 0.125
    assert decide_one(0.5, None, tau, inc) == "act"  # Psi >= tau (boundary)
    assert decide_one(0.25, 0.375, tau, inc) == "look"  # Psi' = Psi + tau_inc (boundary) < tau
    assert decide_one(0.25, 0.37, tau, inc) == "global"
    assert decide_one(0.45, 0.5, tau, inc) == "look"  # min(tau, Psi + inc) = tau = 0.5
    assert decide_one(0.45, 0.49, tau, inc) == "global"  # Psi + inc = 0.575 > tau: needs Psi' >= tau
    assert decide_one(0.25, None, tau, inc) == "global"


def test_decide_over_candidates_and_the_trusting_agent() -> None:
    c = [Scored(1, S=0.6, psi=0.55), Scored(2, S=0.7, psi=0.6), Scored(3, S=0.5, psi=0.2, psi_prime=0.4),
         Scored(4, S=0.2, psi=0.9)]
    d = decide(c, 0.5, 0.05, cs=0.3)
    assert (d.action, d.instance_id) == ("act", 2)  # highest Psi passing tau; 4 is below cs
    d = decide(c, 0.5, 0.05, cs=0.3, exclude={1, 2})
    assert (d.action, d.instance_id) == ("look", 3)
    assert decide(c, 0.5, 0.05, cs=0.3, exclude={1, 2, 3}).action == "global"
    weak = [Scored(5, S=0.31, psi=0.01)]
    assert decide(weak, 0.5, 0.05, cs=0.3).action == "global"
    t = decide(weak, 0.5, 0.05, cs=0.3, trusting=True)
    assert (t.action, t.instance_id) == ("act", 5)  # trusting acts on the first detection
    assert decide([], 0.5, 0.05, cs=0.3, trusting=True).action == "global"


def test_pick_attempt_limits() -> None:
    one = PickBudget(pick_limit("1"))
    assert not one.exhausted
    one.attempt(False)
    assert one.exhausted
    with pytest.raises(RuntimeError):
        one.attempt(True)
    five = PickBudget(pick_limit(5))
    for _ in range(5):
        five.attempt(False)
    assert five.exhausted and five.attempts == 5
    unlimited = PickBudget(pick_limit("unlimited"))
    for _ in range(100):
        unlimited.attempt(False)
    assert not unlimited.exhausted
    assert pick_limit(0) is None and pick_limit(None) is None
    for bad in ("many", -1):
        with pytest.raises(ValueError):
            pick_limit(bad)
    with pytest.raises(ValueError):
        PickBudget(0)


# ---- gaze points -------------------------------------------------------------------------------------------

GRID = GridSpec(origin_x=-3.0, origin_y=-3.0, resolution=0.1, rows=60, cols=60)


def _cell(x: float, y: float) -> tuple[int, int]:
    return math.floor((y + 3.0) / 0.1), math.floor((x + 3.0) / 0.1)


def test_contour_is_at_the_radius_around_the_footprint() -> None:
    pts = contour_points((1.0, 2.0), (0.5, 0.25), 1.0, 40)
    assert pts.shape == (40, 2)
    assert pts[0] == pytest.approx([2.5, 2.0])  # starts in the middle of the +x side
    for x, y in pts:
        dx = max(abs(x - 1.0) - 0.5, 0.0)
        dy = max(abs(y - 2.0) - 0.25, 0.0)
        assert math.hypot(dx, dy) == pytest.approx(1.0, abs=1e-9)
    # evenly spaced by arc length: perimeter 2*(0.5)+2*(1.0)+2*pi = 9.283; 40 steps of 0.232 (chords ~ arcs)
    steps = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    assert steps.max() == pytest.approx((3.0 + 2 * math.pi) / 40, rel=0.02)


def test_gaze_points_orientation_and_occupancy_filter() -> None:
    occ = np.zeros((60, 60), bool)
    centre, extent = (0.0, 0.0, 0.4), (0.4, 0.4, 0.8)
    pts = gaze_points(occ, None, GRID, centre, extent, 1.0, 8, 1.0)
    assert len(pts) == 8
    p0 = pts[0]
    assert (p0.x, p0.y) == pytest.approx((1.2, 0.0))
    assert p0.yaw == pytest.approx(math.pi)  # looks back at the centre
    assert p0.pitch == pytest.approx(math.atan2(0.8 - 1.5, 1.2), abs=1e-6)  # at the top (0.8 m) from 1.5 m
    for g in pts:
        d = math.atan2(-g.y, -g.x) - g.yaw
        assert math.atan2(math.sin(d), math.cos(d)) == pytest.approx(0.0, abs=1e-6)
    occ[_cell(1.2, 0.0)] = True  # the first gaze point's cell is occupied
    left = gaze_points(occ, None, GRID, centre, extent, 1.0, 8, 1.0)
    assert len(left) == 7 and all((g.x, g.y) != pytest.approx((1.2, 0.0)) for g in left)
    off_map = gaze_points(np.zeros((60, 60), bool), None, GRID, (2.5, 0.0, 0.4), extent, 1.0, 8, 1.0)
    assert all(g.x < 3.0 for g in off_map) and len(off_map) < 8


def test_gaze_points_occlusion_filter_uses_height() -> None:
    occ = np.zeros((60, 60), bool)
    heights = np.zeros((60, 60))
    centre, extent = (0.0, 0.0, 0.4), (0.4, 0.4, 0.8)
    # the object's own footprint (a table under it) is occupied and high: not in its own way
    for x in np.arange(-0.15, 0.2, 0.1):
        for y in np.arange(-0.15, 0.2, 0.1):
            occ[_cell(x, y)] = True
            heights[_cell(x, y)] = 0.9
    assert len(gaze_points(occ, heights, GRID, centre, extent, 1.0, 8, 0.6)) == 8
    # a wall stub between the +x gaze point (1.2, 0) and the object
    for y in (-0.05, 0.05):
        occ[_cell(0.65, y)] = True
        heights[_cell(0.65, y)] = 1.2
    tall = gaze_points(occ, heights, GRID, centre, extent, 1.0, 8, 0.6)
    assert len(tall) == 7 and all(g.x < 1.1 or abs(g.y) > 0.1 for g in tall)
    heights[_cell(0.65, -0.05)] = heights[_cell(0.65, 0.05)] = 0.3  # low: the camera sees over it
    assert len(gaze_points(occ, heights, GRID, centre, extent, 1.0, 8, 0.6)) == 8
    # without a height map every occupied cell on the way occludes (the footprint still does not)
    assert len(gaze_points(occ, None, GRID, centre, extent, 1.0, 8, 0.6)) == 7


def test_gaze_points_refuse_bad_input() -> None:
    occ = np.zeros((60, 60), bool)
    with pytest.raises(ValueError):
        gaze_points(np.zeros((5, 5), bool), None, GRID, (0, 0, 0), (1, 1, 1), 1.0, 8, 1.0)
    with pytest.raises(ValueError):
        gaze_points(occ, None, GRID, (0, 0, 0), (1, 1, 1), 1.0, 0, 1.0)
    with pytest.raises(ValueError):
        gaze_points(occ, None, GRID, (math.nan, 0, 0), (1, 1, 1), 1.0, 8, 1.0)
    with pytest.raises(ValueError):
        gaze_points(occ, None, GRID, (0, 0, 0), (1, 1, 1), -1.0, 8, 1.0)


# ---- the skill pose (the gaze contour was the pick reach) ----------------------------------------


def test_skill_pose_is_within_reach_of_the_object_facing_it() -> None:
    from services.planner.task_fsm import SKILL_APPROACH_M, SeenObject, TaskMachine, approach_pose

    x, y, yaw = approach_pose((1.0, 1.0), (1.0, 2.5), 0.6)  # a gaze point 1.5 m north
    assert (x, y) == pytest.approx((1.0, 1.6)) and yaw == pytest.approx(-math.pi / 2)
    assert approach_pose((0.0, 0.0), (0.3, 0.4), 0.6) == pytest.approx((0.3, 0.4, math.atan2(-0.4, -0.3)))
    # a confident object without gaze points (the trusting agent's case): approached from the robot's side
    m = TaskMachine("pick_place", "mug", "table", "counter", "trusting")
    mug = SeenObject(7, "mug", {"mug": (0.4, 0.2, 0.2)}, 4.0, 0.0)
    a = m.step((0.0, 0.0, 0.0), [], [mug])
    assert a.kind == "pick" and a.ref == 7
    assert a.pose == pytest.approx((4.0 - SKILL_APPROACH_M, 0.0, 0.0))
    assert SKILL_APPROACH_M < 0.9  # the oracle pick's reach (services/sim/skills.py REACH_M)


def test_find_object_looks_from_a_gaze_point_before_stopping() -> None:
    """Section 4.2: a confident candidate is seen again from a gaze point, then the stop is decided again."""
    from services.planner.task_fsm import Gaze, SeenObject, TaskMachine

    gaze = (Gaze(2.0, 1.0, math.pi, psi_prime=0.7), Gaze(0.0, 1.0, 0.0, psi_prime=0.6))
    box = SeenObject(3, "box", {"box": (0.77, 0.19, 0.58)}, 1.0, 1.0, gaze=gaze)  # one view: Psi 0.58 >= 0.5
    m = TaskMachine("find_object", "box", ablation="helios")
    a = m.step((5.0, 5.0, 0.0), [], [box])
    assert (a.kind, a.pose) == ("move", (2.0, 1.0, math.pi))  # the best gaze point first, no stop yet
    # at the gaze point: the false positive was not seen again, Psi fell below tau -> no stop
    m2 = TaskMachine.from_json(m.to_json())  # (the state survives a planner restart)
    fp = SeenObject(3, "box", {"box": (0.55, 0.2, 0.35)}, 1.0, 1.0, gaze=gaze)
    assert m2.step((2.0, 1.0, math.pi), [], [fp]).kind != "stop"
    # a real box: still confident after the look -> stop
    m3 = TaskMachine.from_json(m.to_json())
    assert m3.step((2.0, 1.0, math.pi), [], [box]).kind == "stop"
    t = TaskMachine("find_object", "box", ablation="trusting")
    assert t.step((5.0, 5.0, 0.0), [], [box]).kind == "stop"  # the trusting agent stops at once


def test_choose_keeps_the_committed_frontier_but_a_better_candidate_wins() -> None:
    """Eq. 10 with a frontier the robot is on its way to (``committed``): the committed frontier is kept while
    a frontier ranks first; a candidate that ranks first is chosen at once."""
    from services.planner import helios as h

    fr = [h.FrontierOption(0, 5.0, 0.0, 0.9), h.FrontierOption(1, -5.0, 0.0, 0.4)]
    assert h.choose((0.0, 0.0), fr, [], h.SearchMemory(), 0.001, 0.3).ref == 0
    mem = h.SearchMemory()
    kept = h.choose((0.0, 0.0), fr, [], mem, 0.001, 0.3, committed=1)
    assert (kept.kind, kept.ref) == ("frontier", 1) and not mem.chosen  # F' grows in the planner shell
    # a candidate with S IG = 0.8 * 2 = 1.6 > 0.9 F0 (F0 = 1: no previous frontier): the candidate
    cand = [h.CandidateObservation(7, 0.8, 2.0, 1.0, 1.0)]
    won = h.choose((0.0, 0.0), fr, cand, h.SearchMemory(), 0.001, 0.3, committed=1)
    assert (won.kind, won.ref) == ("candidate", 7)
