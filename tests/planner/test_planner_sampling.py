"""Frontier sampling: Eq. A6 weights from the mapper's own functions, strategies, seeding, bad weights."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eqa.messages import Frontier, GridSpec, Pose2D
from services.mapper.frontiers import find_frontiers, weigh_frontiers
from services.mapper.semantic_map import write_values
from services.planner.sampling import choose, probabilities, step_rng
from services.planner.step import Memory, plan_step


def explored_room() -> tuple[GridSpec, np.ndarray, np.ndarray, np.ndarray]:
    """A 20 x 20 m hall, all seen free; the robot explored the middle 8 x 8 m only."""
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=200, cols=200)
    occ = np.zeros((200, 200), dtype=bool)
    occ[:3] = occ[-3:] = True
    occ[:, :3] = occ[:, -3:] = True
    free = ~occ
    explored = np.zeros_like(free)
    explored[60:140, 60:140] = True
    return grid, free, occ, explored


def frontiers_with_layer(layer: np.ndarray | None) -> list[Frontier]:
    grid, free, occ, explored = explored_room()
    frs = find_frontiers(free, explored, occ, (grid.origin_x, grid.origin_y), grid.resolution, (10.0, 10.0))
    return weigh_frontiers(frs, layer, (grid.origin_x, grid.origin_y), grid.resolution, 1.0, 1.0)


def picks(strategy: str, frs: list[Frontier], n: int) -> list[int]:
    grid, free, occ, _ = explored_room()
    out = []
    for seed in range(n):
        plan = plan_step(grid, free, occ, Pose2D(x=10.0, y=10.0), frs, strategy, Memory(), step_rng(seed, 0))
        assert plan.kind == "move", plan.reason
        out.append(int(plan.frontier_index))
    return out


def test_equal_semantic_values_sample_like_fbe() -> None:
    layer = np.full((200, 200), 2.0, dtype=np.float32)  # every region judged the same
    frs = frontiers_with_layer(layer)
    assert len(frs) >= 8
    assert len({round(f.weight, 9) for f in frs}) == 1
    sem = picks("semantic", frs, 60)
    fbe = picks("fbe", frs, 60)
    assert sem == fbe  # same probabilities, same seeded draws
    assert len(set(sem)) >= len(frs) // 2  # and it does spread over the frontiers


def test_one_high_value_region_draws_semantic_exploration_towards_it() -> None:
    _grid, *_ = explored_room()
    layer = np.zeros((200, 200), dtype=np.float32)
    low = math.exp(0.1 + 0.2)  # Eq. 3 with tau = 1: LSV 0.1, GSV 0.2
    high = math.exp(0.9 + 0.9)
    pts = [(x, y) for x in np.arange(2.0, 19.0, 2.0) for y in np.arange(2.0, 19.0, 2.0)]
    write_values(layer, (0.0, 0.0), 0.1, pts, [low] * len(pts), sigma=1.0)
    write_values(layer, (0.0, 0.0), 0.1, [(16.0, 10.0)], [high], sigma=1.5)  # east of the explored room
    frs = frontiers_with_layer(layer)
    facing = {i for i, f in enumerate(frs) if f.nx > 0.7 and f.x > 13.0}
    assert facing and len(facing) < len(frs) / 2
    n = 120
    sem = picks("semantic", frs, n)
    fbe = picks("fbe", frs, n)
    sem_share = sum(i in facing for i in sem) / n
    fbe_share = sum(i in facing for i in fbe) / n
    print(f"share of picks facing the valuable region: semantic {sem_share:.2f}, fbe {fbe_share:.2f}")
    assert sem_share >= 0.6, sem_share
    assert fbe_share <= 0.45, fbe_share
    assert sem_share >= 2 * fbe_share


def test_sampling_is_reproducible_per_seed_and_step() -> None:
    frs = frontiers_with_layer(None)
    a = picks("fbe", frs, 15)
    assert a == picks("fbe", frs, 15)
    w = [1.0] * 10
    cand = [True] * 10
    draws_step0 = [choose("fbe", w, cand, [0.0] * 10, step_rng(7, 0))[0] for _ in range(3)]
    assert len(set(draws_step0)) == 1
    by_step = {choose("fbe", w, cand, [0.0] * 10, step_rng(7, s))[0] for s in range(40)}
    assert len(by_step) > 3


def test_nearest_is_deterministic_and_geodesic() -> None:
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=60, cols=100)
    occ = np.zeros((60, 100), dtype=bool)
    occ[:2] = occ[-2:] = True
    occ[:, :2] = occ[:, -2:] = True
    occ[:50, 40:42] = True  # a wall with a passage only at the top
    free = ~occ
    behind_wall = Frontier(x=5.0, y=1.0, nx=0, ny=-1, size=5)  # 1.2 m away, 10+ m to walk
    open_side = Frontier(x=1.0, y=4.0, nx=-1, ny=0, size=5)  # 2.9 m away, straight
    pose = Pose2D(x=3.5, y=1.5)
    for seed in range(5):
        plan = plan_step(
            grid, free, occ, pose, [behind_wall, open_side], "nearest", Memory(), step_rng(seed, 0)
        )
        assert plan.frontier_index == 1 and plan.probabilities == [0.0, 1.0]


@pytest.mark.parametrize("strategy", ["semantic", "no_lsv", "no_gsv"])
def test_weighted_probabilities(strategy: str) -> None:
    p, note = probabilities(strategy, [1.0, 3.0, float("nan"), -1.0, 4.0], [True, True, True, True, False])
    assert np.allclose(p, [0.25, 0.75, 0.0, 0.0, 0.0])
    assert "2 frontier(s) with invalid weight" in note
    p, note = probabilities(strategy, [1e308, 1e308], [True, True])  # sum overflows
    assert np.allclose(p, [0.5, 0.5])
    p, _ = probabilities(strategy, [0.0, 0.0], [True, True])
    assert np.allclose(p, [0.5, 0.5])
    p, note = probabilities(strategy, [1.0], [False])
    assert not p.any() and "no candidate" in note


def test_fbe_ignores_weights() -> None:
    p, _ = probabilities("fbe", [1.0, 100.0, float("nan")], [True, True, True])
    assert np.allclose(p, [1 / 3] * 3)
