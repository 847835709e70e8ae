"""Run many questions through the real services and collect their per-step scores (traces).

A :class:`Runner` starts a fleet (every pipeline service as its own process, several scorer replicas if asked)
and drives several simulated robots at once: it publishes one ``EpisodeStart`` per free robot with the
stopping rule ``max_steps`` (full-length runs: until it stops, a robot's path does not depend on the stopping
rule, so every rule and threshold is later evaluated by replaying these traces), records every
``StepScores`` of the episode, and yields a :class:`services.stopper.calibration.Trace` when the stopper ends
the episode. Episodes are seeded from the question id, so a rerun gives the same trace.

:func:`collect_traces` adds resumption: traces are stored (``TraceStore``) as they finish and questions
with a stored trace are skipped. ``eqa calibrate`` and ``eqa bench`` use it.
"""

from __future__ import annotations

import hashlib
import logging
import queue
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

from eqa import keys
from eqa.launcher import PIPELINE, Fleet
from eqa.messages import (
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    ErrorReply,
    Question,
    StepScores,
    StopConfig,
    Strategy,
    new_id,
)
from eqa.settings import Settings
from eqa.store import open_store

log = logging.getLogger(__name__)


def question_seed(question_id: str) -> int:
    """A stable 31-bit seed per question (start-pose sampling, frontier sampling, oracle noise)."""
    return int.from_bytes(hashlib.sha256(question_id.encode()).digest()[:4], "little") & 0x7FFFFFFF


def yardstick_paths(question: Question, strategy: str, scenes_path: Any, scene: Any = None) -> Any:
    """The ground truth the ``target_oracle`` yardstick plans with (:func:`services.sim.paths.target_paths`:
    walked distances to the question's targets through the true house), for its :class:`EpisodeStart`; None
    for every other strategy. ``scene``: the loaded scene, if the caller has it."""
    if strategy != "target_oracle" or not question.targets:
        return None
    from services.sim.library import load_or_generate
    from services.sim.paths import target_paths

    return target_paths(scene if scene is not None else load_or_generate(question.scene, scenes_path),
                        question.targets)


@dataclass
class _Running:
    question: Question
    episode_id: str
    robot: str
    max_steps: int
    started: float
    last_seen: float
    scores: dict[int, StepScores] = field(default_factory=dict)


@dataclass
class RunResult:
    """One finished full-length episode."""

    question: Question
    episode_id: str
    steps: list[StepScores]
    end: EpisodeEnd | None
    reason: str
    seconds: float
    answer_counting: str | None = None  # the stopper's trace: counting across views pooled into the steps' f

    def trace(self, strategy: str) -> Any:
        from services.stopper.calibration import Trace, TraceStep

        return Trace(
            question_id=self.question.id,
            scene=self.question.scene,
            category=self.question.category,
            choices=self.question.choices,
            answer=self.question.answer,
            max_steps=self.question.max_steps or max(len(self.steps), 1),
            strategy=strategy,
            steps=[TraceStep(answer_probs=s.answer_probs, relevance=s.relevance) for s in self.steps],
            episode_id=self.episode_id,
            end_reason=self.reason,
            answer_counting=self.answer_counting,
        )


def _stopper_trace(settings: Settings, episode_id: str) -> Any:
    """The trace the stopper stored for the episode (exactly the steps it decided on), or None."""
    from services.stopper.calibration import TraceStore

    with open_store(settings) as store:
        return TraceStore(store).trace_for_episode(episode_id)


class Runner:
    """Full-length episodes of many questions over ``robots`` simulated robots through a real fleet."""

    def __init__(
        self,
        settings: Settings,
        strategy: Strategy = "semantic",
        robots: int = 2,
        scorers: int = 1,
        step_timeout_s: float = 120.0,
        record: bool = False,
    ) -> None:
        if robots < 1:
            raise ValueError("robots must be at least 1")
        self.settings = settings.model_copy(update={"record": record})
        self.strategy = strategy
        self.robots = [f"bench{i}" for i in range(robots)]
        self.scorers = scorers
        self.step_timeout_s = step_timeout_s
        self.record = record
        self._inbox: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.fleet: Fleet | None = None

    def __enter__(self) -> Runner:
        self.fleet = Fleet(self.settings, services=PIPELINE, scorers=self.scorers).start()
        bus = self.fleet.hub
        for pair in (keys.MAPPER_SCORES, keys.EPISODE_END, keys.SIM_ERROR):
            from eqa.messages import STREAM_TYPES

            bus.subscribe(keys.any_robot(pair), STREAM_TYPES[pair], lambda k, m: self._inbox.put((k, m)))
        time.sleep(0.3)  # let the subscriptions propagate before the first start
        return self

    def __exit__(self, *exc: object) -> None:
        if self.fleet is not None:
            self.fleet.stop()
            self.fleet = None

    def _start(self, robot: str, question: Question) -> _Running:
        assert self.fleet is not None
        if question.max_steps is None:
            raise ValueError(f"question {question.id} has no max_steps")
        episode_id = new_id("run")
        start = EpisodeStart(
            episode_id=episode_id,
            robot=robot,
            question=question,
            strategy=self.strategy,
            stop=StopConfig(rule="max_steps"),
            max_steps=question.max_steps,
            seed=question_seed(question.id),
            draws=question.id,  # the simulated detector's draws are the question's, as in the in-process runner
            record=self.record,
            target_paths=yardstick_paths(question, self.strategy, self.settings.scenes_path),
        )
        self.fleet.hub.publish(keys.stream(robot, keys.EPISODE_START), start)
        now = time.monotonic()
        return _Running(question, episode_id, robot, question.max_steps, now, now)

    def run(self, questions: Iterable[Question]) -> Iterator[RunResult]:
        """Yield one result per question (in completion order)."""
        if self.fleet is None:
            raise RuntimeError("use the Runner as a context manager")
        pending = list(questions)
        pending.reverse()
        running: dict[str, _Running] = {}
        free = list(self.robots)
        while pending or running:
            while free and pending:
                robot = free.pop(0)
                run = self._start(robot, pending.pop())
                running[run.episode_id] = run
            try:
                _key, msg = self._inbox.get(timeout=1.0)
            except queue.Empty:
                msg = None
            now = time.monotonic()
            if msg is not None:
                run = running.get(getattr(msg, "episode_id", "") or "")
                if run is not None:
                    run.last_seen = now
                    done = self._handle(run, msg)
                    if done is not None:
                        del running[run.episode_id]
                        free.append(run.robot)
                        yield done
            for run in list(running.values()):
                if now - run.last_seen > self.step_timeout_s:
                    reason = f"no progress for {self.step_timeout_s:.0f} s (missing: {self._missing()})"
                    log.error("episode %s of %s: %s", run.episode_id, run.question.id, reason)
                    self.fleet.hub.publish(
                        keys.stream(run.robot, keys.EPISODE_CANCEL), EpisodeCancel(episode_id=run.episode_id,
                                                                                    reason=reason)
                    )
                    del running[run.episode_id]
                    free.append(run.robot)
                    yield self._result(run, None, f"failed: {reason}")

    def _missing(self) -> str:
        assert self.fleet is not None
        missing = [c.service for c in self.fleet.missing()]
        return ", ".join(missing) or "none"

    def _handle(self, run: _Running, msg: Any) -> RunResult | None:
        if isinstance(msg, StepScores):
            run.scores[msg.step] = msg
            return None
        if isinstance(msg, EpisodeEnd):
            return self._result(run, msg, msg.reason)
        if isinstance(msg, ErrorReply) and (msg.step in (None, 0)) and not run.scores:
            # The sim could not start the episode (unknown scene, no valid start pose): nothing will come.
            self.fleet.hub.publish(  # type: ignore[union-attr]
                keys.stream(run.robot, keys.EPISODE_CANCEL), EpisodeCancel(episode_id=run.episode_id,
                                                                            reason=msg.reason)
            )
            return self._result(run, None, f"failed: {msg.source}: {msg.reason}")
        return None

    def _result(self, run: _Running, end: EpisodeEnd | None, reason: str) -> RunResult:
        # The stopper's stored trace is authoritative: the last StepScores may reach us after the EpisodeEnd
        # (two publishers, two Zenoh threads), and the stopper saw every step it decided on.
        stored = _stopper_trace(self.settings, run.episode_id) if end is not None else None
        counting = stored.answer_counting if stored is not None else None
        if stored is not None:
            for t, s in enumerate(stored.steps):
                if t not in run.scores:
                    run.scores[t] = StepScores(episode_id=run.episode_id, step=t, answer_probs=s.answer_probs,
                                               relevance=s.relevance)
                elif counting is not None:  # the f the stopper decided on: the VLM's pooled with the room's count
                    run.scores[t] = run.scores[t].model_copy(update={"answer_probs": s.answer_probs})
        steps = [run.scores[t] for t in sorted(run.scores)]
        # Keep the contiguous prefix: a trace is a causal sequence of steps 0..t.
        contiguous = [s for i, s in enumerate(steps) if s.step == i]
        if len(contiguous) != len(steps):
            log.warning("episode %s: scores of steps %s missing", run.episode_id,
                        sorted(set(range(len(steps))) - set(run.scores)))
        return RunResult(run.question, run.episode_id, contiguous, end, reason, time.monotonic() - run.started,
                         counting)


def collect_traces(
    questions: list[Question],
    settings: Settings,
    strategy: Strategy = "semantic",
    set_name: str = "default",
    progress: Any = None,
    robots: int = 2,
    scorers: int = 1,
) -> Iterator[Any]:
    """Run the questions without a stored trace in ``set_name``; store and yield each trace as it finishes."""
    from services.stopper.calibration import TraceStore

    with open_store(settings) as store:
        traces = TraceStore(store)
        missing = [q for q in questions if not traces.has(set_name, q.id)]
        if not missing:
            return
        with Runner(settings, strategy=strategy, robots=robots, scorers=scorers) as runner:
            for result in runner.run(missing):
                if not result.steps:
                    log.error("question %s produced no step (%s); not stored", result.question.id, result.reason)
                    if progress is not None:
                        progress.set_postfix_str(f"failed {result.question.id}")
                    continue
                trace = result.trace(strategy)
                traces.save(set_name, trace)
                if progress is not None:
                    progress.set_postfix_str(f"{result.question.id}: {len(result.steps)} steps, {result.seconds:.0f} s")
                yield trace
