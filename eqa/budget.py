"""Step budgets: Explore-EQA's step limit of a question (appendix B) and what it leaves a question asked in a home
whose map already covers part of the house.

Appendix B sizes the budget to the house: ``T = int(3 sqrt(A))`` for a floor of ``A`` m2, the steps a robot needs
to see it once. A question asked in a known home (:mod:`services.mapper.home_shell`) starts from a map that already
covers ``A_e`` m2 of it; the same rule for the floor still to see gives ``3 sqrt(A - A_e)``, where ``A = (T / 3)^2``
is the floor the episode's own budget stands for. Re-looking at places already seen needs steps too (the view
memory keeps a bounded set of views, so the evidence of a new question may be in none of them): a warm budget is
never less than a share ``min_share`` of ``T``.

``A_e`` is the floor the home map has *observed* (:func:`services.mapper.home_memory.observed_floor`,
``EQA_HOME_WARM_AREA=observed``) or the floor it has *explored* (appendix B's narrow sub-field of view,
``explored``). ``T`` is what seeing the house once with the full camera takes, so the floor already seen is what
it no longer owes; the explored rule saturates below the seen floor (generated houses explored for ``T`` steps:
0.66-0.73 of the floor area explored, 0.67-0.86 observed inside the house; docs/homes.md) and so still grants
steps for floor the robot has seen. A house larger than its budget stands for
(``A`` below the true floor) reaches ``A_e >= A`` before it is all seen: the budget is then ``min_share`` of ``T``.
"""

from __future__ import annotations

import math

STEPS_PER_SQRT_M2 = 3.0  # a question, appendix B: T = int(3 sqrt(floor area))
TASK_STEPS_PER_SQRT_M2 = 6.0  # a HELIOS task (search, pick, search for the goal): the task benchmark's budget


def steps_for(area_m2: float, per_sqrt_m2: float = STEPS_PER_SQRT_M2) -> int:
    """A budget of ``int(per_sqrt_m2 * sqrt(area))`` steps, at least 1."""
    return max(1, int(per_sqrt_m2 * math.sqrt(max(area_m2, 0.0))))


def max_steps_for(area_m2: float) -> int:
    """Step limit of a question ``T = int(3 * sqrt(area))`` (Explore-EQA appendix B)."""
    return steps_for(area_m2, STEPS_PER_SQRT_M2)


def task_steps_for(area_m2: float) -> int:
    """Step limit of a task, ``int(6 * sqrt(area))``."""
    return steps_for(area_m2, TASK_STEPS_PER_SQRT_M2)


def area_for(max_steps: int) -> float:
    """The floor area (m2) whose appendix-B budget is ``max_steps``: ``(T / 3)^2``."""
    return (max(int(max_steps), 0) / STEPS_PER_SQRT_M2) ** 2


def warm_step_limit(max_steps: int, covered_m2: float, min_share: float) -> int:
    """The step limit of a question in a home whose map covers ``covered_m2`` of the floor: appendix B's
    budget for the floor left, ``int(3 sqrt(max(0, A - A_e)))`` with ``A`` = :func:`area_for` ``(max_steps)``, at
    least ``ceil(min_share * max_steps)`` (and 1), never more than ``max_steps``. ``min_share >= 1``: ``max_steps``."""
    if not math.isfinite(covered_m2) or not math.isfinite(min_share):
        raise ValueError("covered area and share must be finite")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, not {max_steps}")
    if min_share >= 1.0:
        return int(max_steps)
    left = max(0.0, area_for(max_steps) - max(covered_m2, 0.0))
    floor = max(1, math.ceil(max(min_share, 0.0) * max_steps - 1e-9))
    return int(min(max_steps, max(floor, int(STEPS_PER_SQRT_M2 * math.sqrt(left) + 1e-9))))
