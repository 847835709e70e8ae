"""A task step on the 2D map (services/planner/task_step.py): paths to gaze poses, skills only on arrival."""

from __future__ import annotations

import math

import numpy as np

from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner.step import Memory, PlannerParams
from services.planner.task_fsm import MAX_UNREACHABLE_STEPS, Gaze, SeenObject, TaskMachine, Thresholds
from services.planner.task_step import plan_to_pose, task_step, travel_distances

GRID = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=100, cols=100)


def _room() -> tuple[np.ndarray, np.ndarray]:
    """A 10 x 10 m free room with a wall at x = 5 m (y < 8 m): the way round is through the gap at the top."""
    occ = np.zeros((100, 100), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    occ[:80, 50] = True
    return ~occ, occ


def test_plan_to_pose_goes_round_the_wall_in_steps_and_arrives() -> None:
    free, occ = _room()
    robot = Pose2D(x=2.0, y=2.0, yaw=0.0)
    target = (8.0, 2.0, math.pi)
    arrived, steps = False, 0
    while not arrived and steps < 20:
        ps = plan_to_pose(GRID, free, occ, robot, target)
        assert ps.plan is not None and ps.plan.pose is not None
        for x, y in ps.plan.path:  # never through the wall
            assert not (4.9 <= x <= 5.2 and y < 8.0)
        robot, arrived, steps = ps.plan.pose, ps.arrived, steps + 1
    assert arrived and steps >= 5  # > 3 m per step: the detour is ~ 16 m
    assert (robot.x, robot.y) == (8.0, 2.0) and abs(robot.yaw) == math.pi
    blocked = occ.copy()
    blocked[:, 50] = True  # no way round
    assert plan_to_pose(GRID, ~blocked, blocked, Pose2D(x=2.0, y=2.0), target).plan is None


def test_task_step_asks_for_the_skill_only_on_arrival() -> None:
    free, occ = _room()
    mug = SeenObject(20, "mug", {"mug": (0.7, 0.1, 0.6)}, 3.0, 5.0, 1.0, (Gaze(3.0, 4.2, math.pi / 2),))
    m = TaskMachine("pick_place", "mug", "table", "counter")
    far = task_step(m, GRID, free, occ, Pose2D(x=1.0, y=0.8), [], [mug], None, Memory(), np.random.default_rng(0))
    assert (far.skill, far.phase, far.target) == ("move", "picking", 20)  # 3.9 m away: a move first
    pose = far.plan.pose
    near = task_step(m, GRID, free, occ, pose, [], [mug], None, Memory(), np.random.default_rng(0))
    assert (near.skill, near.target) == ("pick", 20)
    # the skill is called 0.6 m from the object's centre (3, 5) on the line to its gaze point (3, 4.2): within the
    # oracle pick's 0.9 m reach after the planner's arrival tolerance (task_fsm.SKILL_APPROACH_M)
    assert (near.plan.pose.x, near.plan.pose.y) == (3.0, 4.4)


def test_an_unreachable_skill_pose_falls_back_to_a_frontier_and_rules_out_only_after_repeated_steps() -> None:
    _, occ = _room()
    behind = occ.copy()
    behind[:, 50] = True
    mug = SeenObject(20, "mug", {"mug": (0.7, 0.1, 0.6)}, 8.0, 5.0, 1.0, (Gaze(8.0, 4.2, 0.0),))
    frontier = Frontier(x=2.0, y=7.0, nx=0.0, ny=1.0, size=5, sv=0.5)
    m = TaskMachine("pick_place", "mug", "table", "counter")
    st = task_step(m, GRID, ~behind, behind, Pose2D(x=1.0, y=1.0), [frontier], [mug], None, Memory(),
                   np.random.default_rng(0), PlannerParams())
    assert st.phase == "searching" and st.plan.kind == "move"
    assert 20 not in m.fails and m.unreachable_steps == {20: 1}  # one step on a half-built map drops nothing
    for k in range(2, MAX_UNREACHABLE_STEPS + 1):
        task_step(m, GRID, ~behind, behind, Pose2D(x=1.0, y=1.0), [frontier], [mug], None, Memory(),
                  np.random.default_rng(0), PlannerParams())
        assert m.unreachable_steps == {20: k}
    assert 20 in m._ruled_out()


def test_the_frontier_on_the_way_stays_the_choice_until_reached() -> None:
    """Eq. 10 read as a choice that holds until the robot gets there (services/planner/helios.py choose): the
    frontier values change while the robot moves, and a robot that re-chose the highest value every step went back
    and forth across a room (tuning seed 11). Here the robot heads for frontier A (6 m away, more than one 3 m
    step); on the next step frontier B's value has risen above A's: the robot keeps going to A, and only after
    arriving there does it choose B."""
    free = np.ones((100, 100), bool)
    occ = np.zeros((100, 100), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    free &= ~occ
    a = Frontier(x=8.0, y=2.0, nx=1.0, ny=0.0, size=5, sv=0.6)
    b = Frontier(x=2.0, y=8.0, nx=0.0, ny=1.0, size=5, sv=0.5)
    m = TaskMachine("pick_place", "mug", "table", "counter", ablation="trusting")
    rng = np.random.default_rng(0)
    first = task_step(m, GRID, free, occ, Pose2D(x=2.0, y=2.0), [a, b], [], None, Memory(), rng)
    assert first.plan.frontier is not None and first.plan.frontier.x == 8.0  # A: the highest value
    assert first.memory.target is not None  # on the way, not there yet
    b_up = b.model_copy(update={"sv": 0.9})
    second = task_step(m, GRID, free, occ, first.plan.pose, [a, b_up], [], None, first.memory, rng)
    assert second.plan.frontier is not None and second.plan.frontier.x == 8.0, second.plan.reason
    pose, mem = second.plan.pose, second.memory
    for _ in range(3):
        if mem.target is None:
            break
        st = task_step(m, GRID, free, occ, pose, [a, b_up], [], None, mem, rng)
        pose, mem = st.plan.pose, st.memory
    assert mem.target is None and math.hypot(pose.x - 8.0, pose.y - 2.0) < 0.6  # A reached
    after = task_step(m, GRID, free, occ, pose, [b_up], [], None, mem, rng)
    assert after.plan.frontier is not None and after.plan.frontier.y == 8.0  # then B



def test_path_distance_ranks_a_frontier_behind_a_wall_by_the_way_round() -> None:
    """Eq. 10's dist with EQA_HELIOS_DISTANCE=path: frontier A is 2 m from the robot through the wall at x = 5 m
    but about 15 m the way round (the gap at the top); B is 5 m away in the open with a lower value. The straight
    line sends the robot to A, the path to B -- for every agent, since the trusting agent and the goal-receptacle
    search rank frontiers by the same values."""
    free, occ = _room()
    robot = Pose2D(x=4.0, y=2.0)
    travel = travel_distances(GRID, free, occ, robot, PlannerParams())
    assert 13.0 < travel(6.0, 2.0) < 17.0  # up to y = 8, over, and down again
    assert abs(travel(1.0, 6.0) - 5.0) < 0.6  # the straight line is free
    a = Frontier(x=6.0, y=2.0, nx=1.0, ny=0.0, size=5, sv=0.6)
    b = Frontier(x=1.0, y=6.0, nx=-1.0, ny=0.0, size=5, sv=0.5)
    for ablation in ("trusting", "helios"):
        for distance, want in (("straight", 6.0), ("path", 1.0)):
            th = Thresholds(alpha_d=0.05, value_scale="best", distance=distance)
            m = TaskMachine("pick_place", "mug", "table", "counter", ablation=ablation, th=th)
            st = task_step(m, GRID, free, occ, robot, [a, b], [], None, Memory(), np.random.default_rng(0))
            assert st.plan.frontier is not None and st.plan.frontier.x == want, (ablation, distance, st.plan.reason)


def test_a_refused_skill_pose_is_not_planned_again() -> None:
    """The simulator refuses a goal pose within its robot radius of the true scene; the refused position is
    remembered (``Memory.refused``) and the next attempt of a skill or gaze pose keeps away from it, as frontier
    steps do. Planned again at the same block, a refused skill pose came back at every attempt and every step
    (tuning seed 11: the trusting agent turned in place for 130 steps next to its detection). Here the
    simulator refuses every pose within 0.2 m of (3.0, 4.4), the preferred pose of the pick."""
    from services.planner.refusals import MAX_REFUSALS, Refusals

    free, occ = _room()
    mug = SeenObject(20, "mug", {"mug": (0.7, 0.1, 0.6)}, 3.0, 5.0, 1.0, (Gaze(3.0, 4.2, math.pi / 2),))
    robot = Pose2D(x=3.0, y=3.0)
    m = TaskMachine("pick_place", "mug", "table", "counter", ablation="trusting")
    refusals = Refusals(0, robot, 0, Memory())
    before = m.to_json()
    for _ in range(MAX_REFUSALS + 1):
        machine = TaskMachine.from_json(before)
        st = task_step(machine, GRID, free, occ, robot, [], [mug], None, refusals.memory(), np.random.default_rng(0))
        p = st.plan.pose
        if math.hypot(p.x - 3.0, p.y - 4.4) > 0.2:
            break
        assert refusals.refuse(st.plan, "goal refused: in collision") is None, "refusals ran out on one pose"
    assert (st.skill, st.target, st.plan.kind) == ("pick", 20, "move"), st.plan.reason
    assert refusals.attempt == 1  # one refusal, then another pose within reach
    x, y = st.plan.pose.x, st.plan.pose.y
    assert math.hypot(x - 3.0, y - 4.4) > PlannerParams().refused_radius_m - 0.05
    assert math.hypot(max(abs(x - 3.0) - 0.1, 0.0), max(abs(y - 5.0) - 0.1, 0.0)) <= 0.7  # within reach


def test_a_kept_path_keeps_the_collision_radius_from_the_edge_of_a_mapped_cell() -> None:
    """The clearance is measured between cell centres of the mapper's grid (0.1 m cells, its voxel size): a
    mapped obstacle fills its cell up to half a cell beyond the centre and a path point lies up to half a cell
    from its own cell's centre. A path along x = 2.21 next to an occupied cell spanning x in [2.0, 2.1] lies in
    cells whose centres are 0.2 m from the obstacle's centre, 0.11 m from its edge: inside the collision radius,
    the path must be cut before it."""
    from eqa import robot as body
    from services.mapper.tsdf import VolumeConfig
    from services.planner.task_step import clearance_field, safe_prefix

    assert GRID.resolution == VolumeConfig().voxel_size  # the task map's cells (this test's grid)
    occ = np.zeros((100, 100), bool)
    occ[50, 20] = True  # the cell x in [2.0, 2.1], y in [5.0, 5.1]
    field = clearance_field(GRID, occ)
    path, whole = safe_prefix([(2.21, 3.0), (2.21, 7.0)], field, GRID)
    assert not whole
    for x, y in path:
        edge = math.hypot(max(abs(x - 2.05) - 0.05, 0.0), max(abs(y - 5.05) - 0.05, 0.0))
        assert edge >= body.COLLISION_RADIUS_M, (x, y, edge)
