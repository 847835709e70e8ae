"""HELIOS task search and skill logic (services/planner/task_fsm.py, helios.py, task_step.py): the global search's
F0 (Eq. 9), candidates without gaze points, looks used up, the last resort with no frontier, the trusting agent
without a 3D layer, skill poses within reach, and paths that keep the collision radius on the mapped occupancy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eqa.messages import GridSpec, Pose2D
from services.planner import helios
from services.planner import task_step as ts
from services.planner.helios import CandidateObservation, ChosenFrontier, FrontierOption, SearchMemory, StoredCandidate
from services.planner.step import Memory
from services.planner.task_fsm import Gaze, SeenObject, SkillOutcome, TaskMachine, from_instance

ROBOT = (0.0, 0.0, 0.0)


def body():
    import eqa.robot

    return eqa.robot


def _machine(**kw: object) -> TaskMachine:
    return TaskMachine("pick_place", "mug", "table", "counter", **kw)  # type: ignore[arg-type]


# ---- B4: F0 of Eq. 9 never inverts the frontier ranking --------------------------------------------------------
def test_f0_with_worthless_stored_candidates_keeps_the_value_maps_order() -> None:
    # one earlier frontier at (0, 0) stored with F0(f') = 0.5; one stored candidate, S0 = 0.4, IG0 = 0, 5 m away:
    # V0 = 0.4 * 0 - 0.001 * 5 = -0.005 -> the ratio -0.01 would be F0; the reading keeps F0 = 1
    chosen = [ChosenFrontier(0.0, 0.0, 0.5)]
    stored = [StoredCandidate(7, 0.4, 0.0, 3.0, 4.0)]
    assert helios.f0_association(chosen, stored, 0.001) == 1.0
    mem = SearchMemory(stored={7: stored[0]}, chosen=list(chosen))
    fr = [FrontierOption(0, 1.0, 0.0, 0.1), FrontierOption(1, -1.0, 0.0, 0.9)]  # same distance, F 0.1 and 0.9
    ranked = helios.values((0.0, 0.0), fr, [], mem, 0.001)
    assert [c.ref for c in ranked] == [1, 0]
    assert ranked[0].value == pytest.approx(0.9 * 1.0 - 0.001)


def test_f0_averages_only_positive_associations_over_all_previous_frontiers() -> None:
    # two earlier frontiers: (0, 0) with F0 0.5 and (10, 0) with F0 0.25; a candidate S0 0.5, IG0 2 at (0, 0):
    # V0(f'1) = 1 - 0 = 1 -> ratio 2; V0(f'2) = 1 - 0.001 * 10 = 0.99 -> ratio 3.96; F0 = (2 + 3.96) / 2
    chosen = [ChosenFrontier(0.0, 0.0, 0.5), ChosenFrontier(10.0, 0.0, 0.25)]
    stored = [StoredCandidate(1, 0.5, 2.0, 0.0, 0.0)]
    assert helios.f0_association(chosen, stored, 0.001) == pytest.approx((2.0 + 3.96) / 2)
    # a third earlier frontier with a non-positive V0 (a worthless candidate near it is the best) adds no term
    stored.append(StoredCandidate(2, 0.0, 0.0, 1000.0, 0.0))
    assert helios.f0_association(chosen, stored, 0.001) == pytest.approx((2.0 + 3.96) / 2)


# ---- B2 (planner side): no gaze point -> IG unknown, not 0 -------------------------------------------------------
class _Inst:
    def __init__(self, gaze: list[object], ig: float = 0.0) -> None:
        self.instance_id, self.cls, self.S, self.U, self.psi = 3, "table", 0.8, 0.1, 0.7
        self.scores = {"table": (0.8, 0.1, 0.7)}
        self.centre, self.extent, self.ig, self.gaze = (1.0, 2.0, 0.4), (0.8, 0.6, 0.7), ig, gaze


def test_an_instance_without_gaze_points_is_not_stored_with_ig_zero() -> None:
    o = from_instance(_Inst([]))
    assert math.isnan(o.ig) and o.half == pytest.approx((0.4, 0.3))
    mem = SearchMemory()
    fr = [FrontierOption(0, 5.0, 0.0, 0.5)]
    helios.choose((0.0, 0.0), fr, [CandidateObservation(3, o.scores["table"][0], o.ig, o.x, o.y)], mem, 0.001, 0.3)
    assert mem.stored == {}  # its IG0 is stored once it has gaze points (a pose set P), not as 0 now


# ---- B3: looks used up on one candidate -> the next one is looked at --------------------------------------------
def _mug(iid: int, x: float, psi_prime: float) -> SeenObject:
    gaze = tuple(Gaze(x + 0.5 * k, 1.0, 0.0, psi_prime=psi_prime - 0.01 * k) for k in range(5))
    return SeenObject(iid, "mug", {"mug": (0.45, 0.1, 0.35)}, x, 2.0, 1.0, gaze)


def test_a_candidate_with_its_looks_used_up_gives_way_to_the_next() -> None:
    m = _machine()
    a, b = _mug(1, 0.0, 0.6), _mug(2, 10.0, 0.55)  # a has the higher Psi': looked at first
    fr = [FrontierOption(0, -5.0, 0.0, 0.5)]
    robot = ROBOT
    for _ in range(m.th.max_looks):
        act = m.step(robot, fr, [a, b])
        assert (act.kind, act.phase, act.ref) == ("move", "looking", 1)
        robot = (act.pose[0], act.pose[1], 0.0)  # standing at it: the frame there was the look
    act = m.step(robot, fr, [a, b])
    assert (act.kind, act.phase, act.ref) == ("move", "looking", 2)


def test_an_unreachable_gaze_point_of_a_look_costs_that_point_not_the_instance() -> None:
    m = _machine()
    a = _mug(1, 0.0, 0.6)
    act = m.step(ROBOT, [], [a])
    m.unreachable(1, act)
    nxt = m.step(ROBOT, [], [a])
    assert (nxt.kind, nxt.ref) == ("move", 1) and nxt.pose[:2] != act.pose[:2]


# ---- B8: no frontier left but candidates known -> act on the best ------------------------------------------------
def test_holding_with_no_frontier_places_on_the_best_known_goal_candidate() -> None:
    m = _machine()
    m.holding = True
    weak = SeenObject(30, "counter", {"counter": (0.35, 0.2, 0.15)}, -3.0, 0.0, 1.0, (Gaze(-2.0, 0.0, 3.14),))
    weaker = SeenObject(31, "counter", {"counter": (0.32, 0.2, 0.12)}, 3.0, 0.0, 1.0, ())
    act = m.step(ROBOT, [], [weaker, weak])
    assert (act.kind, act.ref) == ("place", 30)


def test_searching_with_nothing_left_picks_the_best_known_object_candidate() -> None:
    m = _machine()
    mug = SeenObject(20, "mug", {"mug": (0.3, 0.2, 0.1)}, 2.0, 0.0, 1.0, ())
    act = m.step(ROBOT, [], [mug])
    assert (act.kind, act.ref) == ("pick", 20)


# ---- trusting: single-frame detections, kept until the skill is tried --------------------------------------------
def test_the_trusting_agent_keeps_going_to_a_detection_gone_from_the_next_frame() -> None:
    t = _machine(ablation="trusting")
    mug = SeenObject(20, "mug", {"mug": (0.2, 0.2, 0.0)}, 2.0, 0.0, 1.0, ())
    fr = [FrontierOption(0, 5.0, 0.0, 0.5)]
    first = t.step(ROBOT, fr, [mug])
    assert first.kind == "pick"
    again = t.step((1.0, 0.0, 0.0), fr, [])  # the next frame shows no detection
    assert (again.kind, again.ref, again.pose) == ("pick", 20, first.pose)
    after = t.step((1.0, 0.0, 0.0), fr, [], SkillOutcome("pick", False, 20, "no target object in frame"))
    assert after.kind == "frontier"


# ---- B5 / B6: one collision model, skill poses within reach --------------------------------------------------------
def _room(table: bool = True) -> tuple[GridSpec, np.ndarray, np.ndarray]:
    """A 6 m x 6 m free room at 0.05 m cells, walls around it; a 1 m x 1 m table in the middle."""
    g = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.05, rows=120, cols=120)
    free = np.zeros((120, 120), bool)
    free[2:-2, 2:-2] = True
    occ = ~free
    if table:
        occ[50:70, 50:70] = True  # x, y in [2.5, 3.5]
        free[50:70, 50:70] = False
    return g, free, occ


def test_a_skill_pose_is_within_reach_of_the_footprint_and_clear_of_the_table() -> None:
    g, free, occ = _room()
    near = (3.0, 3.0, 0.1, 0.1)  # a mug at the table's centre: its box 0.4 m inside the table's edge
    # the machine's preferred pose (0.6 m from the centre) lies on the table: the nearest free cell within the
    # arrival tolerance would be ~0.5 m from the mug's box, but any pose must keep the mapped clearance
    ps = ts.plan_to_pose(g, free, occ, Pose2D(x=1.0, y=3.0, yaw=0.0), (2.4, 3.0, 0.0), near=near)
    assert ps.plan is not None and ps.arrived
    x, y = ps.plan.pose.x, ps.plan.pose.y
    box = math.hypot(max(abs(x - 3.0) - 0.1, 0.0), max(abs(y - 3.0) - 0.1, 0.0))
    assert box <= ts.SKILL_REACH_M < body().REACH_M
    field = ts.clearance_field(g, occ)
    assert float(field[int(y / 0.05), int(x / 0.05)]) >= body().mapped_clearance_m() - 1e-9
    assert ps.plan.pose.yaw == pytest.approx(math.atan2(3.0 - y, 3.0 - x))


def test_a_path_is_cut_before_it_comes_within_the_collision_radius() -> None:
    g, _, occ = _room()
    field = ts.clearance_field(g, occ)
    # straight at the table (edge x = 2.5) from x = 1: cut where 0.2 m from the centre of the table's first cell
    # (x = 2.525) is reached, x = 2.325, which keeps the collision radius from the table's edge
    path, whole = ts.safe_prefix([(1.0, 3.0), (3.0, 3.0)], field, g)
    assert not whole and 2.25 <= path[-1][0] <= 2.5 - body().COLLISION_RADIUS_M
    # a robot already 0.1 m from the wall may move away from it
    path, whole = ts.safe_prefix([(0.2, 3.0), (1.0, 3.0)], field, g)
    assert whole


def test_task_step_tries_every_frontier_before_giving_up() -> None:
    from eqa.messages import Frontier

    g, free, occ = _room(table=False)
    free[2:-2, 60:62] = False  # a wall across the room at x = 3.0 .. 3.1: the east half cannot be reached
    occ[2:-2, 60:62] = True
    east = [Frontier(x=4.0 + 0.1 * k, y=1.0 + 0.4 * k, nx=1.0, ny=0.0, size=5, sv=0.9) for k in range(10)]
    west = [Frontier(x=1.0, y=3.0, nx=-1.0, ny=0.0, size=5, sv=0.1)]
    st = ts.task_step(_machine(), g, free, occ, Pose2D(x=2.0, y=3.0, yaw=0.0), east + west, [], None, Memory(),
                      np.random.default_rng(0))
    assert st.plan.kind == "move", st.plan.reason
