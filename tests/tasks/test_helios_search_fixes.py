"""HELIOS task search and skills: one arrival tolerance, candidates kept after an unplannable pose, nothing ended
while something can be reopened, Eq. 9's F' once per frontier set out for, picks planned to the object itself, no
last-resort pick under a pick limit (services/planner/task_fsm.py, task_step.py, helios.py)."""

from __future__ import annotations

import math

import numpy as np

from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner import task_fsm
from services.planner import task_step as ts
from services.planner.step import Memory, full_turn
from services.planner.task_fsm import Gaze, SeenObject, TaskMachine

ROBOT = (0.0, 0.0, 0.0)


def _machine(**kw: object) -> TaskMachine:
    return TaskMachine("pick_place", "mug", "table", "counter", **kw)  # type: ignore[arg-type]


def _room() -> tuple[GridSpec, np.ndarray, np.ndarray]:
    """A 10 m x 10 m free room at 0.05 m cells with walls around it."""
    g = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.05, rows=200, cols=200)
    free = np.zeros((200, 200), bool)
    free[2:-2, 2:-2] = True
    return g, free, ~free


def test_a_gaze_point_the_planner_calls_reached_is_not_asked_for_again() -> None:
    """The planner arrives within ARRIVE_TOLERANCE_M of a gaze point; the machine must count the same distance
    as arrived, or it asks for the look it has had at every step (a run stood 73 of 77 steps)."""
    assert ts.ARRIVE_TOLERANCE_M is task_fsm.ARRIVE_TOLERANCE_M
    g0 = Gaze(0.4, 0.0, 0.0, psi_prime=0.6)  # 0.4 m away: reached for the planner
    g1 = Gaze(3.0, 0.0, 0.0, psi_prime=0.55)
    mug = SeenObject(1, "mug", {"mug": (0.45, 0.1, 0.35)}, 1.5, 1.0, 1.0, (g0, g1))
    act = _machine().step(ROBOT, [], [mug])
    assert (act.kind, act.phase, act.ref) == ("move", "looking", 1)
    assert act.pose is not None and act.pose[:2] == (3.0, 0.0)


def test_with_nothing_left_the_looks_reopen_instead_of_a_last_resort_pick_under_a_limit() -> None:
    """No frontier, the only candidate's looks used up, one pick allowed: looking again can still raise Psi above
    tau_g, a pick below it would likely spend the only pick and end the task."""
    m = _machine(pick_limit=1)
    gaze = tuple(Gaze(0.5 * k + 1.0, 1.0, 0.0, psi_prime=0.6 - 0.01 * k) for k in range(5))
    mug = SeenObject(1, "mug", {"mug": (0.45, 0.1, 0.35)}, 2.0, 2.0, 1.0, gaze)
    m.looked[1] = [(g.x, g.y) for g in gaze[:m.th.max_looks]]
    act = m.step(ROBOT, [], [mug])
    assert (act.kind, act.phase, act.ref) == ("move", "looking", 1)
    assert not m.finished and m.budget.attempts == 0


def test_no_last_resort_pick_under_a_limit_and_the_episode_goes_on() -> None:
    m = _machine(pick_limit=1)
    mug = SeenObject(20, "mug", {"mug": (0.3, 0.2, 0.1)}, 2.0, 0.0, 1.0, ())  # no gaze point, nothing to reopen
    act = m.step(ROBOT, [], [mug])
    assert act.kind == "done" and "nothing left" in act.reason  # no pick of a Psi 0.1 candidate
    unlimited = _machine()
    assert unlimited.step(ROBOT, [], [mug]).kind == "pick"  # without a limit a failed pick costs nothing


def test_frontiers_gone_to_before_are_options_again_when_no_other_is_left() -> None:
    g, free, occ = _room()
    fr = [Frontier(x=8.0, y=5.0, nx=1.0, ny=0.0, size=5, sv=0.5)]
    mem = Memory()
    mem.visited = [(8.0, 5.0)]
    st = ts.task_step(_machine(), g, free, occ, Pose2D(x=2.0, y=5.0, yaw=0.0), fr, [], None, mem,
                      np.random.default_rng(0))
    assert st.plan.kind == "move" and st.phase == "searching", st.plan.reason
    assert "all are options again" in st.plan.reason


def test_f_prime_grows_once_per_frontier_set_out_for() -> None:
    """Eq. 9's F' holds the frontiers chosen before; a frontier kept while the robot is on its way (several
    planner steps) is one choice, not one per step."""
    g, free, occ = _room()
    fr = [Frontier(x=9.0, y=5.0, nx=1.0, ny=0.0, size=5, sv=0.5)]  # 8 m away: several steps
    m = _machine()
    pose, mem = Pose2D(x=1.0, y=5.0, yaw=0.0), Memory()
    for _ in range(3):
        st = ts.task_step(m, g, free, occ, pose, fr, [], None, mem, np.random.default_rng(0))
        assert st.plan.kind == "move" and st.plan.pose is not None
        pose, mem = st.plan.pose, st.memory
    assert len(m.memory.chosen) == 1 and m.memory.chosen[0].F0 == 0.5


def test_a_pick_is_planned_within_reach_of_the_object_not_of_its_gaussians_footprint() -> None:
    """A target whose Gaussians spread 0.6 m around its centre: within reach of that footprint the robot may be
    1 m from the object; the pick is planned to reach the object's centre region instead."""
    g, free, occ = _room()
    mug = SeenObject(7, "mug", {"mug": (0.9, 0.05, 0.85)}, 5.0, 5.0, 1.0, (Gaze(5.0, 3.4, math.pi / 2),),
                     (0.6, 0.6))
    m = _machine()
    robot = Pose2D(x=5.0, y=4.0, yaw=math.pi / 2)  # 1.0 m from the centre, 0.4 m from the footprint
    st = ts.task_step(m, g, free, occ, robot, [], [mug], None, Memory(), np.random.default_rng(0))
    assert (st.phase, st.skill) == ("picking", "pick"), st.plan.reason
    p = st.plan.pose
    assert p is not None and math.hypot(p.x - 5.0, p.y - 5.0) < 0.7  # moved in before the pick, not from 1.0 m
    assert math.hypot(p.x - 5.0, p.y - 5.0) <= ts.SKILL_REACH_M + task_fsm.PICKABLE_HALF_M * math.sqrt(2)


def test_with_cut_clearance_a_task_path_is_planned_at_the_clearance_it_is_cut_at() -> None:
    """Planned at a level below the mapped clearance (0.2 m here) and cut at the mapped clearance, the robot
    creeps along the cut route step after step; planned at the levels that keep the mapped clearance, it is not
    cut."""
    from eqa import robot as body
    from services.planner.task_fsm import Thresholds

    assert ts.cut_clearances((0.3, 0.2, 0.1), 0.25) == (0.3, 0.25)
    g, free, occ = _room()
    occ[:, 100:104] = True  # a wall at x = 5.0 .. 5.2 with a 0.5 m gap at y 4.0 .. 4.5 and a 0.7 m one at y 8 .. 8.7
    occ[80:90, 100:104] = False
    occ[160:174, 100:104] = False
    free = ~occ
    fr = [Frontier(x=7.0, y=4.25, nx=1.0, ny=0.0, size=5, sv=0.5)]
    m = _machine(th=Thresholds(path_clearance="cut"))
    st = ts.task_step(m, g, free, occ, Pose2D(x=3.0, y=4.25, yaw=0.0), fr, [], None, Memory(),
                      np.random.default_rng(0))
    assert st.plan.kind == "move" and st.plan.clearance_m >= body.mapped_clearance_m() - 1e-9, st.plan.reason


def test_a_wedged_robot_backs_out_instead_of_turning_in_place() -> None:
    """0.1 m from a wall, with the only frontier cut off: no path keeps the mapped clearance from where it stands,
    and turning in place would repeat to the end of the episode; it backs out to a point that keeps it."""
    from eqa import robot as body

    g, free, occ = _room()
    occ[:, 140:144] = True  # a closed wall at x = 7.0 .. 7.2: the frontier behind it cannot be reached
    free = ~occ
    fr = [Frontier(x=8.5, y=5.0, nx=1.0, ny=0.0, size=5, sv=0.5)]
    pose = Pose2D(x=1.0, y=0.22, yaw=0.0)  # 0.12 m from the wall cells' centres
    st = ts.task_step(_machine(), g, free, occ, pose, fr, [], None, Memory(), np.random.default_rng(0))
    assert st.plan.kind == "move" and "backing out" in st.plan.reason, st.plan.reason
    p = st.plan.pose
    field = ts.clearance_field(g, occ)
    assert p is not None and float(field[int(p.y / 0.05), int(p.x / 0.05)]) >= body.mapped_clearance_m()
    assert math.hypot(p.x - pose.x, p.y - pose.y) <= ts.ESCAPE_RADIUS_M


def test_with_nothing_left_and_no_goal_believed_the_object_goes_on_the_best_scored_instance() -> None:
    """No frontier, no instance believed to be the goal receptacle, steps left: ending fails for certain; the
    instance of highest goal Psi (the layer believes it a table) may be the counter."""
    m = _machine()
    m.holding = True
    table = SeenObject(4, "table", {"counter": (0.35, 0.15, 0.20), "table": (0.4, 0.15, 0.25)}, 2.0, 0.0, 1.0,
                       (Gaze(2.5, 0.0, 0.0, psi_prime=0.3),))
    other = SeenObject(5, "table", {"counter": (0.20, 0.15, 0.05)}, 4.0, 0.0, 1.0, (Gaze(4.5, 0.0, 0.0),))
    act = m.step(ROBOT, [], [table, other])
    assert (act.kind, act.ref) == ("place", 4), act
    assert "no instance believed to be a counter" in act.reason


def test_with_nothing_mapped_left_the_robot_looks_around_a_full_circle_before_it_ends() -> None:
    """No frontier and no candidate (a doorway the map has not got yet): ending the episode fails for certain,
    new frames from here may open a frontier. A full circle of turns in place, then the end with steps left."""
    g, free, occ = _room()
    m, mem = _machine(pick_limit=1), Memory()
    pose = Pose2D(x=5.0, y=5.0, yaw=0.0)
    full = full_turn(ts.PlannerParams())
    for k in range(full):
        st = ts.task_step(m, g, free, occ, pose, [], [], None, mem, np.random.default_rng(k))
        assert st.plan.kind == "turn" and st.phase == "searching", st.plan.reason
        assert "nothing left to search" in st.plan.reason and m.finished is None
        mem, pose = st.memory, st.plan.pose
    st = ts.task_step(m, g, free, occ, pose, [], [], None, mem, np.random.default_rng(full))
    assert st.plan.kind == "done" and st.phase == "finished"
    assert "even after turning in place a full circle" in st.plan.reason


def test_the_last_resort_on_an_instance_not_believed_waits_for_the_look_around() -> None:
    """Holding the object, no frontier, the only instance scored for the goal class believed to be another class:
    the robot first turns a full circle where it stands (new frames may open a frontier; a place on it ends the
    task), then places on it. With no steps left for the circle it places at once."""
    g, free, occ = _room()
    table = SeenObject(4, "table", {"counter": (0.35, 0.15, 0.20), "table": (0.4, 0.15, 0.25)}, 5.8, 5.0, 1.0,
                       (Gaze(6.5, 5.0, math.pi, psi_prime=0.3),))
    full = full_turn(ts.PlannerParams())
    m, mem = _machine(), Memory()
    m.holding = True
    pose = Pose2D(x=5.0, y=5.0, yaw=0.0)
    for k in range(full):
        st = ts.task_step(m, g, free, occ, pose, [], [table], None, mem, np.random.default_rng(k))
        assert st.plan.kind == "turn", st.plan.reason
        mem, pose = st.memory, st.plan.pose
    st = ts.task_step(m, g, free, occ, pose, [], [table], None, mem, np.random.default_rng(full))
    assert st.target == 4 and st.phase == "placing", st.plan.reason
    assert "no instance believed to be a counter" in st.plan.reason
    late = _machine(max_steps=10)
    late.holding = True
    st = ts.task_step(late, g, free, occ, Pose2D(x=5.0, y=5.0, yaw=0.0), [], [table], None, Memory(),
                      np.random.default_rng(0), step=5)  # 4 goals left: no full circle and a place
    assert st.target == 4 and st.phase == "placing", st.plan.reason
