"""Planner paths: never through occupied or unknown cells, clearance kept, at most 3 m per step, bad maps."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy import ndimage

from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner.paths import block_footprint, planning_grid
from services.planner.sampling import step_rng
from services.planner.step import Memory, PlannerParams, plan_step
from services.planner.synthetic import rooms_map


def clearance_field(free: np.ndarray, res: float) -> np.ndarray:
    """Ground truth: metres from each cell centre to the nearest non-free cell centre (outside = blocked)."""
    padded = np.pad(free, 1, constant_values=False)
    return ndimage.distance_transform_edt(padded)[1:-1, 1:-1] * res


def check_polyline(
    grid: GridSpec, free: np.ndarray, pts: list[tuple[float, float]], clearance: float
) -> None:
    clear = clearance_field(free, grid.resolution)
    for a, b in itertools.pairwise(pts):
        n = max(2, math.ceil(math.hypot(b[0] - a[0], b[1] - a[1]) / 0.005) + 1)
        t = np.linspace(0, 1, n)
        x = a[0] + (b[0] - a[0]) * t
        y = a[1] + (b[1] - a[1]) * t
        j = np.floor((x - grid.origin_x) / grid.resolution).astype(int)
        i = np.floor((y - grid.origin_y) / grid.resolution).astype(int)
        assert ((i >= 0) & (i < grid.rows) & (j >= 0) & (j < grid.cols)).all()
        assert free[i, j].all(), f"segment {a}->{b} crosses a non-free cell"
        worst = float(clear[i, j].min())
        assert worst >= clearance - 1e-9, f"segment {a}->{b} comes within {worst:.2f} m of a blocked cell"


def free_cells_with_clearance(grid: GridSpec, free: np.ndarray, c: float) -> np.ndarray:
    clear = clearance_field(free, grid.resolution)
    return np.argwhere(clear >= c + 0.05)


def cell_xy(grid: GridSpec, i: int, j: int) -> tuple[float, float]:
    return grid.origin_x + (j + 0.5) * grid.resolution, grid.origin_y + (i + 0.5) * grid.resolution


@pytest.mark.parametrize(("c", "k"), [(3.0, 2), (2.0, 2), (3.0, 1), (2.5, 3), (4.0, 2)])
def test_traversable_blocks_keep_the_clearance(c: float, k: int) -> None:
    """Every fine cell of a traversable block is free with clearance >= c; for c=3, k=2 the block test is
    exact (no block is rejected that a brute-force check would accept)."""
    rng = np.random.default_rng(int(c * 10 + k))
    grid, free, occ = rooms_map(rng, width_m=8, height_m=6, furniture=5)
    res = grid.resolution
    pg = planning_grid(grid, free, occ, clearance_m=c * res, coarse_m=k * res)
    clear = clearance_field(free, res)
    R, C = pg.traversable.shape
    exact_ok = np.zeros((R, C), dtype=bool)
    for bi in range(R):
        for bj in range(C):
            i0, j0 = pg.i0 + bi * k, pg.j0 + bj * k
            rows = range(i0, i0 + k)
            cols = range(j0, j0 + k)
            inside = all(0 <= i < grid.rows for i in rows) and all(0 <= j < grid.cols for j in cols)
            ok = inside and all(free[i, j] and clear[i, j] >= c * res - 1e-9 for i in rows for j in cols)
            exact_ok[bi, bj] = ok
            if pg.traversable[bi, bj]:
                assert ok, f"block {(bi, bj)} is traversable but a cell violates the clearance"
    if (c, k) == (3.0, 2):
        assert (pg.traversable == exact_ok).all()
    assert pg.traversable.sum() > 0.5 * exact_ok.sum()


def test_footprint_shapes() -> None:
    assert block_footprint(3, 2).shape == (3, 3)
    assert block_footprint(3, 1).shape == (5, 5) and block_footprint(3, 1).all()
    fp = block_footprint(4, 1)  # cells closer than 4: a disk, not a square
    assert fp.shape == (7, 7) and not fp[0, 0] and fp[0, 3]


@pytest.mark.parametrize("seed", range(6))
def test_paths_avoid_occupied_and_unknown_keep_clearance_and_3m(seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid, free, occ = rooms_map(rng, width_m=14, height_m=10, furniture=8)
    # carve an unknown region (neither free nor occupied) into the house
    ui, uj = int(rng.integers(20, 70)), int(rng.integers(20, 100))
    free[ui : ui + 25, uj : uj + 30] = False
    params = PlannerParams()
    starts = free_cells_with_clearance(grid, free, 0.3)
    n_moves = 0
    for trial in range(10):
        si, sj = starts[int(rng.integers(len(starts)))]
        sx, sy = cell_xy(grid, si, sj)
        fi, fj = starts[int(rng.integers(len(starts)))]
        fx, fy = cell_xy(grid, fi, fj)
        fr = [Frontier(x=fx, y=fy, nx=1.0, ny=0.0, size=5)]
        plan = plan_step(
            grid, free, occ, Pose2D(x=sx, y=sy), fr, "fbe", Memory(), step_rng(seed, trial), params
        )
        if plan.kind != "move":
            continue
        n_moves += 1
        assert plan.path[0] == (sx, sy)
        check_polyline(grid, free, plan.path, plan.clearance_m or 0.3)
        check_polyline(grid, free, plan.full_path, plan.clearance_m or 0.3)
        step_len = sum(
            math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(plan.path, plan.path[1:], strict=False)
        )
        assert step_len <= params.max_step_m + 1e-9
        assert math.hypot(plan.pose.x - sx, plan.pose.y - sy) <= params.max_step_m + 1e-9
        assert plan.path[-1] == (plan.pose.x, plan.pose.y)
    assert n_moves >= 3  # some pairs lie in parts that furniture or the unknown region cut off


def test_walks_through_a_door_and_commits_to_a_far_target_then_faces_the_normal() -> None:
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=60, cols=160)
    occ = np.zeros((60, 160), dtype=bool)
    occ[:2] = occ[-2:] = True
    occ[:, :2] = occ[:, -2:] = True
    occ[:, 79:81] = True
    occ[25:33, 79:81] = False  # a 0.8 m door
    free = ~occ
    target = Frontier(x=15.0, y=1.0, nx=0.0, ny=-1.0, size=8)
    pose = Pose2D(x=1.0, y=5.0, yaw=0.0)
    mem = Memory()
    seen_commit = False
    for step in range(10):
        # a second frontier near the robot's side keeps the sampling honest; the commitment must win
        frs = [target, Frontier(x=3.0, y=1.0, nx=0.0, ny=-1.0, size=8)]
        # no distance decay: this test is about the door and the commitment, not about preferring near ones
        no_decay = PlannerParams(distance_decay_m=None)
        plan = plan_step(grid, free, occ, pose, frs, "fbe", mem, step_rng(3, step), no_decay)
        assert plan.kind == "move", plan.reason
        check_polyline(grid, free, plan.path, 0.3)
        if "kept the committed target" in plan.reason:
            seen_commit = True
            assert plan.frontier == target
        mem, pose = plan.memory, plan.pose
        if plan.frontier == target and "arrives" in plan.reason:
            assert math.isclose(pose.yaw, -math.pi / 2, abs_tol=1e-6)
            assert math.hypot(pose.x - target.x, pose.y - target.y) < 1.0
            break
        if plan.frontier != target:  # it went to the near one first: then aim at the far one only
            frs = [target]
    else:
        pytest.fail("never arrived at the far frontier")
    assert seen_commit


def test_unreachable_frontier_is_not_a_candidate_and_robot_turns_then_stops() -> None:
    rng = np.random.default_rng(0)
    grid, free, occ = rooms_map(rng, width_m=6, height_m=5, room_m=10, furniture=0)
    occ[20:26, :] = True  # wall the house in two, no door
    free &= ~occ
    fr = [Frontier(x=3.0, y=4.0, nx=0.0, ny=1.0, size=5)]  # beyond the wall
    pose = Pose2D(x=3.0, y=1.0, yaw=0.0)
    mem = Memory()
    yaws = []
    for step in range(10):
        plan = plan_step(grid, free, occ, pose, fr, "semantic", mem, step_rng(0, step))
        if plan.kind == "done":
            assert "not reachable" in plan.reason or "reachable" in plan.reason
            assert "full circle" in plan.reason
            break
        assert plan.kind == "turn"
        assert (plan.pose.x, plan.pose.y) == (pose.x, pose.y)
        yaws.append(plan.pose.yaw)
        mem, pose = plan.memory, plan.pose
    else:
        pytest.fail("never gave up")
    assert len(yaws) == 6 and len({round(y, 6) for y in yaws}) == 6


def test_no_frontier_means_fully_explored() -> None:
    rng = np.random.default_rng(1)
    grid, free, occ = rooms_map(rng, width_m=6, height_m=5, furniture=0)
    mem = Memory(turns=6)
    plan = plan_step(grid, free, occ, Pose2D(x=2.0, y=2.0), [], "fbe", mem, step_rng(0, 0))
    assert plan.done and "fully explored" in plan.reason


def test_bad_maps_answer_with_a_reason() -> None:
    rng = np.random.default_rng(2)
    grid, free, occ = rooms_map(rng, width_m=6, height_m=5, furniture=0)
    fr = [Frontier(x=2.0, y=2.0, nx=1.0, ny=0.0, size=5)]
    # robot outside the map
    plan = plan_step(grid, free, occ, Pose2D(x=500.0, y=2.0), fr, "fbe", Memory(), step_rng(0, 0))
    assert plan.done and "outside the map" in plan.reason
    # layers that do not match the grid
    plan = plan_step(grid, free[:10], occ, Pose2D(x=2.0, y=2.0), fr, "fbe", Memory(), step_rng(0, 0))
    assert plan.done and "shape" in plan.reason
    # no free cell around the robot: look around, never wander
    nofree = np.zeros_like(free)
    plan = plan_step(grid, nofree, occ, Pose2D(x=2.0, y=2.0), fr, "fbe", Memory(), step_rng(0, 0))
    assert plan.kind == "turn" and "no free cell" in plan.reason
    assert (plan.pose.x, plan.pose.y) == (2.0, 2.0)
    plan = plan_step(grid, nofree, occ, Pose2D(x=2.0, y=2.0), fr, "fbe", Memory(turns=6), step_rng(0, 0))
    assert plan.done and "no free cell" in plan.reason
    # frontiers outside the map or with NaN coordinates are dropped, the good one is used
    bad = [
        Frontier(x=-40.0, y=2.0, nx=1.0, ny=0.0, size=5),
        Frontier(x=float("nan"), y=1.0, nx=1, ny=0, size=3),
    ]
    plan = plan_step(grid, free, occ, Pose2D(x=1.0, y=1.0), [*bad, *fr], "fbe", Memory(), step_rng(0, 0))
    assert plan.kind == "move" and plan.frontier_index == 2
    assert "outside the map" in plan.reason and "non-finite" in plan.reason
    plan = plan_step(grid, free, occ, Pose2D(x=1.0, y=1.0), bad, "fbe", Memory(), step_rng(0, 0))
    assert plan.kind == "turn" and "no usable frontier" in plan.reason


def test_nan_weights_do_not_break_sampling() -> None:
    rng = np.random.default_rng(3)
    grid, free, occ = rooms_map(rng, width_m=8, height_m=6, furniture=0)
    frs = [
        Frontier(x=1.0, y=1.0, nx=1, ny=0, size=5, weight=float("nan")),
        Frontier(x=6.0, y=4.0, nx=1, ny=0, size=5, weight=2.0),
    ]
    plan = plan_step(grid, free, occ, Pose2D(x=3.0, y=3.0), frs, "semantic", Memory(), step_rng(0, 0))
    assert plan.kind == "move" and plan.frontier_index == 1
    assert plan.probabilities == [0.0, 1.0] and "invalid weight" in plan.reason
    frs[1].weight = float("nan")
    plan = plan_step(grid, free, occ, Pose2D(x=3.0, y=3.0), frs, "semantic", Memory(), step_rng(0, 0))
    assert plan.kind == "move" and "sampled uniformly" in plan.reason
    assert sum(plan.probabilities) == pytest.approx(1.0) and min(plan.probabilities) > 0.3  # uniform x decay


def test_refused_places_are_avoided() -> None:
    rng = np.random.default_rng(4)
    grid, free, occ = rooms_map(rng, width_m=8, height_m=6, furniture=0)
    fr = [Frontier(x=6.0, y=1.0, nx=1, ny=0, size=5)]
    first = plan_step(grid, free, occ, Pose2D(x=1.0, y=1.0), fr, "fbe", Memory(), step_rng(0, 0))
    assert first.kind == "move"
    mem = Memory(refused=[(first.pose.x, first.pose.y)])
    again = plan_step(grid, free, occ, Pose2D(x=1.0, y=1.0), fr, "fbe", mem, step_rng(0, 0, 1))
    assert again.kind == "move"
    assert math.hypot(again.pose.x - first.pose.x, again.pose.y - first.pose.y) > 0.35
