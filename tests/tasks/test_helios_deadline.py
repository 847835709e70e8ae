"""The step budget in the task machine: with only the steps left to reach the best known candidate, the machine
acts on it (place while holding, stop in an object search, pick without a pick limit) instead of running out of
steps; never a pick under a pick limit; nothing changes with the deadline off or the budget unknown
(services/planner/task_fsm.py ``_deadline``, task_step.py)."""

from __future__ import annotations

import numpy as np

from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner import task_step as ts
from services.planner.helios import FrontierOption
from services.planner.step import Memory
from services.planner.task_fsm import Gaze, SeenObject, TaskMachine, Thresholds

ROBOT = (0.0, 0.0, 0.0)
COMMIT = Thresholds(deadline="commit")
FRONTIER = [FrontierOption(0, -4.0, 0.0, 0.9)]


def _counter(iid: int = 7, x: float = 3.0, psi: float = 0.35) -> SeenObject:
    """A goal-receptacle candidate below tau_b 0.5, with a gaze point that promises more (a look is due)."""
    gaze = (Gaze(x, 1.0, 0.0, psi_prime=0.55), Gaze(x + 0.5, 1.0, 0.0, psi_prime=0.5))
    return SeenObject(iid, "counter", {"counter": (psi + 0.15, 0.15, psi)}, x, 0.0, 1.0, gaze)


def _holding(th: Thresholds = COMMIT, **kw: object) -> TaskMachine:
    m = TaskMachine("pick_place", "mug", "table", "counter", th=th, **kw)  # type: ignore[arg-type]
    m.holding = True
    return m


def test_holding_with_the_steps_running_out_the_machine_places_on_the_best_goal_candidate() -> None:
    m = _holding()
    act = m.step(ROBOT, FRONTIER, [_counter(7, psi=0.30), _counter(8, x=2.0, psi=0.38)], steps_left=2)
    assert (act.kind, act.ref) == ("place", 8), act
    assert "steps left" in act.reason


def test_with_steps_enough_the_paper_rule_decides() -> None:
    """Psi 0.38 < tau_b and a look that could raise it: the paper looks (Eq. 11), as long as steps are left."""
    m = _holding()
    act = m.step(ROBOT, FRONTIER, [_counter(8, x=2.0, psi=0.38)], steps_left=30)
    assert (act.kind, act.phase, act.ref) == ("move", "looking", 8)


def test_the_steps_needed_grow_with_the_distance_to_the_candidate() -> None:
    """12 m away: 1.5 x 11.4 m at 3 m a step and one in hand is 7 steps; with 5 left it cannot be reached in
    time either way, with 7 it can."""
    far = _counter(8, x=12.0, psi=0.38)
    assert _holding().step(ROBOT, FRONTIER, [far], steps_left=7).kind == "place"
    assert _holding().step(ROBOT, FRONTIER, [far], steps_left=8).kind == "move"


def test_no_deadline_pick_under_a_pick_limit_but_one_without() -> None:
    mug = SeenObject(1, "mug", {"mug": (0.45, 0.15, 0.30)}, 1.0, 0.0, 1.0, (Gaze(1.0, 1.0, 0.0, psi_prime=0.5),))
    limited = TaskMachine("pick_place", "mug", "table", "counter", th=COMMIT, pick_limit=1)
    assert limited.step(ROBOT, FRONTIER, [mug], steps_left=1).kind != "pick"
    free = TaskMachine("pick_place", "mug", "table", "counter", th=COMMIT)
    assert free.step(ROBOT, FRONTIER, [mug], steps_left=1).kind == "pick"


def test_an_object_search_stops_at_its_best_candidate() -> None:
    mug = SeenObject(1, "mug", {"mug": (0.45, 0.15, 0.30)}, 1.0, 0.0, 1.0, (Gaze(1.0, 1.0, 0.0, psi_prime=0.5),))
    m = TaskMachine("find_object", "mug", th=COMMIT)
    act = m.step(ROBOT, FRONTIER, [mug], steps_left=1)
    assert (act.kind, act.ref) == ("stop", 1)


def test_off_or_unknown_budget_leaves_the_paper_rule() -> None:
    cand = [_counter(8, x=2.0, psi=0.38)]
    assert _holding(Thresholds(deadline="off")).step(ROBOT, FRONTIER, cand, steps_left=1).kind == "move"
    assert _holding().step(ROBOT, FRONTIER, cand, steps_left=None).kind == "move"


def test_task_step_counts_the_goals_left_from_the_step_budget() -> None:
    """max_steps 20: the goal of step 18 is the last one carried out (step 19 is the last frame): the machine
    places, where at step 2 it looks."""
    g = GridSpec(origin_x=-5.0, origin_y=-5.0, resolution=0.05, rows=200, cols=200)
    free = np.zeros((200, 200), bool)
    free[2:-2, 2:-2] = True
    pose = Pose2D(x=0.0, y=0.0, yaw=0.0)
    fr = [Frontier(x=-4.0, y=0.0, nx=-1.0, ny=0.0, size=20, sv=0.9)]
    cand = [_counter(8, x=2.0, psi=0.38)]
    rng = np.random.default_rng(0)
    early = ts.task_step(_holding(max_steps=20), g, free, ~free, pose, fr, cand, None, Memory(), rng, step=2)
    assert early.phase == "looking"
    late = ts.task_step(_holding(max_steps=20), g, free, ~free, pose, fr, cand, None, Memory(), rng, step=18)
    assert (late.skill, late.target, late.phase) == ("place", 8, "placing")
    restored = TaskMachine.from_json(_holding(max_steps=20).to_json())
    assert restored.max_steps == 20
