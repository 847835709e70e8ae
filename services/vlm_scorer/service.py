"""The scorer replica: a Zenoh queryable on ``eqa/v1/scorer/{replica}/score`` serving ScoreRequests.

The replica id is ``EQA_SCORER_REPLICA`` (default: the instance id); the bus instance is set to it, so the
liveliness token ``eqa/v1/alive/vlm_scorer/{replica}`` names the same replica as the queryable key, which is
how :class:`eqa.scorer_client.ScorerClient` finds it.

Concurrency (``Bus.declare_queryable(serial=True)``): the Zenoh callback only queues the query; one worker
thread decodes, scores and replies, so a replica serves one request at a time (a model is not safe to share
between threads, and on CPU a second concurrent forward pass only competes for the same cores) and queues the
rest. Scale with replicas.

Dynamic batching (``EQA_SCORER_BATCH_MAX`` > 1, ``EQA_SCORER_BATCH_WINDOW_MS``): the worker takes the requests
that queued while it was busy (and, with a window, those that arrive within it) as one batch, and the steps of
several robots go through the model in one forward pass (:meth:`handle_many`); each request still gets its own
reply or error. On the hf backend the values are the same per request as unbatched
(tests/scorer/test_scorer_batching.py).

Errors are replies, never crashes: a malformed request, a bad image, an empty question, too many choices or
a backend that could not load (missing model directory, not a vision-language model) give an
:class:`eqa.messages.ErrorReply` with the reason, and the replica keeps serving.

Monitoring: with recording on, the visually prompted image of each step is logged to the episode's Rerun
recording (``EpisodeRecorder(settings, episode_id, "vlm_scorer")``, entity ``camera/annotated``).
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from typing import Any

from eqa import keys, logs, metrics
from eqa.bus import Bus
from eqa.messages import (
    DetectRequest,
    DetectResult,
    ErrorReply,
    Message,
    ScoreRequest,
    ScoreResult,
    ValueRequest,
    ValueResult,
)
from eqa.recording import EpisodeRecorder
from eqa.service import SHELL_GROUPS, Service
from eqa.settings import (
    ObjectLayerSettings,
    ScorerSettings,
    SettingsGroup,
    SimulatedDetectorSettings,
    SimulatedPerceptionSettings,
    StopperSettings,
    view,
)
from eqa.store import Store
from services.vlm_scorer.backends import Backend, make_backend
from services.vlm_scorer.backends.base import Scores
from services.vlm_scorer.detector import Detector, make_detector
from services.vlm_scorer.target_values import target_values
from services.vlm_scorer.visual_prompt import annotate

log = logging.getLogger(__name__)

ANNOTATED_ENTITY = "camera/annotated"
MAX_OPEN_RECORDINGS = 4


class ScorerService(Service):
    """VLM scorer replica (Explore-EQA Eq. 1, 2, 5 and the answer distribution) as a Zenoh queryable."""

    name = "vlm_scorer"
    description = "VLM scorer replica: answers ScoreRequests on eqa/v1/scorer/{replica}/score."
    # the backends' and the detector's (real and simulated); StopperSettings: whether answers are joint
    settings_groups = (*SHELL_GROUPS, ScorerSettings, SimulatedPerceptionSettings, ObjectLayerSettings,
                       SimulatedDetectorSettings, StopperSettings)

    def __init__(
        self,
        settings: SettingsGroup,
        bus: Bus | None = None,
        store: Store | None = None,
        *,
        backend: Backend | None = None,
    ) -> None:
        settings = view(settings, self.settings_groups)
        self.replica = keys.check_id(settings.scorer_replica or settings.instance, "replica")
        super().__init__(settings, bus or Bus(settings, self.name, self.replica), store)
        self.backend = backend
        self.backend_error: str | None = None
        self.detector: Detector | None = None  # HELIOS detector (EQA_DETECTOR_BACKEND), made on first request
        self.detector_error: str | None = None
        self._queryable: Any = None
        self._recorders: OrderedDict[str, EpisodeRecorder] = OrderedDict()
        self.served = 0

    @property
    def key(self) -> str:
        return keys.scorer_replica(self.replica)

    def setup(self) -> None:
        if self.backend is None:
            try:
                self.backend = make_backend(self.settings)
            except Exception as exc:
                self.backend_error = f"scorer backend {self.settings.scorer_backend!r} is unavailable: {exc}"
                log.error("%s; replying with this error to every request", self.backend_error)
        if self.settings.answer_memory_mode == "joint" and self.backend is not None and \
                not callable(getattr(self.backend, "answer_from_views", None)):
            log.error("EQA_ANSWER_MEMORY_MODE=joint, but scorer backend %r takes one image per prompt: every joint "
                      "answer request is refused (the mapper then keeps the single-view answer); use the hf "
                      "backend, or EQA_ANSWER_MEMORY_MODE=fusion with EQA_ANSWER_MEMORY_K", self.backend.name)
        self._queryable = self.bus.declare_queryable(
            self.key, (ScoreRequest, DetectRequest, ValueRequest), self._route, serial=True,
            batch_handler=self.handle_many, batch_max=self.settings.scorer_batch_max,
            batch_window_s=self.settings.scorer_batch_window_ms / 1000.0,
        )
        log.info("scorer replica %s on %s (backend %s, batches of up to %d, window %.0f ms)", self.replica, self.key,
                 self.settings.scorer_backend, self.settings.scorer_batch_max, self.settings.scorer_batch_window_ms)

    def teardown(self) -> None:
        if self._queryable is not None:
            self._queryable.undeclare()  # stop serving (the request in hand is answered) before the backend closes
        for rec in self._recorders.values():
            rec.close()
        self._recorders.clear()
        if self.backend is not None:
            self.backend.close()
        if self.detector is not None:
            self.detector.close()

    # ---- serving (eqa.bus.Bus.declare_queryable decodes, answers errors and replies) -------------------
    def _route(self, request: ScoreRequest | DetectRequest | ValueRequest) -> Message:
        with logs.bind(service=self.name, episode=request.episode_id, step=request.step), \
                metrics.timer(metrics.REPLICA_SECONDS, request.kind, "served") as timed:
            reply = self._answer(request)
            if isinstance(reply, ErrorReply):
                timed.relabel(request.kind, "refused")
            return reply

    def _answer(self, request: ScoreRequest | DetectRequest | ValueRequest) -> Message:
        if isinstance(request, DetectRequest):
            return self.handle_detect(request)
        if isinstance(request, ValueRequest):
            return self.handle_values(request)
        return self.handle(request)

    def handle(self, req: ScoreRequest) -> Message:
        """Score one request (the in-process call; the queryable wraps it)."""

        def error(reason: str) -> ErrorReply:
            return ErrorReply(
                source=f"vlm_scorer/{self.replica}",
                reason=reason,
                episode_id=req.episode_id,
                step=req.step,
                request_id=req.request_id,
            )

        if self.backend_error is not None or self.backend is None:
            return error(self.backend_error or "scorer backend is not loaded")
        if req.memory_views:
            return self.handle_joint(req, error)
        t0 = time.perf_counter()
        try:
            scores = self.backend.score(req)
        except Exception as exc:
            return self._scored(req, exc, 0.0)
        return self._scored(req, scores, (time.perf_counter() - t0) * 1000.0)

    def handle_many(self, requests: list[ScoreRequest | DetectRequest | ValueRequest]) -> list[Message]:
        """A batch of queued requests (``EQA_SCORER_BATCH_MAX`` > 1): the single-view score requests go to the
        backend together (:meth:`Backend.score_many`: one merged forward pass on hf, results split back per
        request; a request that fails gets its own error), the others one by one, every reply in order."""
        out: list[Message | None] = [None] * len(requests)
        plain = [(i, r) for i, r in enumerate(requests) if isinstance(r, ScoreRequest) and not r.memory_views]
        if len(plain) > 1 and self.backend is not None and self.backend_error is None:
            t0 = time.perf_counter()
            try:
                results: list[Scores | Exception] = self.backend.score_many([r for _, r in plain])
            except Exception as exc:  # a backend's own score_many must not raise; if it does, each is told
                results = [exc] * len(plain)
            latency = (time.perf_counter() - t0) * 1000.0  # the batch's time, which each of its requests waited
            for (i, req), res in zip(plain, results, strict=True):
                out[i] = self._scored(req, res, latency)
        return [o if o is not None else self._route(r) for o, r in zip(out, requests, strict=True)]

    def _scored(self, req: ScoreRequest, scores: Scores | Exception, latency: float) -> Message:
        """The reply to one score request: its result, or the error its scoring raised."""
        assert self.backend is not None
        if isinstance(scores, Exception):
            exc = scores
            if isinstance(exc, (ValueError, RuntimeError)):  # BadRequest, BackendUnavailable, RemoteError
                log.warning("score request %s (episode %s step %d) refused: %s", req.request_id, req.episode_id,
                            req.step, exc)
                reason = str(exc)
            else:
                log.error("scorer backend failed on %s", req.request_id, exc_info=exc)
                reason = f"{type(exc).__name__}: {exc}"
            return ErrorReply(source=f"vlm_scorer/{self.replica}", reason=reason, episode_id=req.episode_id,
                              step=req.step, request_id=req.request_id)
        self.served += 1
        self._record(req, scores)
        return ScoreResult(
            request_id=req.request_id,
            episode_id=req.episode_id,
            step=req.step,
            answer_probs=scores.answer_probs,
            relevance=scores.relevance,
            lsv=scores.lsv,
            gsv=scores.gsv,
            backend=self.backend.name,
            model=self.backend.model_name,
            replica=self.replica,
            latency_ms=latency,
            proposed_choices=scores.proposed_choices,
            mode=scores.mode,
            resolution=scores.resolution,
            object_yes=scores.object_yes,
            in_room=scores.in_room,
        )

    def handle_joint(self, req: ScoreRequest, error: Any) -> Message:
        """Joint answer memory: the answer distribution over the request's ``memory_views`` in ONE
        prompt (``answer_from_views``: backends that take several images, i.e. hf); others refuse."""
        assert self.backend is not None
        joint = getattr(self.backend, "answer_from_views", None)
        if not callable(joint):
            return error(f"scorer backend {self.backend.name!r} cannot answer from several views in one prompt "
                         "(joint answer memory needs the hf backend; use EQA_ANSWER_MEMORY_MODE=fusion)")
        t0 = time.perf_counter()
        try:
            probs = joint(list(req.memory_views), req.question, req.question.choices)
        except (ValueError, RuntimeError) as exc:
            log.warning("joint answer request %s (episode %s step %d) refused: %s", req.request_id,
                        req.episode_id, req.step, exc)
            return error(str(exc))
        except Exception as exc:
            log.exception("joint answer failed on %s", req.request_id)
            return error(f"{type(exc).__name__}: {exc}")
        self.served += 1
        return ScoreResult(
            request_id=req.request_id, episode_id=req.episode_id, step=req.step, answer_probs=list(probs),
            relevance=0.0, backend=self.backend.name, model=self.backend.model_name, replica=self.replica,
            latency_ms=(time.perf_counter() - t0) * 1000.0, mode="logprobs",  # softmax over the choice letters
        )

    # ---- HELIOS: detections and per-target values ------------------------------------------------------
    def _detector(self) -> Detector | None:
        if self.detector is None and self.detector_error is None:
            try:
                self.detector = make_detector(self.settings)
            except Exception as exc:
                self.detector_error = f"detector backend {self.settings.detector_backend!r} is unavailable: {exc}"
                log.error("%s; replying with this error to every detection request", self.detector_error)
        return self.detector

    def _error_for(self, req: DetectRequest | ValueRequest, reason: str) -> ErrorReply:
        return ErrorReply(
            source=f"vlm_scorer/{self.replica}", reason=reason, episode_id=req.episode_id, step=req.step,
            request_id=req.request_id,
        )

    def handle_detect(self, req: DetectRequest) -> Message:
        """Detections of one frame (the in-process call; the queryable wraps it)."""
        detector = self._detector()
        if detector is None:
            return self._error_for(req, self.detector_error or "detector is not loaded")
        t0 = time.perf_counter()
        try:
            dets = detector.detect(req)
        except (ValueError, RuntimeError) as exc:
            log.warning("detect request %s (episode %s step %d) refused: %s", req.request_id, req.episode_id,
                        req.step, exc)
            return self._error_for(req, str(exc))
        except Exception as exc:
            log.exception("detector failed on %s", req.request_id)
            return self._error_for(req, f"{type(exc).__name__}: {exc}")
        self.served += 1
        return DetectResult(
            request_id=req.request_id, episode_id=req.episode_id, step=req.step, detections=dets,
            backend=detector.name, model=detector.model_name, replica=self.replica,
            latency_ms=(time.perf_counter() - t0) * 1000.0,
        )

    def handle_values(self, req: ValueRequest) -> Message:
        """P(Yes) of "Seems like there is a (target) ahead" per target (HELIOS 3.1.2)."""
        if self.backend_error is not None or self.backend is None:
            return self._error_for(req, self.backend_error or "scorer backend is not loaded")
        t0 = time.perf_counter()
        try:
            values = target_values(self.backend, req)
        except (ValueError, RuntimeError) as exc:
            return self._error_for(req, str(exc))
        except Exception as exc:
            log.exception("value prompt failed on %s", req.request_id)
            return self._error_for(req, f"{type(exc).__name__}: {exc}")
        self.served += 1
        return ValueResult(
            request_id=req.request_id, episode_id=req.episode_id, step=req.step, values=values,
            backend=self.backend.name, model=self.backend.model_name, replica=self.replica,
            latency_ms=(time.perf_counter() - t0) * 1000.0,
        )

    # ---- monitoring -----------------------------------------------------------------------------------
    def _recorder(self, episode_id: str) -> EpisodeRecorder:
        rec = self._recorders.pop(episode_id, None)
        if rec is None:
            rec = EpisodeRecorder(self.settings, episode_id, self.name)
            while len(self._recorders) >= MAX_OPEN_RECORDINGS:
                _, old = self._recorders.popitem(last=False)
                old.close()
        self._recorders[episode_id] = rec
        return rec

    def _record(self, req: ScoreRequest, scores: Scores) -> None:
        if not self.settings.record or len(req.prompt_points) < 2:
            return
        try:
            import rerun as rr

            image = scores.annotated if scores.annotated is not None else annotate(req.rgb, req.prompt_points)
            rec = self._recorder(req.episode_id)
            rec.set_step(req.step)
            rec.log(ANNOTATED_ENTITY, rr.Image(image))
        except Exception:
            log.exception("recording the annotated image failed; going on")
