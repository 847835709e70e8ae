"""``cp_guided``: the CP prediction set re-tempers the frontier weights; the planner service uses the
stopper's Decision of the step (real Zenoh)."""

from __future__ import annotations

import math
import queue
import time

import numpy as np
import pytest
from test_planner_service import ROBOT, _map, rig  # noqa: F401  (the fixture)

from eqa import keys
from eqa.messages import Decision, EpisodeStart, Frontier, Goal, Pose2D, Question
from services.planner import cp_guided


def _d(step: int, left: list[str], rule: str = "cp", episode: str = "ep-plan") -> Decision:
    return Decision(episode_id=episode, step=step, rule=rule, stop=False, reason="go on", prediction_set=left,
                    scores={y: -0.1 for y in "ABCD"} if rule == "cp" else {"relevance": 0.1})


def test_narrowing_and_reweighting() -> None:
    assert cp_guided.narrowing(None) == 0.0
    assert cp_guided.narrowing(_d(0, list("ABCD"))) == 0.0
    assert cp_guided.narrowing(_d(0, ["A", "C"])) == pytest.approx(2 / 3)
    assert cp_guided.narrowing(_d(0, ["A"])) == 1.0
    assert cp_guided.narrowing(_d(0, [], rule="relevance")) == 0.0
    w = [math.exp(3.0), math.exp(1.0), float("nan"), 0.0]
    same = cp_guided.reweight(w, _d(0, list("ABCD")))
    assert same[:2] == w[:2]
    two = cp_guided.reweight(w, _d(0, ["A", "C"]), gamma=2.0)
    assert two[0] / two[1] == pytest.approx(math.exp(2.0 * (1 + 2 * 2 / 3)))
    assert math.isnan(two[2]) and two[3] == 0.0
    huge = cp_guided.reweight([1e300, 1e299], _d(0, ["A"]))
    assert all(np.isfinite(huge)) and huge[0] == 1.0 and huge[1] == pytest.approx(1e-3)
    with pytest.raises(ValueError):
        cp_guided.reweight(w, None, gamma=-1)


def _ratio(goals: queue.Queue[Goal], pub, episode: str, left: list[str]) -> float:
    q = Question(text="Where is the sofa?", choices=["kitchen", "bedroom", "hallway", "garage"], scene="synthetic")
    pub(keys.EPISODE_START, EpisodeStart(episode_id=episode, robot=ROBOT, question=q, strategy="cp_guided",
                                         max_steps=20, seed=5))
    frs = [Frontier(x=8.5, y=6.5, nx=1, ny=0, size=9, weight=math.exp(2.0)),
           Frontier(x=1.0, y=6.5, nx=-1, ny=0, size=9, weight=math.exp(1.0))]
    update = _map(0, Pose2D(x=4.5, y=3.5), frs).model_copy(update={"episode_id": episode})
    pub(keys.MAPPER_MAP, update)
    pub(keys.STOPPER_DECISION, _d(0, left, episode=episode))
    g = goals.get(timeout=15)
    assert g.episode_id == episode and len(g.weights) == 2
    return g.weights[0] / g.weights[1]


def test_the_planner_service_retempers_by_the_stoppers_prediction_set(rig) -> None:  # noqa: F811
    hub, _svc, goals = rig
    pub = lambda pair, msg: hub.publish(keys.stream(ROBOT, pair), msg)  # noqa: E731
    full = _ratio(goals, pub, "ep-full", list("ABCD"))
    time.sleep(0.2)
    narrowed = _ratio(goals, pub, "ep-narrow", ["A"])
    # the same map and frontiers: with one answer left the Eq. A6 weights count (1 + gamma) times as much
    assert narrowed / full == pytest.approx(math.exp(cp_guided.DEFAULT_GAMMA * 1.0), rel=1e-6)
