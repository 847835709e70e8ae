"""Step budgets (eqa/budget.py): appendix B's T = int(3 sqrt(A)) and a warm question's budget for the floor its
home map left unexplored, against hand-computed values."""

from __future__ import annotations

import math

import pytest

from eqa.budget import area_for, max_steps_for, warm_step_limit


def test_appendix_b_budget_and_its_area() -> None:
    assert max_steps_for(100.0) == 30 and max_steps_for(336.0) == 54 and max_steps_for(0.0) == 1
    assert area_for(30) == pytest.approx(100.0) and area_for(55) == pytest.approx(336.111, abs=1e-3)
    # the area a budget stands for gives that budget back, for every budget (no float rounding down)
    assert all(warm_step_limit(t, 0.0, 0.0) == t for t in range(1, 400))


def test_warm_budget_is_appendix_b_for_the_floor_left_with_a_floor_share() -> None:
    # T = 55 stands for (55/3)^2 = 336.11 m2; 163.23 m2 explored leaves 172.88 m2: int(3 * 13.148) = 39
    assert warm_step_limit(55, 163.23, 0.3) == 39
    # 330 m2 explored leaves 6.11 m2: int(3 * 2.472) = 7, under the share: ceil(0.3 * 55) = 17
    assert warm_step_limit(55, 330.0, 0.3) == 17
    # more explored than the budget's area (walls and the outside of a house count as explored cells): the share
    assert warm_step_limit(55, 1000.0, 0.15) == math.ceil(0.15 * 55) == 9
    assert warm_step_limit(55, 1000.0, 0.0) == 1
    # share 1: the full budget whatever the map; never more than T
    assert warm_step_limit(55, 330.0, 1.0) == 55 and warm_step_limit(55, -5.0, 0.5) == 55
    with pytest.raises(ValueError):
        warm_step_limit(0, 1.0, 0.3)
    with pytest.raises(ValueError):
        warm_step_limit(55, math.nan, 0.3)
