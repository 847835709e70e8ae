"""Counting across views in the product (EQA_ANSWER_COUNTING=views, rule 2 of
docs/results/closed-world-answers.md): the mapper's question-objects extension (IN_ROOM prompt, detections, the
room's extent, the step's evidence) and the stopper's step function give the offline bench's pooled f on the same
episode, and a counting question's answer is the fused count with the setting on and the single-frame answer
with it off. Seed-11 (tuning) counting questions, short budgets; the oracle scorer and the simulated detector
(simulated perception model, not a VLM/detector)."""

from __future__ import annotations

import numpy as np
import pytest

from eqa.messages import EpisodeStart, ObjectEvidence, Question, StepScores, StopConfig, letters
from eqa.seeds import TUNING_SEED
from eqa.settings import Settings
from eqa_app import core_runner
from eqa_app.benches import closed_world as cw
from eqa_app.benchmark_runner import question_seed
from services.mapper.episode_map import EpisodeMap
from services.planner.step import PlannerParams
from services.sim.library import load_or_generate
from services.sim.questions import benchmark_candidates
from services.sim.render import Renderer
from services.sim.service import load_scene
from services.stopper.calibration import CalibrationError, Trace, TraceStep, calibrate
from services.stopper.state import CalibrationChoice, EpisodeRecord, counting_mismatch, decide
from services.vlm_scorer.backends.oracle import OracleBackend

STEPS = 10


def _counting_questions(settings: Settings) -> list[Question]:
    load_or_generate(f"gen-{TUNING_SEED * 10000:05d}", settings.scenes_path)
    qs = benchmark_candidates(TUNING_SEED, 0, settings.scenes_path)["counting"][:2]
    assert {bool(q.query.get("room_kind")) for q in qs} == {True, False}  # the whole house and one room
    return [q.model_copy(update={"max_steps": STEPS}) for q in qs]


class _Asked(OracleBackend):
    """The oracle scorer; keeps the presence query of every request it answers."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.asked: list = []

    def score(self, req):
        self.asked.append(req.presence)
        return super().score(req)


def _services_episode(settings: Settings, q: Question) -> tuple[EpisodeRecord, list]:
    """The episode as the bench records it (same id, map, image size), with the services' extension and
    stopper step function (eqa_app.core_runner._CountingTrace) instead of the bench's hooks."""
    seed = question_seed(q.id)
    start = EpisodeStart(episode_id=f"cw-{q.id}", robot="r0", question=q, strategy="semantic",
                         max_steps=q.max_steps, seed=seed)
    scene = load_scene(settings, q.scene)
    emap = EpisodeMap(start)
    hooks = core_runner._CountingTrace(settings, start, emap)
    scorer = _Asked.from_settings(settings)
    cores = core_runner.EpisodeCores(scene, Renderer(scene), scorer, emap, PlannerParams(), 320, 240)
    try:
        core_runner.run_episode_loop(q, "semantic", cores, episode_id=start.episode_id, seed=seed, hooks=hooks)
    finally:
        hooks.close()
    return hooks.record, scorer.asked


def test_the_services_and_the_offline_bench_give_the_same_pooled_f() -> None:
    settings = Settings()
    for q in _counting_questions(settings):
        ep = cw.run_episode((q, TUNING_SEED, "semantic"))
        record, asked = _services_episode(settings, q)
        f_bench, rel_bench, _ = cw.transformed(ep, None, True)
        np.testing.assert_allclose(np.array(record.probs), f_bench, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.array(record.relevance), rel_bench, rtol=0, atol=1e-12)
        raw = np.array([s.probs for s in ep.steps])
        assert np.abs(f_bench - raw).max() > 0.05  # the layer changed f
        np.testing.assert_allclose(np.array(record.vlm_probs), raw, rtol=0, atol=1e-12)
        # the answer at the budget is the bench's rule 2 answer
        right = letters(len(q.choices)).index(record.fallback() or "") == ep.truth
        assert right == cw.rule_outcome(ep, None, 1.0)[0]
        # IN_ROOM only, and only when a room is asked
        room = q.query.get("room_kind")
        if room:
            assert all(p is not None and p.room == room and not p.ask_object for p in asked)
        else:
            assert all(p is None for p in asked)


def test_a_counting_question_through_the_in_process_runner_with_the_setting_on_and_off() -> None:
    """core_episode: with views the trace holds f pooled with the room's count and says so; with frame it holds
    the scorer's f of each single view."""
    on = Settings()
    assert on.answer_counting == "views"
    off = on.model_copy(update={"answer_counting": "frame"})
    q = _counting_questions(on)[1]
    t_on = core_runner.core_episode((q, "semantic", on.model_dump()))
    t_off = core_runner.core_episode((q, "semantic", off.model_dump()))
    assert t_on.answer_counting == "views" and t_off.answer_counting is None
    f_on, f_off = (np.array([s.answer_probs for s in t.steps]) for t in (t_on, t_off))
    assert f_on.shape == f_off.shape and np.abs(f_on - f_off).max() > 0.05
    rel_on, rel_off = ([s.relevance for s in t.steps] for t in (t_on, t_off))
    assert rel_on == pytest.approx(rel_off)  # the same path and views: only the answer changes


def _record(settings: Settings, store_dir) -> EpisodeRecord:
    from eqa.store import EmbeddedStore
    from services.stopper.service import StopperService

    q = Question(id="q-c", text="How many chairs are there in the kitchen?", choices=["One", "Two", "Three"],
                 scene="s", answer="B", category="counting")
    start = EpisodeStart(episode_id="e", robot="r0", question=q, max_steps=3, stop=StopConfig(rule="max_steps"))
    svc = StopperService(settings, store=EmbeddedStore(store_dir / "store.sqlite"))  # its start handler, no bus
    rec = svc.start_episode("r0", start)
    assert rec is not None
    return rec


def test_the_stopper_answers_the_fused_count_only_with_the_setting_on(tmp_path) -> None:
    """The VLM's most relevant view says One; the layer has fused two credible chairs in the room by the last
    step. Views: the answer is Two (f(x^t*) pooled with the latest count); frame: One."""
    vlm = [[0.6, 0.3, 0.1], [0.7, 0.2, 0.1], [0.5, 0.3, 0.2]]
    rel = [0.4, 0.9, 0.5]
    evs = [ObjectEvidence(category="counting", psi=[], explored=0.2),
           ObjectEvidence(category="counting", psi=[0.9], explored=0.5),
           ObjectEvidence(category="counting", psi=[0.95, 0.9], explored=1.0)]
    ends = {}
    for mode in ("views", "frame"):
        rec = _record(Settings(answer_counting=mode), tmp_path)
        for t in range(3):
            d = decide(rec, StepScores(episode_id="e", step=t, answer_probs=vlm[t], relevance=rel[t],
                                       object_evidence=evs[t]))
        assert d is not None and d.stop
        ends[mode] = d.answer
        trace = rec.trace()
        assert trace is not None and trace.answer_counting == ("views" if mode == "views" else None)
    assert ends == {"views": "B", "frame": "A"}


def test_tables_record_the_counting_rule_and_the_stopper_notes_a_mismatch(tmp_path) -> None:
    def trace(i: int, counting: str | None) -> Trace:
        return Trace(question_id=f"q{i}", scene="s", category="counting", choices=["One", "Two"], answer="A",
                     max_steps=2, strategy="semantic", answer_counting=counting,  # type: ignore[arg-type]
                     steps=[TraceStep(answer_probs=[0.6, 0.4], relevance=0.5)] * 2)

    assert calibrate([trace(i, "views") for i in range(20)], [0.2]).provenance["answer_counting"] == "views"
    frame = calibrate([trace(i, None) for i in range(20)], [0.2])
    assert frame.provenance["answer_counting"] == "frame"
    with pytest.raises(CalibrationError, match="one rule"):
        calibrate([trace(i, "views" if i % 2 else None) for i in range(20)], [0.2])
    rec = _record(Settings(), tmp_path)
    decide(rec, StepScores(episode_id="e", step=0, answer_probs=[0.5, 0.3, 0.2], relevance=0.5,
                           object_evidence=ObjectEvidence(category="counting", psi=[0.9], explored=0.5)))
    cal = CalibrationChoice(q_hat=1.0, eps=0.2, asked_eps=0.2, n=20, source="t")
    assert "EQA_ANSWER_COUNTING=views" in counting_mismatch(cal, rec)  # unrecorded: the single-frame rule
    assert counting_mismatch(cal.model_copy(update={"answer_counting": "views"}), rec) == ""


def test_counting_asks_only_the_in_room_prompt() -> None:
    """The IN_ROOM prompt alone (PRESENCE is not needed for a count); the oracle's IN_ROOM answer is the one it
    gives when both are asked (its draws do not depend on what is asked)."""
    from eqa.messages import PresenceQuery
    from services.vlm_scorer import prompts

    only = prompts.presence_queries(PresenceQuery(object="chair", room="kitchen", ask_object=False))
    assert [q.name for q in only] == ["in_room"]
    settings = Settings()
    q = _counting_questions(settings)[1]
    seed = question_seed(q.id)
    start = EpisodeStart(episode_id="e", robot="r0", question=q, strategy="semantic", max_steps=2, seed=seed)
    scene = load_scene(settings, q.scene)
    emap = EpisodeMap(start)
    from services.sim import camera

    K = camera.intrinsics(160, 120)
    _, req = core_runner.observe_step(Renderer(scene), emap, "e", 0, q.start_pose, K, 160, 120,
                                      q.without_ground_truth(), seed)
    oracle = OracleBackend.from_settings(settings)
    both = oracle.score(req.model_copy(update={"presence": PresenceQuery(object=q.query["category"],
                                                                         room=q.query["room_kind"])}))
    one = oracle.score(req.model_copy(update={"presence": PresenceQuery(object=q.query["category"],
                                                                        room=q.query["room_kind"], ask_object=False)}))
    assert one.object_yes is None and both.object_yes is not None and one.in_room == both.in_room
