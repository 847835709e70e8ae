"""Full-length episodes with the services' pure cores in one process (``eqa bench --runner cores``).

The fleet (:mod:`eqa_app.benchmark_runner`) runs every service as its own process over Zenoh; on a shared
2-core machine that costs several times the CPU of the work itself (bus, per-step map snapshots in the
store, five processes). :func:`run_episode_loop` calls the same step functions the services call, in the
services' order, in one process: the simulator's renderer and goal check (:func:`services.sim.motion.pose_error`),
the mapper's :class:`services.mapper.episode_map.EpisodeMap` (integrate, Eq. 3 values, Eq. A6 frontiers), the
scorer backend's ``score`` (the question without its ground truth, as the mapper sends it) and the planner's
step with the planner service's refusal policy (:mod:`services.planner.refusals`). Seeds are the fleet's
(:func:`eqa_app.benchmark_runner.question_seed`, per-step planner generators), so a question gives the same
trace either way up to float32 rounding (``tests/fleet/test_core_runner_golden.py`` runs tuning-seed questions
through both). Every in-process runner (:func:`core_episode`, :mod:`eqa_app.stop_sensitivity`,
``eqa_app/benches/tune_oracle.py``, ``eqa_app/benches/tune_explore.py``, ``eqa_app/benches/object_evidence.py``) is
this loop with its own :class:`StepHooks`. It is not a replacement for the fleet's end-to-end test, and figures say
which runner made them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from eqa.messages import Frame, MapUpdate, Pose2D, Question, ScoreRequest, Strategy
    from services.mapper.episode_map import EpisodeMap
    from services.planner.step import PlannerParams, StepPlan
    from services.sim.render import Renderer
    from services.sim.scene import Scene


def observe_step(renderer: Renderer, emap: EpisodeMap, episode_id: str, step: int, pose: Pose2D, K: Any,
                 w: int, h: int, blind: Question, seed: int) -> tuple[Frame, ScoreRequest]:
    """One step's perception as the services do it: the sim's frame at ``pose`` (camera, render, labels) is
    integrated into the mapper's :class:`~services.mapper.episode_map.EpisodeMap`; returns the frame and the
    :class:`~eqa.messages.ScoreRequest` the mapper sends for it (``blind``: the question without its ground
    truth)."""
    from eqa.messages import Frame, ScoreRequest
    from services.sim import camera

    cam = camera.camera_pose(pose)
    r = renderer.render(cam, K, w, h)
    frame = Frame(episode_id=episode_id, step=step, pose=pose, camera_pose=cam, intrinsics=K,
                  rgb=r.rgb, depth=r.depth, instances=r.instances, labels=renderer.labels(r.instances))
    emap.integrate(frame)
    return frame, ScoreRequest(episode_id=episode_id, step=step, question=blind, rgb=frame.rgb,
                               prompt_points=emap.prompts, instances=frame.instances, labels=frame.labels,
                               depth=frame.depth, seed=seed)


class StepHooks:
    """What one in-process runner records (or changes) at each step of :func:`run_episode_loop`; the loop
    itself is the services'. The defaults record nothing and change nothing."""

    def request(self, step: int, request: ScoreRequest) -> ScoreRequest:
        """The step's score request as the mapper's extensions send it (:meth:`MapperExtension.score_request`)."""
        return request

    def scored(self, step: int, frame: Frame, request: ScoreRequest, scores: Any) -> None:
        """The scorer's reply of the step, before the mapper applies its values."""

    def mapped(self, step: int, emap: EpisodeMap, step_map: MapUpdate) -> None:
        """The mapper's update of the step (every step, the last one too)."""

    def steer(self, step: int, step_map: MapUpdate, scores: Any) -> MapUpdate | None:
        """The map the planner plans this step on (the stopper's decision reaches the planner first: a
        ``cp_guided`` runner re-weights it, and None ends the episode as a stop)."""
        return step_map

    def moved(self, step: int, step_map: MapUpdate, plan: StepPlan, before: Pose2D) -> None:
        """The goal the simulator took at ``step`` (from ``before`` to ``plan.pose``)."""


@dataclass
class EpisodeCores:
    """The parts one in-process episode runs on: the scene and its renderer, the scorer backend, the
    mapper's episode map, the planner's constants, the image size."""

    scene: Scene
    renderer: Renderer
    scorer: Any
    emap: EpisodeMap
    params: PlannerParams
    width: int
    height: int


def goal_refusal(scene: Scene, plan: StepPlan) -> str | None:
    """The simulator service's reply to a goal (``services.sim.service`` ``on_goal``): its reason to refuse
    it, or None when it takes it."""
    from eqa.robot import NO_POSE
    from services.sim.motion import pose_error

    if plan.pose is None:
        return NO_POSE
    reason = pose_error(scene, plan.pose)
    return None if reason is None else f"goal refused: {reason}"


def run_episode_loop(question: Question, strategy: Strategy, cores: EpisodeCores, *, episode_id: str, seed: int,
                     steps: int | None = None, hooks: StepHooks | None = None) -> str:
    """Run one episode of ``question`` for at most ``steps`` steps (default ``question.max_steps``); returns
    why it ended: ``"step limit"``, ``"stopped"`` (``hooks.steer`` returned None) or ``"planner done: ..."``."""
    from services.planner.refusals import Refusals, plan_attempt, plan_until_accepted
    from services.planner.sampling import step_rng
    from services.planner.step import Memory
    from services.sim import camera

    hooks = hooks or StepHooks()
    budget = int(question.max_steps if steps is None else steps)
    K = camera.intrinsics(cores.width, cores.height)
    pose = question.start_pose
    if pose is None:
        raise ValueError(f"question {question.id} has no start pose")
    memory = Memory()
    blind = question.without_ground_truth()
    for step in range(budget):
        frame, req = observe_step(cores.renderer, cores.emap, episode_id, step, pose, K, cores.width, cores.height,
                                  blind, seed)
        req = hooks.request(step, req)
        scores = cores.scorer.score(req)
        hooks.scored(step, frame, req, scores)
        cores.emap.apply_scores(scores.lsv, scores.gsv)
        cores.emap.compute_frontiers()
        step_map = cores.emap.map_update()
        hooks.mapped(step, cores.emap, step_map)
        if step + 1 >= budget:
            break
        steered = hooks.steer(step, step_map, scores)
        if steered is None:
            return "stopped"
        refusals = Refusals(step, steered.pose, len(steered.frontiers), memory, cores.params.turn_deg)
        plan = plan_until_accepted(
            refusals,
            lambda r, m=steered, s=step: plan_attempt(m, strategy, r, step_rng(seed, s, r.attempt), cores.params),
            lambda p: goal_refusal(cores.scene, p),
        )
        if plan.done or plan.pose is None:
            return f"planner done: {plan.reason}"
        hooks.moved(step, steered, plan, pose)
        memory, pose = plan.memory, plan.pose
    return "step limit"


class _TraceSteps(StepHooks):
    def __init__(self) -> None:
        from services.stopper.calibration import TraceStep

        self.step_type = TraceStep
        self.steps: list[Any] = []

    def scored(self, step: int, frame: Frame, request: ScoreRequest, scores: Any) -> None:
        self.steps.append(self.step_type(answer_probs=list(scores.answer_probs), relevance=float(scores.relevance)))


class _CountingTrace(_TraceSteps):
    """Counting across views (``EQA_ANSWER_COUNTING=views``) as the services do it: the mapper's
    :class:`~services.mapper.question_objects.QuestionObjectsExtension` (its IN_ROOM prompt, detections of the
    simulated detector in-process, the room's extent, the step's evidence) and the stopper's :func:`decide`, whose
    record holds the pooled ``f`` the fleet's stopper traces hold."""

    def __init__(self, settings: Any, start: Any, emap: EpisodeMap) -> None:
        from eqa.messages import DetectResult, StopConfig
        from services.mapper.extension import MapperContext
        from services.mapper.question_objects import QuestionObjectsExtension
        from services.stopper.state import EpisodeRecord
        from services.vlm_scorer.detector import make_detector

        super().__init__()
        detector = make_detector(settings)

        def detect(req: Any) -> Any:
            return DetectResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                                detections=detector.detect(req), backend=settings.detector_backend)

        def no_values(req: Any) -> Any:
            raise RuntimeError("a question episode asks no value prompts")

        def report(robot: str, episode_id: str | None, step: int | None, reason: str) -> None:
            raise RuntimeError(f"episode {episode_id} step {step}: {reason}")

        self.start, self.emap = start, emap
        self.ext = QuestionObjectsExtension(MapperContext(settings, None, report, detector=detect, values=no_values))
        self.ext.begin(emap, None, restored=False)
        self.record = EpisodeRecord.from_start(start, start.robot)
        self.record.stop = StopConfig(rule="max_steps")  # a trace runs full length
        self.record.object_evidence = (settings.object_evidence_psi_min, settings.object_evidence_weight)
        self.record.evidence_categories = ["counting"]
        self.pending: tuple[Any, Any] | None = None

    def request(self, step: int, request: ScoreRequest) -> ScoreRequest:
        return self.ext.score_request(self.emap, request)

    def scored(self, step: int, frame: Frame, request: ScoreRequest, scores: Any) -> None:
        from services.mapper.extension import StepOutputs

        self.ext.scores(self.emap, frame, scores, StepOutputs(), {}, again=False)
        self.pending = (frame, scores)

    def mapped(self, step: int, emap: EpisodeMap, step_map: MapUpdate) -> None:
        from eqa.messages import StepScores
        from services.mapper.extension import StepOutputs
        from services.stopper.calibration import TraceStep
        from services.stopper.state import decide

        assert self.pending is not None
        frame, scores = self.pending
        out = StepOutputs()
        self.ext.apply(self.start.robot, emap, frame, self.ext.submit(self.start.robot, emap, frame), out, {})
        decide(self.record, StepScores(episode_id=self.start.episode_id, step=step,
                                       answer_probs=list(scores.answer_probs), relevance=float(scores.relevance),
                                       choices=list(self.start.question.choices), object_evidence=out.object_evidence))
        self.steps = [TraceStep(answer_probs=p, relevance=r)
                      for p, r in zip(self.record.probs, self.record.relevance, strict=True)]

    def close(self) -> None:
        self.ext.close()


def core_episode(args: tuple[Any, str, dict[str, Any]]) -> Any:
    """One full-length episode of ``question`` with ``strategy`` under ``settings`` (a ``model_dump``); returns a
    :class:`services.stopper.calibration.Trace` (its ``end_reason`` says why it ended)."""
    from eqa.messages import EpisodeStart
    from eqa.settings import Settings
    from eqa_app.benchmark_runner import question_seed, yardstick_paths
    from services.mapper.episode_map import EpisodeMap, MapperConfig
    from services.mapper.question_objects import question_target
    from services.planner.step import PlannerParams
    from services.sim.library import load_or_generate
    from services.sim.render import Renderer
    from services.stopper.calibration import Trace
    from services.vlm_scorer.backends import make_backend

    question, strategy, settings_dump = args
    settings = Settings.model_validate(settings_dump)
    scene = load_or_generate(question.scene, settings.scenes_path)
    seed = question_seed(question.id)
    start = EpisodeStart(episode_id=f"cores-{question.id}", robot="cores", question=question, strategy=strategy,
                         max_steps=question.max_steps, seed=seed, record=False, draws=question.id,
                         target_paths=yardstick_paths(question, strategy, settings.scenes_path, scene))
    emap = EpisodeMap(start, MapperConfig(tau_lsv=settings.tau_lsv, tau_gsv=settings.tau_gsv, tau_sv=settings.tau_sv,
                                          tau_sv_normal=settings.tau_sv_normal, view_bins=settings.view_bins,
                                          view_agree=settings.view_agree))
    cores = EpisodeCores(scene, Renderer(scene), make_backend(settings), emap, PlannerParams(),
                         settings.sim_width, settings.sim_height)
    target = question_target(question)
    counting = settings.answer_counting == "views" and target is not None and target[0] == "counting"
    trace = _CountingTrace(settings, start, emap) if counting else _TraceSteps()
    try:
        reason = run_episode_loop(question, strategy, cores, episode_id=start.episode_id, seed=seed, hooks=trace)
    finally:
        if isinstance(trace, _CountingTrace):
            trace.close()
    return Trace(question_id=question.id, scene=question.scene, category=question.category,
                 choices=question.choices, answer=question.answer, max_steps=question.max_steps, strategy=strategy,
                 steps=trace.steps, episode_id=start.episode_id, end_reason=reason,
                 answer_counting="views" if isinstance(trace, _CountingTrace) and trace.record.count_latest else None)
