"""Full-length benchmark episodes with the services' pure cores in one process (``eqa bench --runner cores``).

The fleet (:mod:`eqa.app.benchmark_runner`) runs every service as its own process over Zenoh; on a shared
2-core machine that costs several times the CPU of the work itself (bus, per-step map snapshots in the
store, five processes). This runner calls the same step functions the services call, in the services' order,
in one process per worker: the simulator's renderer and goal check (:func:`services.sim.motion.pose_error`),
the mapper's :class:`services.mapper.episode_map.EpisodeMap` (integrate, Eq. 3 values, Eq. A6 frontiers), the
scorer backend's ``score`` (the question without its ground truth, as the mapper sends it) and the planner's
:func:`services.planner.step.plan_step` with the planner service's handling of a refused goal (the frontier
excluded for the step, the pose remembered as refused, a turn in place after ``MAX_REFUSALS``). Seeds are the
fleet's (:func:`eqa.app.benchmark_runner.question_seed`, per-step planner generators), so a question gives the
same trace either way up to float32 rounding (checked on 30 evaluation-seed questions, fbe and semantic: 30 of 30
traces equal within 1e-6, ``bench/results/explore-seeds/fleet-check/``).
It is not a replacement for the fleet's end-to-end test, and figures say which runner made them.
"""

from __future__ import annotations

import math
from typing import Any


def observe_step(renderer: Any, emap: Any, episode_id: str, step: int, pose: Any, K: Any, w: int, h: int,
                 blind: Any, seed: int) -> Any:
    """One step's perception as the services do it: the sim's frame at ``pose`` (camera, render, labels) is
    integrated into the mapper's :class:`~services.mapper.episode_map.EpisodeMap`; returns the
    :class:`~eqa.messages.ScoreRequest` the mapper sends for it (``blind``: the question without its ground
    truth). Every in-process runner (this module, :mod:`eqa.app.stop_sensitivity`, ``bench/tune_oracle.py``,
    ``bench/tune_explore.py``) calls it."""
    from eqa.messages import Frame, ScoreRequest
    from services.sim import camera

    cam = camera.camera_pose(pose)
    r = renderer.render(cam, K, w, h)
    frame = Frame(episode_id=episode_id, step=step, pose=pose, camera_pose=cam, intrinsics=K,
                  rgb=r.rgb, depth=r.depth, instances=r.instances, labels=renderer.labels(r.instances))
    emap.integrate(frame)
    return ScoreRequest(episode_id=episode_id, step=step, question=blind, rgb=frame.rgb, prompt_points=emap.prompts,
                        instances=frame.instances, labels=frame.labels, depth=frame.depth, seed=seed)


def core_episode(args: tuple[Any, str, dict[str, Any]]) -> Any:
    """One full-length episode of ``question`` with ``strategy`` under ``settings`` (a ``model_dump``); returns a
    :class:`services.stopper.calibration.Trace` (its ``end_reason`` says why it ended)."""
    from eqa.app.benchmark_runner import question_seed
    from eqa.messages import EpisodeStart, Pose2D
    from eqa.settings import Settings
    from services.mapper.episode_map import EpisodeMap, MapperConfig
    from services.planner.sampling import step_rng
    from services.planner.service import MAX_REFUSALS
    from services.planner.step import Memory, PlannerParams, StepPlan, plan_step
    from services.sim import camera
    from services.sim.library import load_or_generate
    from services.sim.motion import pose_error
    from services.sim.render import Renderer
    from services.stopper.calibration import Trace, TraceStep
    from services.vlm_scorer.backends import make_backend

    question, strategy, settings_dump = args
    settings = Settings.model_validate(settings_dump)
    w, h = settings.sim_width, settings.sim_height
    scene = load_or_generate(question.scene, settings.scenes_path)
    renderer = Renderer(scene)
    scorer = make_backend(settings)
    seed = question_seed(question.id)
    start = EpisodeStart(episode_id=f"cores-{question.id}", robot="cores", question=question, strategy=strategy,
                         max_steps=question.max_steps, seed=seed, record=False)
    emap = EpisodeMap(start, MapperConfig(tau_lsv=settings.tau_lsv, tau_gsv=settings.tau_gsv, tau_sv=settings.tau_sv,
                                          tau_sv_normal=settings.tau_sv_normal, view_bins=settings.view_bins,
                                          view_agree=settings.view_agree))
    params = PlannerParams()
    K = camera.intrinsics(w, h)
    pose = question.start_pose
    memory = Memory()
    blind = question.model_copy(update={"answer": None, "evidence_ids": [], "targets": []})
    steps: list[Any] = []
    reason = "step limit"
    for step in range(question.max_steps):
        req = observe_step(renderer, emap, start.episode_id, step, pose, K, w, h, blind, seed)
        scores = scorer.score(req)
        steps.append(TraceStep(answer_probs=list(scores.answer_probs), relevance=float(scores.relevance)))
        emap.apply_scores(scores.lsv, scores.gsv)
        emap.compute_frontiers()
        mu = emap.map_update()
        if step + 1 >= question.max_steps:
            break
        before = memory.copy()
        excluded: list[tuple[float, float]] = []
        refused: list[tuple[float, float]] = []
        plan: StepPlan | None = None
        for attempt in range(MAX_REFUSALS + 2):
            mem = before.copy()
            mem.refused.extend(refused)
            if attempt > MAX_REFUSALS:  # the planner service turns in place after MAX_REFUSALS refusals
                mem.target = None
                yaw = mu.pose.yaw + math.radians(params.turn_deg)
                plan = StepPlan("turn", "refused goals: turning in place",
                                pose=Pose2D(x=mu.pose.x, y=mu.pose.y, yaw=math.atan2(math.sin(yaw), math.cos(yaw))),
                                memory=mem)
            else:
                plan = plan_step(mu.grid, mu.free, mu.occupied, mu.pose, mu.frontiers, strategy, mem,
                                 step_rng(seed, step, attempt), params, exclude=excluded)
            if plan.done or plan.pose is None or pose_error(scene, plan.pose) is None:
                break
            if plan.kind == "turn":
                plan = StepPlan("done", "the simulator refused a turn in place", memory=before)
                break
            if plan.frontier is not None:
                excluded.append((plan.frontier.x, plan.frontier.y))
            if math.hypot(plan.pose.x - mu.pose.x, plan.pose.y - mu.pose.y) > 0.05:
                refused.append((plan.pose.x, plan.pose.y))
        assert plan is not None
        if plan.done or plan.pose is None:
            reason = f"planner done: {plan.reason}"
            break
        memory, pose = plan.memory, plan.pose
    return Trace(question_id=question.id, scene=question.scene, category=question.category,
                 choices=question.choices, answer=question.answer, max_steps=question.max_steps, strategy=strategy,
                 steps=steps, episode_id=start.episode_id, end_reason=reason)
