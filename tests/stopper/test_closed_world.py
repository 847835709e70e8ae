"""The closed-world existence rule (services/stopper/closed_world.py)."""

from __future__ import annotations

import numpy as np
import pytest

from services.stopper.closed_world import ClosedWorldParams, PresenceStep, apply, firing_step, no_distribution
from services.stopper.conformal import nonconformity

CHOICES = ["(Do not choose this option)", "Yes", "(Do not choose this option)", "No"]


def _steps(*rows: tuple[float, float | None, float, float]) -> list[PresenceStep]:
    return [PresenceStep(object_yes=a, in_room=b, room_area_m2=c, open_share=d) for a, b, c, d in rows]


def test_fires_once_the_room_is_observed_without_evidence():
    p = ClosedWorldParams(k_yes=1, min_area_m2=2.0, max_open=0.2)
    steps = _steps((0.1, 0.9, 1.0, 0.5), (0.2, 0.9, 3.0, 0.4), (0.1, 0.8, 6.0, 0.1), (0.1, 0.9, 6.0, 0.0))
    assert firing_step(steps, p) == 2
    assert firing_step(steps[:2], p) is None  # not yet observed


def test_a_room_view_showing_the_object_blocks_it_and_other_views_do_not():
    p = ClosedWorldParams(k_yes=1, min_area_m2=2.0, max_open=0.2)
    seen = _steps((0.9, 0.8, 1.0, 0.5), (0.1, 0.9, 6.0, 0.1))
    assert firing_step(seen, p) is None
    elsewhere = _steps((0.9, 0.1, 1.0, 0.5), (0.1, 0.9, 6.0, 0.1))  # the object seen outside the room
    assert firing_step(elsewhere, p) == 1
    two = ClosedWorldParams(k_yes=2, min_area_m2=2.0, max_open=0.2)
    assert firing_step(seen, two) == 1  # one yes is not evidence when two are asked for


def test_closed_world_scores_and_their_calibration():
    p = ClosedWorldParams(confidence=0.9, padding=1e-3)
    d = no_distribution(CHOICES, p)
    assert d is not None and d[3] == pytest.approx(0.9) and d[0] == d[2] == pytest.approx(1e-3)
    assert d.sum() == pytest.approx(1.0) and d[1] == pytest.approx(0.098)
    assert no_distribution(["One", "Two"], p) is None
    f = np.full((4, 4), 0.25)
    rel = np.full(4, 0.1)
    f2, r2 = apply(f, rel, 2, CHOICES, p)
    assert (f2[:2] == 0.25).all() and np.allclose(f2[2:], d) and list(r2) == [0.1, 0.1, 1.0, 1.0]
    assert f[2, 3] == 0.25  # the input is not changed
    # the conclusion enters the conformal score: a wrong "No" is a large nonconformity
    assert nonconformity(f2, r2, 1) > nonconformity(f, rel, 1) and nonconformity(f2, r2, 3) < 1.2
    same = apply(f, rel, None, CHOICES, p)
    assert np.array_equal(same[0], f) and np.array_equal(same[1], rel)
    with pytest.raises(ValueError):
        apply(f[:, :3], rel, 1, CHOICES, p)


def test_bad_params_are_refused():
    for bad in ({"k_yes": 0}, {"max_open": 1.5}, {"min_area_m2": float("nan")}, {"padding": 0.3},
                {"confidence": 2.0}):
        with pytest.raises(ValueError):
            ClosedWorldParams(**bad)
