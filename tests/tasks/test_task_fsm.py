"""The HELIOS task state machine (services/planner/task_fsm.py): phases, decisions, pick limits, restart."""

from __future__ import annotations

import json
import math

import pytest

from eqa.settings import Settings
from services.planner.helios import FrontierOption
from services.planner.task_fsm import Gaze, SeenObject, SkillOutcome, TaskMachine, Thresholds

ROBOT = (0.0, 0.0, 0.0)
FRONTIER = [FrontierOption(0, 5.0, 0.0, 0.2), FrontierOption(1, -5.0, 0.0, 0.9)]


def _table(S: float = 0.8, ig: float = 50.0) -> SeenObject:
    gaze = (Gaze(3.0, 1.0, 0.0), Gaze(1.0, 1.0, 0.0), Gaze(2.0, 2.5, 0.0))
    return SeenObject(10, "table", {"table": (S, 0.1, S - 0.1)}, 2.0, 1.0, ig, gaze)


def _mug(psi: float, psi_prime: float = -1.0) -> SeenObject:
    return SeenObject(20, "mug", {"mug": (psi + 0.1, 0.1, psi)}, 2.0, 1.2, 1.0,
                      (Gaze(1.5, 1.2, 0.0, psi_prime=psi_prime), Gaze(2.5, 0.2, 1.0, psi_prime=psi_prime - 0.1)))


def _counter(psi: float) -> SeenObject:
    return SeenObject(30, "counter", {"counter": (psi + 0.1, 0.1, psi)}, -3.0, 0.0, 1.0, (Gaze(-2.0, 0.0, 3.14),))


def _machine(**kw: object) -> TaskMachine:
    return TaskMachine("pick_place", "mug", "table", "counter", **kw)  # type: ignore[arg-type]


def test_nothing_seen_goes_to_the_best_frontier() -> None:
    a = _machine().step(ROBOT, FRONTIER, [])
    assert (a.kind, a.phase, a.ref) == ("frontier", "searching", 1)


def test_a_start_receptacle_is_searched_at_all_its_gaze_points_nearest_first() -> None:
    m = _machine()
    seen = [_table()]
    poses = []
    robot = ROBOT
    for _ in range(3):
        a = m.step(robot, FRONTIER, seen)
        assert (a.kind, a.phase, a.ref) == ("move", "local_search", 10)
        poses.append(a.pose[:2])
        robot = (*a.pose[:2], 0.0)
    assert poses == [(1.0, 1.0), (2.0, 2.5), (3.0, 1.0)]  # greedy nearest from where the robot is
    assert 10 in m.memory.visited
    assert m.step(robot, FRONTIER, seen).kind == "frontier"  # visited: not searched again


def test_pick_look_and_limits() -> None:
    m = _machine(pick_limit=1)
    a = m.step(ROBOT, FRONTIER, [_mug(0.3, psi_prime=0.6)])
    assert (a.kind, a.phase, a.ref, a.pose) == ("move", "looking", 20, (1.5, 1.2, 0.0))  # best Psi' gaze
    a = m.step(ROBOT, FRONTIER, [_mug(0.3, psi_prime=0.31)])
    assert a.kind == "frontier"  # Psi' below min(tau, Psi + tau_inc): back to the global search
    a = m.step(ROBOT, FRONTIER, [_mug(0.55)])
    assert (a.kind, a.phase, a.ref) == ("pick", "picking", 20)
    done = m.step(ROBOT, FRONTIER, [_mug(0.55)], SkillOutcome("pick", False, 20, "no target object in frame"))
    assert (done.kind, done.success) == ("done", False) and "pick limit 1" in done.reason
    assert m.step(ROBOT, FRONTIER, []).kind == "done"  # stays finished


def test_unlimited_picks_retry_then_rule_out_the_instance() -> None:
    m = _machine()
    for _ in range(2):
        assert m.step(ROBOT, FRONTIER, [_mug(0.55)]).kind == "pick"
        m.step(ROBOT, FRONTIER, [], SkillOutcome("pick", False, 20, "not in frame"))
    assert m.step(ROBOT, FRONTIER, [_mug(0.55)]).kind == "frontier"  # two failures: ruled out
    assert m.budget.attempts == 2 and not m.budget.exhausted


def test_after_the_pick_the_goal_receptacle_and_place() -> None:
    m = _machine()
    m.step(ROBOT, FRONTIER, [_mug(0.6)])
    a = m.step(ROBOT, FRONTIER, [_counter(0.2)], SkillOutcome("pick", True, 20))
    assert m.holding and (a.kind, a.phase) == ("frontier", "searching")  # counter not confident, no look
    a = m.step(ROBOT, FRONTIER, [_counter(0.7)])
    # the skill pose: SKILL_APPROACH_M (0.6 m) from the counter's centre towards its gaze point, facing it
    assert (a.kind, a.phase, a.ref) == ("place", "placing", 30)
    assert a.pose == pytest.approx((-2.4, 0.0, math.pi))
    done = m.step(ROBOT, FRONTIER, [], SkillOutcome("place", True, 30, "on the counter"))
    assert (done.kind, done.success) == ("done", True)


def test_trusting_acts_on_any_detection_and_no_global_prefers_candidates() -> None:
    t = _machine(ablation="trusting")
    assert t.step(ROBOT, FRONTIER, [_mug(0.05)]).kind == "pick"
    assert _machine(ablation="trusting").step(ROBOT, FRONTIER, [_table()]).kind == "frontier"  # no local search
    # a weak candidate: the full objective prefers the frontier, no_global the candidate
    weak = _table(S=0.35, ig=0.1)
    assert _machine().step(ROBOT, FRONTIER, [weak]).kind == "frontier"
    assert _machine(ablation="no_global").step(ROBOT, FRONTIER, [weak]).phase == "local_search"


def test_find_object_stops_when_confident() -> None:
    m = TaskMachine("find_object", "mug")
    assert m.step(ROBOT, FRONTIER, [_mug(0.3, psi_prime=0.6)]).phase == "looking"
    a = m.step(ROBOT, FRONTIER, [_mug(0.6)])
    assert (a.kind, a.phase, a.pose) == ("move", "looking", (1.5, 1.2, 0.0))  # a view from a gaze point first
    a = m.step((1.5, 1.2, 0.0), FRONTIER, [_mug(0.6)])
    assert a.kind == "stop" and a.ref == 20
    assert m.step(ROBOT, FRONTIER, [], SkillOutcome("stop", True, 20, "near a mug")).success


def test_an_object_search_stops_at_tau_stop_and_a_pick_waits_for_tau_g() -> None:
    """The search's stop and the pick have a threshold each (Thresholds docstring): Psi 0.45 between them."""
    th = Thresholds(tau_g=0.5, tau_stop=0.4)
    find = TaskMachine("find_object", "mug", th=th)
    find.step(ROBOT, FRONTIER, [_mug(0.45)])  # a view from a gaze point first
    assert find.step((1.5, 1.2, 0.0), FRONTIER, [_mug(0.45)]).kind == "stop"
    pick = _machine(th=th)
    assert pick.step(ROBOT, FRONTIER, [_mug(0.45)]).kind != "pick"
    assert Thresholds.from_settings(Settings(helios_tau_stop=0.7)).tau_stop == 0.7


def test_the_machine_survives_a_restart_mid_task() -> None:
    m = _machine(pick_limit=5)
    seen = [_table()]
    first = m.step(ROBOT, FRONTIER, seen)
    m.step(ROBOT, FRONTIER, [_mug(0.6)])
    m.step(ROBOT, FRONTIER, [_mug(0.6)], SkillOutcome("pick", False, 20, "far"))
    saved = json.loads(json.dumps(m.to_json()))
    m2 = TaskMachine.from_json(saved)
    assert m2.to_json() == m.to_json()
    robot = (*first.pose[:2], 0.0)
    assert m2.step(robot, FRONTIER, seen) == m.step(robot, FRONTIER, seen)  # the same next action
    assert m2.budget.attempts == 1 and m2.budget.limit == 5


def test_looking_again_visits_each_gaze_point_once_then_gives_up() -> None:
    m = _machine()
    gaze = tuple(Gaze(float(x), 1.0, 0.0, psi_prime=0.6 - 0.01 * x) for x in range(1, 6))
    mug = SeenObject(20, "mug", {"mug": (0.4, 0.1, 0.3)}, 2.0, 1.2, 1.0, gaze)
    robot = ROBOT
    visited = []
    for _ in range(6):
        a = m.step(robot, FRONTIER, [mug])
        if a.kind != "move":
            break
        assert a.phase == "looking"
        visited.append(a.pose[:2])
        robot = (*a.pose[:2], 0.0)  # the robot gets there; Psi does not change
    assert visited == [(1.0, 1.0), (2.0, 1.0), (3.0, 1.0)]  # best Psi' first, each once, at most 3
    assert a.kind == "frontier"  # then back to the global search
    assert TaskMachine.from_json(m.to_json()).looked == m.looked


def test_trusting_acts_only_on_instances_believed_to_be_the_class() -> None:
    """The trusting agent acts on the first *detection* of the object: not on an instance of another class that
    merely has some score for it (every instance has a score for every task class)."""
    t = _machine(ablation="trusting")
    table_with_some_mug_score = SeenObject(10, "table", {"table": (0.8, 0.1, 0.7), "mug": (0.15, 0.1, 0.05)},
                                           2.0, 1.0, 1.0, ())
    assert t.step(ROBOT, FRONTIER, [table_with_some_mug_score]).kind == "frontier"
    assert t.step(ROBOT, FRONTIER, [table_with_some_mug_score, _mug(0.05)]).kind == "pick"
