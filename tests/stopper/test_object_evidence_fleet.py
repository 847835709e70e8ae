"""Object evidence in the live services: an existence question typed by a user (no
benchmark ``query``) through the real mapper, scorer replica (oracle VLM + simulated detector) and stopper on
Zenoh. With EQA_OBJECT_EVIDENCE on, the mapper parses the target from the text, asks the pool for detections,
puts the layer's evidence into StepScores, keeps the layer over a restart; the stopper's trace holds the
combined distribution. A counting question gets no whole-map evidence (WHOLE_MAP_CATEGORIES); with
EQA_ANSWER_COUNTING=views it gets the count in the asked room's extent. With the settings off, no DetectRequest is
sent and the StepScores carry none. Also the question parser on
hand-written questions, including ones it must not match."""

from __future__ import annotations

import queue
import time

import numpy as np
import pytest
from support.objects import ring_views, run_steps

from eqa import keys
from eqa.bus import Bus
from eqa.messages import (
    DetectRequest,
    EpisodeStart,
    ErrorReply,
    Message,
    Question,
    StepScores,
    StopConfig,
)
from eqa.settings import Settings
from services.mapper.question_objects import parse_question, question_target
from services.mapper.service import MapperService
from services.sim.housegen import generate_house
from services.sim.render import Renderer
from services.stopper.calibration import TraceStore
from services.stopper.object_evidence import EvidenceParams, combine, layer_distribution
from services.stopper.service import StopperService
from services.vlm_scorer.service import ScorerService

ROBOT = "r0"
W, H = 160, 120
COUNT = ["One", "Two", "Three", "Four"]
YESNO = ["Yes", "No"]


@pytest.mark.parametrize(("text", "want"), [
    ("How many chairs are there in the kitchen?", ("counting", "chair", "kitchen")),
    ("How many chairs are in the kitchen?", ("counting", "chair", "kitchen")),
    ("how many Boxes can you see in the storage", ("counting", "box", "storage")),
    ("How many bookshelves are there in the living room?", ("counting", "bookshelf", "living_room")),
    ("How many red cushions are there?", ("counting", "cushion", None)),
    ("How many coffee tables are there in the house?", ("counting", "coffee_table", None)),
    ("Is there a mug in the office?", ("existence", "mug", "office")),
    ("Is there an umbrella in the hallway?", ("existence", "umbrella", "hallway")),
    ("Are there any towels in the bathroom?", ("existence", "towel", "bathroom")),
    ("Are there shoes in the hallway?", ("existence", "shoes", "hallway")),
    ("Is there any laundry basket?", ("existence", "laundry_basket", None)),
])
def test_parser_reads_counting_and_existence_questions(text: str, want: tuple) -> None:
    assert parse_question(text) == want


@pytest.mark.parametrize("text", [
    "What color is the sofa?",
    "Is the lamp on?",
    "Where is the mug?",
    "How many rooms are there?",
    "How many times did you turn around?",
    "How many people live here?",
    "How many cushions are on the sofa?",  # "on the sofa" is no room: not understood, no evidence
    "Is there a way to the garage?",
    "Is the television in the living room on?",
    "How many " + "very " * 80 + "chairs?",
])
def test_parser_leaves_other_questions_alone(text: str) -> None:
    assert parse_question(text) is None


def test_target_prefers_the_benchmark_query_and_respects_the_category() -> None:
    q = Question(text="How many chairs are there in the kitchen?", scene="s")
    assert question_target(q) == ("counting", "chair", "kitchen")
    assert question_target(q.model_copy(update={"category": "identification"})) is None
    bench = q.model_copy(update={"category": "counting",
                                 "query": {"type": "counting", "category": "dining_chair", "room_kind": "den"}})
    assert question_target(bench) == ("counting", "dining_chair", "den")
    assert question_target(Question(text="Is the TV on?", scene="s")) is None


class CountingScorer(ScorerService):
    """The real scorer replica; counts the detection requests it serves (nothing else changed)."""

    def __init__(self, settings: Settings) -> None:
        super().__init__(settings)
        self.detect_requests: list[DetectRequest] = []

    def handle_detect(self, req: DetectRequest) -> Message:
        self.detect_requests.append(req)
        return super().handle_detect(req)


@pytest.fixture(scope="module")
def chair_views():
    scene = generate_house(5)
    renderer = Renderer(scene)
    return scene, renderer, ring_views(scene, renderer, 25, W, H)


def start(episode_id: str, room: str, counting: bool = False) -> EpisodeStart:
    # typed by a user: text and choices only, no category, no query, no ground truth
    where = room.replace("_", " ")
    text = f"How many chairs are there in the {where}?" if counting else f"Is there a chair in the {where}?"
    q = Question(text=text, choices=COUNT if counting else YESNO, scene="gen-5")
    return EpisodeStart(episode_id=episode_id, robot=ROBOT, question=q, max_steps=20, record=False, seed=1,
                        stop=StopConfig(rule="max_steps"))


def test_existence_question_through_the_services_with_the_setting_on_and_off(
        hub_settings: Settings, settings: Settings, chair_views, redis_url: str) -> None:
    scene, renderer, views = chair_views
    chair = scene.instances[25]
    room = next(r for r in scene.rooms if r.contains(chair.position[0], chair.position[1]))
    on = settings.model_copy(update={"redis_url": redis_url, "scorer_replica": "qobj", "object_evidence": True,
                                     "answer_counting": "frame", "detector_oracle_background_fp": 0.0})
    scores: queue.Queue[StepScores] = queue.Queue()
    errors: queue.Queue[ErrorReply] = queue.Queue()
    with Bus(hub_settings, "gateway") as bus:
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_SCORES), StepScores, lambda k, m: scores.put(m))
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_ERROR), ErrorReply, lambda k, m: errors.put(m))
        scorer = CountingScorer(on)
        scorer.start()
        stopper = StopperService(on)
        stopper.start()
        mapper = MapperService(on)
        mapper.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-on", room.kind))
            first = run_steps(bus, scores, renderer, views, "ep-on", range(2))
            assert errors.empty(), errors.get()
            assert len(scorer.detect_requests) == 2 and scorer.detect_requests[0].classes == ["chair"]
            ev = first[-1].object_evidence
            assert ev is not None and ev.category == "existence" and ev.psi and max(ev.psi) >= 0.3
            assert 0.0 < ev.explored <= 1.0

            # the stopper's trace holds the pooled distribution, not the VLM's
            traces = TraceStore(stopper.store)
            params = EvidenceParams(psi_min=on.object_evidence_psi_min, weight=on.object_evidence_weight)

            def traced() -> bool:
                t = traces.trace_for_episode("ep-on")
                return t is not None and len(t.steps) == 2
            deadline = time.monotonic() + 15
            while not traced() and time.monotonic() < deadline:
                time.sleep(0.05)
            trace = traces.trace_for_episode("ep-on")
            assert trace is not None and len(trace.steps) == 2
            for s, step in zip(first, trace.steps, strict=True):
                want = combine(np.array(s.answer_probs), layer_distribution(s.object_evidence, YESNO, params),
                               params.weight)
                assert step.answer_probs == pytest.approx(want.tolist())
                assert step.answer_probs != pytest.approx(s.answer_probs)

            # a restarted mapper continues the stored layer: the same chair, seen a third time
            mapper.stop()
            mapper = MapperService(on)
            mapper.start()
            time.sleep(0.5)
            (third,) = run_steps(bus, scores, renderer, views, "ep-on", range(2, 3))
            assert third.object_evidence is not None
            assert max(third.object_evidence.psi) > max(ev.psi)  # a third consistent view raised it
            # per instance: (step, Psi) of its updates
            restored = mapper.question_objects.layers["ep-on"].objects.history
            assert any(step < 2 for hist in restored.values() for step, _ in hist)  # from before the restart
            assert len(third.object_evidence.psi) <= len(ev.psi) + 1  # no duplicate of the restored chair
            assert errors.empty(), errors.get()

            # a counting question without counting across views: no floor plan, no whole-map evidence (the whole
            # map's count is not the room's)
            n_detect = len(scorer.detect_requests)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-count", room.kind, counting=True))
            counted = run_steps(bus, scores, renderer, views, "ep-count", range(1))
            assert counted[0].object_evidence is None and len(scorer.detect_requests) == n_detect
            mapper.stop()

            # with counting across views (the default): the count in the asked room's extent
            views_on = on.model_copy(update={"answer_counting": "views"})
            mapper = MapperService(views_on)
            mapper.start()
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-views", room.kind, counting=True))
            counted = run_steps(bus, scores, renderer, views, "ep-views", range(2))
            assert all(s.object_evidence is not None and s.object_evidence.category == "counting" for s in counted)
            assert len(scorer.detect_requests) == n_detect + 2
            assert "ep-views" in mapper.question_objects.rooms
            mapper.stop()

            # the setting off: the same question, no detection request, no evidence
            off = on.model_copy(update={"object_evidence": False})
            mapper = MapperService(off)
            mapper.start()
            time.sleep(0.5)
            n_detect = len(scorer.detect_requests)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-off", room.kind))
            plain = run_steps(bus, scores, renderer, views, "ep-off", range(2))
            assert all(s.object_evidence is None for s in plain)
            assert len(scorer.detect_requests) == n_detect
            assert errors.empty(), errors.get()
        finally:
            mapper.stop()
            stopper.stop()
            scorer.stop()


def test_a_detector_failure_does_not_fail_the_question(hub_settings: Settings, settings: Settings, chair_views,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    """The pool's detector refuses (EQA_DETECTOR_BACKEND=remote is an error reply): the step's scores are still
    published, without evidence, and the mapper logs why."""
    _, renderer, views = chair_views
    cfg = settings.model_copy(update={"scorer_replica": "qobj-bad", "object_evidence": True,
                                      "detector_backend": "remote"})
    scores: queue.Queue[StepScores] = queue.Queue()
    with Bus(hub_settings, "gateway") as bus:
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_SCORES), StepScores, lambda k, m: scores.put(m))
        scorer = CountingScorer(cfg)
        scorer.start()
        mapper = MapperService(cfg)
        mapper.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-bad", "kitchen"))
            with caplog.at_level("WARNING", logger="services.mapper.question_objects"):
                (s,) = run_steps(bus, scores, renderer, views, "ep-bad", range(1))
            assert len(scorer.detect_requests) == 1  # it was asked
            assert s.object_evidence is None and len(s.answer_probs) == len(YESNO)
            assert "detection failed, no object evidence this step" in caplog.text
        finally:
            mapper.stop()
            scorer.stop()
