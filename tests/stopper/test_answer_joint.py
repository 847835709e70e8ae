"""Joint answer memory in the live services (EQA_ANSWER_MEMORY_MODE=joint): a question episode
through the real mapper and scorer replica (hf backend on a tiny random Qwen2-VL built offline: its
probabilities are meaningless, the plumbing is real) on Zenoh. The mapper keeps the K most relevant views, asks
the pool for one multi-image answer whenever that set changes, and the StepScores carry it; the memory survives
a mapper restart. Fusion mode (the default) sends no memory request; a one-image backend (oracle) refuses and
the episode keeps the per-view answer. Too many / too large views are refused off the bus."""

from __future__ import annotations

import queue
import time

import numpy as np
import pytest
from support.fleet import wait_for
from support.objects import ring_views, run_steps

from eqa import keys
from eqa.bus import Bus
from eqa.codec import CodecError
from eqa.messages import (
    MAX_MEMORY_VIEWS,
    EpisodeStart,
    ErrorReply,
    Message,
    Question,
    ScoreRequest,
    StepScores,
    StopConfig,
    decode,
    encode,
)
from eqa.settings import Settings
from services.mapper.answer_views import AnswerViews, shrink
from services.mapper.service import MapperService
from services.sim.housegen import generate_house
from services.sim.render import Renderer
from services.stopper.calibration import TraceStore
from services.stopper.service import StopperService
from services.vlm_scorer.backends.hf import HFBackend
from services.vlm_scorer.service import ScorerService
from services.vlm_scorer.tiny import build_tiny_qwen2vl

ROBOT = "r0"
W, H = 160, 120
Q = Question(text="What colour is the sofa?", choices=["red", "blue", "green", "grey"], scene="gen-5")


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> HFBackend:
    return HFBackend(build_tiny_qwen2vl(tmp_path_factory.mktemp("tiny") / "qwen2vl"))


@pytest.fixture(scope="module")
def views():
    scene = generate_house(5)
    renderer = Renderer(scene)
    return renderer, ring_views(scene, renderer, 25, W, H)


class CountingScorer(ScorerService):
    """The real scorer replica; keeps the joint (memory) requests it serves (nothing else changed)."""

    def __init__(self, settings: Settings, backend=None) -> None:
        super().__init__(settings, backend=backend)
        self.joint: list[ScoreRequest] = []

    def handle(self, req: ScoreRequest) -> Message:
        if req.memory_views:
            self.joint.append(req)
        return super().handle(req)


def start(episode_id: str) -> EpisodeStart:
    return EpisodeStart(episode_id=episode_id, robot=ROBOT, question=Q, max_steps=20, record=False, seed=1,
                        stop=StopConfig(rule="max_steps"))


def test_joint_answer_through_mapper_and_scorer(hub_settings: Settings, settings: Settings, backend: HFBackend,
                                                views, redis_url: str) -> None:
    renderer, vs = views
    base = settings.model_copy(update={"redis_url": redis_url, "scorer_replica": "joint", "scorer_backend": "hf"})
    joint = base.model_copy(update={"answer_memory_mode": "joint", "answer_memory_views": 2})
    scores: queue.Queue[StepScores] = queue.Queue()
    errors: queue.Queue[ErrorReply] = queue.Queue()
    with Bus(hub_settings, "gateway") as bus:
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_SCORES), StepScores, lambda k, m: scores.put(m))
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_ERROR), ErrorReply, lambda k, m: errors.put(m))
        scorer = CountingScorer(joint, backend=backend)
        scorer.start()
        stopper = StopperService(joint)
        stopper.start()
        mapper = MapperService(joint)
        mapper.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-j"))
            got = run_steps(bus, scores, renderer, vs, "ep-j", range(4))
            assert errors.empty(), errors.get()
            views_kept = mapper.answer_memory.memories["ep-j"]
            assert len(views_kept.steps) == 2  # the memory is full (K = 2)
            # one joint request per change of the kept set, the last one holding K images
            assert 1 <= len(scorer.joint) <= 4 and len(scorer.joint[-1].memory_views) == 2
            assert [len(r.memory_views) for r in scorer.joint][:2] == [1, 2]
            kept_images = [np.asarray(im) for im in views_kept.images]
            for a, b in zip(scorer.joint[-1].memory_views, kept_images, strict=True):
                assert np.array_equal(a, b)
            want = backend.answer_from_views(kept_images, Q, Q.choices)
            assert got[-1].answer_views == sorted(views_kept.steps)
            assert got[-1].answer_probs == pytest.approx(want, abs=1e-5)
            assert got[0].answer_views == [0] and all(s.answer_views for s in got)
            assert all(s.mode == "logprobs" for s in got)  # the scorer's mode is kept
            # the stopper's trace (what `eqa calibrate` learns CP from) holds the joint answers
            traces = TraceStore(stopper.store)
            wait_for(lambda: (t := traces.trace_for_episode("ep-j")) is not None and len(t.steps) == 4, 15.0)
            trace = traces.trace_for_episode("ep-j")
            assert trace is not None and len(trace.steps) == 4
            for s, st in zip(got, trace.steps, strict=True):
                assert st.answer_probs == pytest.approx(s.answer_probs)
            # relevance is the step's own (the scorer's single-view Rel), not touched by the memory
            assert sorted(views_kept.relevance) == sorted(sorted(s.relevance for s in got)[-2:])

            # a restarted mapper continues the stored memory (images included)
            kept_steps = list(views_kept.steps)
            mapper.stop()
            mapper = MapperService(joint)
            mapper.start()
            time.sleep(0.5)
            run_steps(bus, scores, renderer, vs, "ep-j", range(4, 5))
            restored = mapper.answer_memory.memories["ep-j"]
            assert len(restored.steps) == 2 and set(restored.steps) <= set(kept_steps) | {4}
            if 4 not in restored.steps:  # the view of step 4 did not enter: the stored images are the same
                for a, b in zip(restored.images, kept_images, strict=True):
                    assert np.array_equal(a, b)
            assert errors.empty(), errors.get()
            mapper.stop()

            # fusion (the default): no memory request, the per-view answer
            n = len(scorer.joint)
            mapper = MapperService(base)
            mapper.start()
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-f"))
            plain = run_steps(bus, scores, renderer, vs, "ep-f", range(3))
            assert len(scorer.joint) == n and all(not s.answer_views for s in plain)
            assert "ep-f" not in mapper.answer_memory.memories
        finally:
            mapper.stop()
            stopper.stop()
            scorer.stop()


def test_one_image_backend_refuses_and_the_episode_keeps_the_per_view_answer(
        hub_settings: Settings, settings: Settings, views, redis_url: str) -> None:
    renderer, vs = views
    joint = settings.model_copy(update={"redis_url": redis_url, "scorer_replica": "oracle",
                                        "answer_memory_mode": "joint", "answer_memory_views": 2})
    scores: queue.Queue[StepScores] = queue.Queue()
    with Bus(hub_settings, "gateway") as bus:
        bus.subscribe(keys.stream(ROBOT, keys.MAPPER_SCORES), StepScores, lambda k, m: scores.put(m))
        scorer = CountingScorer(joint)
        scorer.start()
        mapper = MapperService(joint)
        mapper.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start("ep-o"))
            got = run_steps(bus, scores, renderer, vs, "ep-o", range(3))
            assert len(scorer.joint) == 1  # refused once, then not asked again in this episode
            assert "ep-o" not in mapper.answer_memory.memories and all(not s.answer_views for s in got)
            assert abs(sum(got[-1].answer_probs) - 1) < 1e-6
        finally:
            mapper.stop()
            scorer.stop()


def test_memory_views_are_validated_off_the_bus() -> None:
    img = np.zeros((H, W, 3), np.uint8)
    ok = ScoreRequest(episode_id="e", step=0, question=Q, rgb=img, memory_views=[img] * MAX_MEMORY_VIEWS)
    assert len(decode(encode(ok), ScoreRequest).memory_views) == MAX_MEMORY_VIEWS
    bad = [
        [img] * (MAX_MEMORY_VIEWS + 1),  # too many
        [np.zeros((10, 449, 3), np.uint8)],  # too large
        [np.zeros((10, 10, 3), np.float32)],  # not uint8
        [np.zeros((10, 10), np.uint8)],  # not RGB
    ]
    for views_ in bad:
        forged = ScoreRequest.model_construct(**{**dict(ok), "memory_views": views_})
        with pytest.raises(CodecError, match="memory_views"):
            decode(encode(forged), ScoreRequest)


def test_view_memory_keeps_the_k_most_relevant_bounded() -> None:
    views_kept = AnswerViews(2)
    big = np.zeros((960, 1280, 3), np.uint8)
    assert views_kept.offer(0, 0.2, big) and views_kept.offer(1, 0.1, big)
    assert not views_kept.offer(2, 0.1, big)  # a tie: the earlier view stays
    assert views_kept.offer(3, 0.5, big) and views_kept.steps == [0, 3]
    assert all(max(im.shape[:2]) <= 448 for im in views_kept.images) and shrink(big).shape == (320, 427, 3)
    again = AnswerViews.restore(views_kept.snapshot())
    assert again.steps == views_kept.steps and again.relevance == views_kept.relevance
    with pytest.raises(ValueError):
        AnswerViews(MAX_MEMORY_VIEWS + 1)
    with pytest.raises(ValueError):
        AnswerViews.restore({**views_kept.snapshot(), "steps": [0, 1, 2], "relevance": [0, 0, 0], "images": [big] * 3})


def test_view_memory_is_bounded_in_views_and_pixels() -> None:
    """The K most relevant views the mapper keeps for a joint answer (services/mapper/answer_views.py)."""
    from eqa.messages import MAX_MEMORY_VIEW_SIDE

    mem = AnswerViews(k=3)
    rng = np.random.default_rng(0)
    rels = rng.random(40)
    for t, rel in enumerate(rels):
        mem.offer(t, rel, np.zeros((480, 640, 3), np.uint8))
        assert len(mem.steps) <= 3
    assert sorted(mem.steps) == sorted(np.argsort(-rels)[:3].tolist())
    assert all(max(im.shape[:2]) <= MAX_MEMORY_VIEW_SIDE for im in mem.images)
    assert mem.nbytes <= 3 * MAX_MEMORY_VIEW_SIDE**2 * 3
    assert not mem.offer(99, -1.0, np.zeros((4, 4, 3), np.uint8))  # worse than every kept view
    with pytest.raises(ValueError):
        AnswerViews(k=MAX_MEMORY_VIEWS + 1)


def test_joint_mode_refuses_a_second_pooling_in_the_stopper() -> None:
    """Joint answers pooled again by the stopper (EQA_ANSWER_MEMORY_K > 0) would be a rule nobody calibrated."""
    import pydantic

    from eqa.settings import Settings

    assert Settings(answer_memory_mode="joint").answer_memory_k == 0
    assert Settings(answer_memory_mode="fusion", answer_memory_k=2).answer_memory_k == 2
    with pytest.raises(pydantic.ValidationError, match="EQA_ANSWER_MEMORY_K=0"):
        Settings(answer_memory_mode="joint", answer_memory_k=2)
