"""Object evidence for questions: the layer's distribution on hand-computed cases, pooling,
validation off the bus, the stopper with the setting on/off, calibration of the combined score, and the real
HELIOS object layer tracking a question's target class in a generated house."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from eqa.messages import EpisodeStart, ObjectEvidence, Question, StepScores, StopConfig
from services.stopper.calibration import calibrate
from services.stopper.object_evidence import (
    EvidenceParams,
    choice_number,
    combine,
    layer_distribution,
    poisson_binomial,
)
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide

COUNT = ["One", "Two", "Three", "Four"]
YESNO = ["(Do not choose this option)", "No", "Yes", "(Do not choose this option)"]


def test_counting_by_hand() -> None:
    assert poisson_binomial([0.9, 0.5]) == pytest.approx([0.05, 0.5, 0.45])
    assert [choice_number(c) for c in ["Three", "3 chairs", "none", "blue"]] == [3, 3, None, None]
    p = EvidenceParams(psi_min=0.3, floor=0.0)
    ev = ObjectEvidence(category="counting", psi=[0.9, 0.5, 0.2], explored=1.0)  # 0.2 is below psi_min
    assert layer_distribution(ev, COUNT, p) == pytest.approx([0.5 / 0.95, 0.45 / 0.95, 0.0, 0.0])
    # half the region unexplored: each count may be one more
    half = ObjectEvidence(category="counting", psi=[0.9, 0.5], explored=0.5)
    counts = np.array([0.05 * 0.5, 0.5 * 0.5 + 0.05 * 0.5, 0.45 * 0.5 + 0.5 * 0.5, 0.45 * 0.5])
    want = np.array([counts[1], counts[2], counts[3], 0.0])  # "Four" cannot be reached with two seen + one
    assert layer_distribution(half, COUNT, p) == pytest.approx(want / want.sum())
    floored = layer_distribution(ev, COUNT, EvidenceParams(psi_min=0.3, floor=0.2))
    assert floored == pytest.approx(0.8 * np.array([0.5 / 0.95, 0.45 / 0.95, 0, 0]) + 0.05)


def test_existence_by_hand_and_no_opinion() -> None:
    p = EvidenceParams(psi_min=0.3, prior=0.5, floor=0.0)
    ev = ObjectEvidence(category="existence", psi=[0.8, 0.4], explored=0.5)
    p_yes = 1 - (1 - 0.8) * (1 - 0.5 * 0.5)
    assert layer_distribution(ev, YESNO, p) == pytest.approx([0, 1 - p_yes, p_yes, 0])
    nothing = ObjectEvidence(category="existence", psi=[0.1], explored=1.0)  # fully explored, nothing credible
    assert layer_distribution(nothing, YESNO, p) == pytest.approx([0, 1, 0, 0])
    assert layer_distribution(ev, ["red", "blue"], p) is None  # not yes/no choices
    assert layer_distribution(ObjectEvidence(category="counting"), ["red", "blue"], p) is None


def test_combine_is_weighted_geometric_pooling() -> None:
    vlm = np.array([0.7, 0.1, 0.1, 0.1])
    lay = np.array([0.1, 0.7, 0.1, 0.1])
    out = combine(vlm, lay, 0.5)
    g = np.sqrt(vlm * lay)
    assert out == pytest.approx(g / g.sum())
    assert combine(vlm, None, 0.5) is not None and np.array_equal(combine(vlm, None, 0.5), vlm)
    assert np.array_equal(combine(vlm, lay, 0.0), vlm)
    with pytest.raises(ValueError):
        EvidenceParams(weight=1.5)


def test_evidence_is_validated_off_the_bus() -> None:
    with pytest.raises(ValidationError):
        ObjectEvidence(category="counting", psi=[1.5])
    with pytest.raises(ValidationError):
        ObjectEvidence(category="counting", psi=[0.5] * 65)
    with pytest.raises(ValidationError):
        ObjectEvidence(category="state", psi=[0.5])
    with pytest.raises(ValidationError):
        ObjectEvidence(category="existence", explored=1.2)


def _rec(on: bool, q_hat: float = 1.3) -> EpisodeRecord:
    q = Question(id="q-c", text="How many chairs are there in the kitchen?", choices=COUNT, scene="s", answer="B",
                 category="counting", query={"type": "counting", "category": "chair", "room_kind": "kitchen"})
    rec = EpisodeRecord.from_start(EpisodeStart(episode_id="e", robot="r", question=q, max_steps=10,
                                                stop=StopConfig(rule="cp", eps=0.2)), "r")
    rec.calibration = CalibrationChoice(q_hat=q_hat, eps=0.2, asked_eps=0.2, n=50, source="t")
    if on:
        rec.object_evidence = (0.3, 0.5)
    return rec


def test_stopper_pools_the_evidence_only_when_on_and_the_trace_holds_what_it_used() -> None:
    vlm = [0.4, 0.3, 0.2, 0.1]  # the VLM leans to One; the layer sees two credible chairs
    ev = ObjectEvidence(category="counting", psi=[0.95, 0.9], explored=1.0)
    scores = StepScores(episode_id="e", step=0, answer_probs=vlm, relevance=0.8, object_evidence=ev)
    off, on = _rec(False), _rec(True)
    d_off, d_on = decide(off, scores), decide(on, scores)
    assert d_off is not None and d_on is not None
    assert off.probs[0] == pytest.approx(vlm)
    expected = combine(np.array(vlm), layer_distribution(ev, COUNT, EvidenceParams(0.3, 0.5)), 0.5)
    assert on.probs[0] == pytest.approx(expected.tolist())
    assert int(np.argmax(on.probs[0])) == 1  # pooled: Two
    assert d_on.scores["B"] == pytest.approx(0.8 * (expected[1] - 1))
    trace = on.trace()
    assert trace is not None and trace.steps[0].answer_probs == pytest.approx(expected.tolist())
    # a step without evidence (the layer had nothing to say) keeps the VLM's distribution
    decide(on, StepScores(episode_id="e", step=1, answer_probs=vlm, relevance=0.5))
    assert on.probs[1] == pytest.approx(vlm)


def test_calibration_covers_the_combined_score() -> None:
    """Exchangeable synthetic counting episodes whose VLM is often wrong and whose layer is informative:
    calibrating the stopper's (combined) traces keeps coverage >= 1 - eps on fresh episodes, and the combined
    score has smaller non-conformity than the VLM's alone (the layer helps in this synthetic world)."""
    rng = np.random.default_rng(0)
    def episode(i: int) -> tuple[EpisodeRecord, int]:
        truth = int(rng.integers(4))  # the count is truth + 1
        rec = _rec(True, q_hat=2.0)
        rec.question = rec.question.model_copy(update={"id": f"q{i}", "answer": "ABCD"[truth]})
        for t in range(6):
            right = rng.random() < 0.5
            fav = truth if right else int(rng.integers(4))
            f = rng.dirichlet(np.ones(4) + 6 * np.eye(4)[fav])
            seen = min(truth + 1, t + 1)
            psi = list(np.clip(rng.normal(0.8, 0.1, size=seen), 0, 1)) + list(rng.uniform(0, 0.25, size=2))
            ev = ObjectEvidence(category="counting", psi=psi, explored=min(1.0, (t + 1) / 4))
            decide(rec, StepScores(episode_id="e", step=t, answer_probs=f.tolist(), relevance=float(rng.beta(4, 3)),
                                   object_evidence=ev))
        return rec, truth

    cal = [episode(i) for i in range(150)]
    table = calibrate([r.trace() for r, _ in cal], [0.2])  # type: ignore[misc]
    q_hat = table.entries[0].q_hat
    test = [episode(1000 + i) for i in range(300)]
    from services.stopper.conformal import relevance_weighted_confidence, sequence_set

    cov = np.mean([sequence_set(relevance_weighted_confidence(np.array(r.probs), np.array(r.relevance)), q_hat)[y]
                   for r, y in test])
    assert cov >= 0.8 - 0.04


def test_the_object_layer_tracks_the_question_target_in_a_house() -> None:
    """The real HELIOS layer (torch) fed by the simulated detector on rendered views of the kitchen chair of
    generated house 5: a counting question about chairs in the kitchen gets credible chair instances in the
    kitchen; a region elsewhere gets none."""
    from support.objects import ring_views

    from eqa.messages import DetectResult, Frame, GridSpec, Pose2D
    from services.mapper.object_map import ObjectMapConfig
    from services.mapper.objects.config import ObjectLayerConfig
    from services.mapper.question_objects import QuestionObjects, question_target
    from services.sim.housegen import generate_house
    from services.sim.render import Renderer
    from services.vlm_scorer.detector.oracle import OracleDetector, OracleDetectorParams

    scene = generate_house(5)
    renderer = Renderer(scene)
    chair = scene.instances[25]
    room = next(r for r in scene.rooms if r.contains(chair.position[0], chair.position[1]))
    q = Question(id="q", text=f"How many chairs are there in the {room.kind}?", choices=COUNT, scene="gen-5",
                 category="counting", query={"type": "counting", "category": "chair", "room_kind": room.kind})
    assert question_target(q) == ("counting", "chair", room.kind)
    assert question_target(q.model_copy(update={"category": "identification", "query": {}})) is None
    cfg = ObjectMapConfig(layer=ObjectLayerConfig(render_scale=1.0))
    here = QuestionObjects(q, [room.rect], config=cfg)
    det = OracleDetector(OracleDetectorParams(recall=1.0, background_fp=0.0, confusion=0.0))
    for step, v in enumerate(ring_views(scene, renderer, 25, 160, 120)[:2]):
        fr = v.frame
        frame = Frame(episode_id="e", step=step, pose=Pose2D(x=v.x, y=v.y, yaw=v.yaw), camera_pose=v.pose,
                      intrinsics=v.K, rgb=fr.rgb, depth=fr.depth, instances=fr.instances,
                      labels=renderer.labels(fr.instances))
        req = here.detect_request(frame, seed=1)
        assert req.classes == ["chair"]
        here.integrate(frame, DetectResult(request_id=req.request_id, episode_id="e", step=step,
                                           detections=det.detect(req), backend="oracle"))
    free, ox, oy = scene.navigable_grid(0.1)
    grid = GridSpec(origin_x=ox, origin_y=oy, resolution=0.1, rows=free.shape[0], cols=free.shape[1])
    ev = here.evidence(free, grid)
    assert ev.category == "counting" and ev.psi and max(ev.psi) >= 0.3
    assert 0.0 < ev.explored <= 1.0
    _, _, x1, y1 = room.rect
    elsewhere = [(x1 + 50.0, y1 + 50.0, x1 + 51.0, y1 + 51.0)]
    here.rects = elsewhere
    assert here.evidence(free, grid).psi == []


def test_question_episode_through_the_stopper_service_with_both_settings_on(hub_settings, settings) -> None:
    """A counting question episode over the real bus: the stopper service (EQA_OBJECT_EVIDENCE on, answer
    memory K = 2, a table calibrated with that rule) pools the object layer's evidence into f, warns about
    nothing, stops by CP and answers the count the evidence supports."""
    from test_stopper_service import listened_stopper

    from eqa import keys
    from eqa.store import EmbeddedStore
    from services.stopper import synthetic
    from services.stopper.answer_memory import AnswerRule
    from services.stopper.calibration import save_table

    rule = AnswerRule(2)
    traces = [synthetic.to_trace(e, f"q{i}") for i, e in enumerate(synthetic.episodes(200, seed=21))]
    store = EmbeddedStore(settings.data_dir / "store.sqlite")
    save_table(store, calibrate(traces, [0.2], answer_rule=rule))
    store.close()
    svc_settings = settings.model_copy(update={"object_evidence": True, "answer_memory_k": 2})
    with listened_stopper(hub_settings, svc_settings) as (lis, _svc):
        rec = _rec(True)
        start = EpisodeStart(episode_id="ep-obj", robot="r0", question=rec.question, max_steps=10,
                             stop=StopConfig(rule="cp", eps=0.2))
        lis.send(keys.EPISODE_START, start)
        vlm = [0.4, 0.3, 0.2, 0.1]
        ev = ObjectEvidence(category="counting", psi=[0.97, 0.95], explored=1.0)
        for t in range(10):
            lis.send(keys.MAPPER_SCORES, StepScores(episode_id="ep-obj", step=t, answer_probs=vlm,
                                                    relevance=0.9, object_evidence=ev, backend="test"))
            d = lis.decision("ep-obj", t)
            assert "answer memory memory-2-loglinear" in d.reason and "table calibrated for" not in d.reason
            if d.stop:
                break
        end = lis.end("ep-obj")
        assert end.answer == "B" and end.correct is True  # Two: what the layer supports
