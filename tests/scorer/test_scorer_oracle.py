"""The SIMULATED PERCEPTION MODEL (oracle backend): reads only the frame and the question."""

from __future__ import annotations

import numpy as np
import pytest
from support.scorer import frame_request

from eqa.messages import NOT_LISTED_CHOICE, PADDING_CHOICE, Question
from services.vlm_scorer.backends.oracle import OracleBackend, OracleParams, parse_target


def test_deterministic_per_question_and_step():
    b = OracleBackend()
    a1, a2 = b.score(frame_request(step=3)), b.score(frame_request(step=3))
    assert a1.answer_probs == a2.answer_probs and a1.lsv == a2.lsv and a1.relevance == a2.relevance
    other = b.score(frame_request(step=4))
    assert other.relevance != a1.relevance


def test_never_reads_the_ground_truth_answer():
    b = OracleBackend()
    base = frame_request()
    for answer in ("A", "B", "C", "D"):
        req = frame_request()
        req.question = req.question.model_copy(update={"answer": answer, "evidence_ids": [7, 99]})
        s = b.score(req)
        assert s.answer_probs == b.score(base).answer_probs


def test_sees_the_target_and_answers_from_it_when_accurate():
    b = OracleBackend(OracleParams(accuracy=1.0))
    hits = []
    for step in range(20):
        s = b.score(frame_request(step=step, episode=f"e{step}"))
        hits.append(int(np.argmax(s.answer_probs)) == 1)  # "Red" is what the frame shows
        assert abs(sum(s.answer_probs) - 1) < 1e-9
    assert sum(hits) >= 14  # weak-quality views fall back to the bias sometimes


def test_irrelevant_views_give_confident_biased_answers_and_low_relevance():
    b = OracleBackend()
    tops, rels, good_rels = [], [], []
    for step in range(30):
        s = b.score(frame_request(step=step, with_target=False))
        tops.append(max(s.answer_probs))
        rels.append(s.relevance)
        good_rels.append(b.score(frame_request(step=step)).relevance)
    assert np.mean(tops) > 0.5  # confident although nothing relevant is in view
    assert np.mean(rels) < 0.15
    assert np.mean(good_rels) > np.mean(rels) and np.median(good_rels) < 0.7  # low even when right


def test_padding_choices_get_only_the_floor():
    q = Question(
        text="Is there a towel in the bathroom?",
        choices=[PADDING_CHOICE, "Yes", "No", PADDING_CHOICE],
        scene="s",
        query={"type": "existence", "category": "towel", "room_kind": "bathroom"},
    )
    p = OracleParams()
    s = OracleBackend(p).score(frame_request(question=q))
    assert s.answer_probs[0] == pytest.approx(p.padding_floor) and s.answer_probs[3] == pytest.approx(
        p.padding_floor
    )
    assert abs(sum(s.answer_probs) - 1) < 1e-9


def test_lsv_prefers_the_room_where_the_object_belongs():
    b = OracleBackend(OracleParams(accuracy=1.0))
    # point A shows the kitchen, point B the living room; sofas live in living rooms
    lsv = [b.score(frame_request(step=s, with_target=False)).lsv for s in range(10)]
    assert all(v[1] > v[0] for v in lsv)
    q = Question(
        text="Is the stove on?",
        choices=["Yes", "No"],
        scene="s",
        query={"type": "state", "category": "stove", "attribute": "state", "value": "on"},
    )
    lsv = [b.score(frame_request(step=s, with_target=False, question=q)).lsv for s in range(10)]
    assert all(v[0] > v[1] for v in lsv)


def test_gsv_higher_when_the_wanted_room_is_in_view():
    b = OracleBackend()
    q_in = Question(
        text="How many sofas are in the living room?",
        choices=["One", "Two", "Three", "Four"],
        scene="s",
        query={"type": "counting", "category": "sofa", "room_kind": "living_room"},
    )
    q_out = Question(
        text="How many toilets are in the bathroom?",
        choices=["One", "Two", "Three", "Four"],
        scene="s",
        query={"type": "counting", "category": "toilet", "room_kind": "bathroom"},
    )
    g_in = np.mean([b.score(frame_request(step=s, question=q_in, with_target=False)).gsv for s in range(20)])
    g_out = np.mean(
        [b.score(frame_request(step=s, question=q_out, with_target=False)).gsv for s in range(20)]
    )
    assert g_in > g_out


def test_free_text_fallback_and_proposals():
    t = parse_target(Question(text="How many towels are there in the bathroom?", scene="s"))
    assert (t.type, t.category, t.room_kind) == ("counting", "towel", "bathroom")
    yn = ["Yes", "No"]
    t = parse_target(Question(text="Is the stove in the kitchen turned off?", choices=yn, scene="s"))
    assert (t.type, t.category, t.room_kind, t.attribute, t.value) == ("state", "stove", "kitchen", "state", "off")
    t = parse_target(Question(text="Is there a towel in the bathroom?", choices=yn, scene="s"))
    assert (t.type, t.value) == ("existence", None)
    t = parse_target(Question(text="Where is the red backpack?", choices=["kitchen", "garage"], scene="s"))
    assert (t.type, t.category, t.color) == ("location", "backpack", "red")
    q = Question(text="In which room did I leave the white mug?", choices=["kitchen", "garage"], scene="s")
    t = parse_target(q)
    assert (t.type, t.category, t.color) == ("location", "mug", "white")
    # a structured parse wins over the text
    t = parse_target(Question(text="Where is the red sofa?", scene="s", query={"type": "location", "category": "sofa"}))
    assert t.color is None
    s = OracleBackend().score(frame_request(question=Question(text="Where is the sofa?", scene="s")))
    assert s.proposed_choices[-1] == NOT_LISTED_CHOICE and "living room" in s.proposed_choices
    assert len(s.answer_probs) == len(s.proposed_choices)


def test_location_question_ignores_objects_of_another_colour():
    """"Where is the blue sofa?" with only a red sofa in view: no evidence, the answer is a guess."""
    b = OracleBackend(OracleParams(accuracy=1.0))
    q = Question(id="q-loc", text="Where is the blue sofa?", choices=["In the kitchen", "In the living room"],
                 scene="s0", query={"type": "location", "category": "sofa", "color": "blue"})
    req = frame_request(question=q)
    assert b.target_views(req, parse_target(q)) == []
    red = q.model_copy(update={"text": "Where is the red sofa?", "query": {**q.query, "color": "red"}})
    views = b.target_views(frame_request(question=red), parse_target(red))
    assert [lab.id for lab, _, _ in views] == [7]
    s = b.score(frame_request(question=red))
    assert int(np.argmax(s.answer_probs)) == 1  # the red sofa stands in the living room


def test_location_guess_without_evidence_follows_the_commonsense_prior():
    """Without evidence a VLM guesses from what it knows ("a towel: the bathroom"), not uniformly."""
    b = OracleBackend(OracleParams(bias_stickiness=1.0))
    hits = 0
    for k in range(60):
        q = Question(id=f"q-towel-{k}", text="Where is the pink towel?",
                     choices=["In the garage", "In the bathroom", "In the office", "In the dining room"],
                     scene="s0", query={"type": "location", "category": "towel", "color": "pink"})
        s = b.score(frame_request(question=q, with_target=False))
        hits += int(np.argmax(s.answer_probs)) == 1
    assert hits >= 40  # uniform guessing would give about 15 of 60
