"""Miscalibration modes of the SIMULATED PERCEPTION MODEL (oracle backend): 0 = today's behaviour."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from support.scorer import frame_request

from eqa.messages import Question
from eqa.settings import Settings
from services.vlm_scorer.backends.oracle import (
    CATEGORY_RELEVANCE_BIAS,
    MISCALIBRATION_MODES,
    OracleBackend,
    OracleParams,
    parse_target,
)

ALL_ON = {"miscal_category": 1.0, "miscal_view": 0.3, "miscal_related": 1.0, "miscal_irrelevant": 1.0}


def _rescore(b: OracleBackend, req):  # what bench/stop_sensitivity.py does with a recorded step
    t = parse_target(req.question)
    return b.miscalibrated_scores(req, list(req.question.choices), t, b.target_views(req, t),
                                  b.related_views(req, t), b.clutter(req))


def test_level_zero_is_todays_model_and_the_offline_rescore_matches_the_service() -> None:
    base, zero = OracleBackend(), OracleBackend(OracleParams(**{m: 0.0 for m in MISCALIBRATION_MODES}))
    assert not zero.p.miscalibrated
    for step in range(12):
        for with_target in (True, False):
            req = frame_request(step=step, with_target=with_target)
            a, b = base.score(req), zero.score(req)
            assert (a.answer_probs, a.relevance, a.lsv, a.gsv) == (b.answer_probs, b.relevance, b.lsv, b.gsv)
            probs, rel = _rescore(base, req)
            assert probs == a.answer_probs and rel == a.relevance


def test_modes_leave_the_path_signals_alone_and_rescore_offline_exactly() -> None:
    on, off = OracleBackend(OracleParams(**ALL_ON)), OracleBackend()
    changed = 0
    for step in range(12):
        req = frame_request(step=step)
        a, b = on.score(req), off.score(req)
        assert a.lsv == b.lsv and a.gsv == b.gsv  # the robot goes where it went at level 0
        assert _rescore(on, req) == (a.answer_probs, a.relevance)
        changed += a.relevance != b.relevance
    assert changed >= 10


def _q(qtype: str) -> Question:
    return Question(id=f"q-{qtype}", text="?", choices=["Blue", "Red", "Green", "White"], scene="s0",
                    query={"type": qtype, "category": "sofa"})


@pytest.mark.parametrize("qtype", ["counting", "state"])
def test_category_mode_scales_relevance_by_the_documented_bias(qtype: str) -> None:
    b0, b1 = OracleBackend(), OracleBackend(OracleParams(miscal_category=1.0))
    ratios = [b1.score(frame_request(step=s, question=_q(qtype))).relevance
              / b0.score(frame_request(step=s, question=_q(qtype))).relevance for s in range(10)]
    clipped = [r for r in ratios if not np.isclose(r, np.exp(CATEGORY_RELEVANCE_BIAS[qtype]))]
    assert len(clipped) <= 3, ratios  # only where Rel hits its [0.01, 0.99] clip


def test_view_mode_makes_relevance_follow_clutter_not_evidence() -> None:
    b0, b1 = OracleBackend(), OracleBackend(OracleParams(miscal_view=1.0))
    # a frame without the sofa: little clutter -> lower relevance; the sofa view has more clutter
    empty = [b1.score(frame_request(step=s, with_target=False)).relevance
             / b0.score(frame_request(step=s, with_target=False)).relevance for s in range(10)]
    assert max(empty) < 1.0
    assert b1.clutter(frame_request()) > b1.clutter(frame_request(with_target=False))


def test_related_mode_takes_the_wrong_rooms_sofa_for_the_target() -> None:
    q = Question(id="q-rel", text="What color is the sofa in the kitchen?", choices=["Blue", "Red", "Green", "White"],
                 scene="s0", query={"type": "identification", "category": "sofa", "room_kind": "kitchen"})
    b0 = OracleBackend(OracleParams(accuracy=1.0))
    b1 = OracleBackend(OracleParams(accuracy=1.0, miscal_related=1.0))
    req = frame_request(question=q)
    t = parse_target(q)
    assert not b0.target_views(req, t) and len(b0.related_views(req, t)) == 1  # the sofa is in the living room
    r0 = [b0.score(frame_request(step=s, question=q)) for s in range(10)]
    r1 = [b1.score(frame_request(step=s, question=q)) for s in range(10)]
    assert np.mean([s.relevance for s in r1]) > 3 * np.mean([s.relevance for s in r0])
    assert sum(int(np.argmax(s.answer_probs)) == 1 for s in r1) >= 7  # reads "Red" off the wrong sofa
    half = OracleBackend(OracleParams(miscal_related=0.5))  # a draw per (question, instance): all or nothing here
    assert len({half.score(frame_request(step=s, question=q)).relevance > 0.15 for s in range(10)}) <= 2


def test_irrelevant_mode_makes_no_evidence_answers_confident() -> None:
    b0, b1 = OracleBackend(), OracleBackend(OracleParams(miscal_irrelevant=1.0))
    for s in range(10):
        a, b = b0.score(frame_request(step=s, with_target=False)), b1.score(frame_request(step=s, with_target=False))
        assert max(b.answer_probs) == pytest.approx(0.99)
        assert int(np.argmax(a.answer_probs)) == int(np.argmax(b.answer_probs))
        assert abs(sum(b.answer_probs) - 1.0) < 1e-9
    half = OracleBackend(dataclasses.replace(OracleParams(), miscal_irrelevant=0.5))
    top0 = max(b0.score(frame_request(with_target=False)).answer_probs)
    assert max(half.score(frame_request(with_target=False)).answer_probs) == pytest.approx(top0 + 0.5 * (0.99 - top0))


def test_modes_come_from_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EQA_ORACLE_MISCAL_VIEW", "0.4")
    assert OracleParams.from_settings(Settings()).miscal_view == 0.4
    monkeypatch.setenv("EQA_ORACLE_MISCAL_VIEW", "1.5")
    with pytest.raises(ValueError):
        Settings()
