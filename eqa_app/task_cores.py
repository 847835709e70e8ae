"""Task episodes with the services' pure cores in one process (``eqa bench ovmm|objectnav --runner cores``).

A task episode through the fleet (:func:`eqa_app.task_bench.run_tasks`) costs minutes on the shared 2-core
machine: five processes, the bus, per-step map snapshots in the store. :func:`run_task_episode` calls the same
step functions the services call, in the services' order, in one process, as :mod:`eqa_app.core_runner` does for
questions:

* simulator (``services.sim.service`` ``on_goal`` / ``_emit``): the goal check
  (:func:`eqa_app.core_runner.goal_refusal`), the move, the frame rendered at the goal with a held object
  hidden, :meth:`services.sim.task_runner.SimTask.after_goal` (the motion's collisions, then the skill; the
  frame rendered again after a successful pick), ``observe`` (FindObj / FindRec) and the trace entry;
* mapper (``services.mapper.service`` ``on_frame``): :meth:`EpisodeMap.integrate`, the frame's detections and
  value prompts answered by the scorer pool's own functions (the detector's ``detect``,
  :func:`services.vlm_scorer.target_values.target_values`), :func:`services.mapper.object_shell.fuse_frame`,
  the frontiers from the phase's value layer, :func:`services.mapper.object_shell.attach_objects`;
* stopper (``max_steps`` rule): the episode ends after the frame of step ``max_steps - 1``, or when the planner
  is done;
* planner (``services.planner.service`` ``_plan_and_publish``): :meth:`services.planner.task_runner.PlannerTask.goal`
  with the per-attempt generator :func:`services.planner.sampling.step_rng` and the refusal policy of
  :class:`services.planner.refusals.Refusals` (a refused goal is planned again from the machine's state before
  the step; after the policy's last refusal its turn in place is taken).

The question's own scores (Explore-EQA's layer) are not computed: in a task episode no decision reads them (the
frontiers take their values from the task layer of the phase, the stopper's rule is ``max_steps``). With the
fleet's episode id and seed a task gives the same trace either way (``tests/tasks/test_task_cores.py`` runs tuning-seed
tasks through both); the detector draws from (seed, episode id, step), so two runs with different episode ids are
two draws of the simulated detector.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from eqa.messages import EpisodeStart, Goal, Question, StopConfig, Task

if TYPE_CHECKING:
    from eqa.settings import Settings
    from eqa_app.task_results import TaskResult

log = logging.getLogger(__name__)


def task_start(task: Task, variant: str, max_steps: int, pick_limit: int | None, episode_id: str, robot: str,
               seed: int) -> EpisodeStart:
    """The ``EpisodeStart`` of one benchmark run (the fleet's and the in-process runner's)."""
    q = Question(text=task.text, scene=task.scene, start_pose=task.start_pose, max_steps=max_steps)
    return EpisodeStart(episode_id=episode_id, robot=robot, question=q, stop=StopConfig(rule="max_steps"),
                        max_steps=max_steps, seed=seed, record=False, task=task,
                        ablation=variant, pick_limit=pick_limit)  # type: ignore[arg-type]


@dataclass
class TaskCores:
    """What in-process task episodes share across runs: the settings, the scorer backend and detector (both
    stateless per request), the scenes and renderers by id."""

    settings: Settings
    backend: Any
    detector: Any
    scenes: dict[str, tuple[Any, Any]]

    @classmethod
    def from_settings(cls, settings: Settings) -> TaskCores:
        from services.vlm_scorer.backends import make_backend
        from services.vlm_scorer.detector import make_detector

        return cls(settings, make_backend(settings), make_detector(settings), {})

    def scene(self, scene_id: str) -> tuple[Any, Any]:
        """The scene and its renderer (kept for the next run in the same house)."""
        if scene_id not in self.scenes:
            from services.sim.library import load_or_generate
            from services.sim.render import Renderer

            while len(self.scenes) >= 4:  # a benchmark runs its houses in order; keep memory bounded
                self.scenes.pop(next(iter(self.scenes)))
            scene = load_or_generate(scene_id, self.settings.scenes_path)
            self.scenes[scene_id] = (scene, Renderer(scene))
        return self.scenes[scene_id]

    def close(self) -> None:
        for part in (self.backend, self.detector):
            close = getattr(part, "close", None)
            if callable(close):
                close()


def run_task_episode(cores: TaskCores, start: EpisodeStart,
                     home: Any = None) -> tuple[str, str, dict[str, float], dict[str, Any]]:
    """One task episode of ``start`` in process (module doc). Returns the end state (``stopped`` / ``failed``),
    its reason, the simulator's metrics and the stored trace (:meth:`TaskEpisode.trace_doc`). ``home``: the
    mapper's :class:`~services.mapper.home_shell.HomeMemory` for an episode whose ``start.home`` is set (the
    service's calls: start, candidate keyframes, the first frame's re-detection, the commit at the end)."""
    from eqa.messages import DetectResult, Frame, ValueResult
    from services.mapper.episode_map import EpisodeMap, MapperConfig
    from services.mapper.object_map import ObjectMap, ObjectMapConfig
    from services.mapper.object_map import task_classes as object_classes
    from services.mapper.object_shell import ask_objects, attach_objects, fuse_frame, task_map_config, value_layer
    from services.mapper.semantic_map import QUESTION_LAYER
    from services.planner.step import Memory, PlannerParams
    from services.planner.task_fsm import Thresholds
    from services.planner.task_runner import PlannerTask
    from services.sim import camera
    from services.sim.motion import pose_error
    from services.sim.task_runner import SimTask
    from services.vlm_scorer.target_values import target_values

    s = cores.settings
    task = start.task
    if task is None:
        raise ValueError(f"episode {start.episode_id} has no task")
    scene, renderer = cores.scene(task.scene)
    pose = task.start_pose
    if pose is None:
        raise ValueError(f"task {task.id} has no start pose")
    why = pose_error(scene, pose)
    if why is not None:
        return "failed", f"sim: start pose refused: {why}", {}, {}
    sim = SimTask.from_start(start, scene, pose)
    assert sim is not None
    w, h = s.sim_width, s.sim_height
    K = camera.intrinsics(w, h)

    # mapper: the map with the task's value layers, the object layer (single frames for the trusting agent)
    om_config = ObjectMapConfig.from_settings(s)
    om = ObjectMap.for_task(task, om_config, single_frame=start.ablation == "trusting")
    classes, _ = object_classes(task, om_config)
    emap = EpisodeMap(start, task_map_config(MapperConfig(tau_lsv=s.tau_lsv, tau_gsv=s.tau_gsv, tau_sv=s.tau_sv,
                                                          tau_sv_normal=s.tau_sv_normal, view_bins=s.view_bins,
                                                          view_agree=s.view_agree)),
                      layers=[QUESTION_LAYER, *(value_layer(c) for c in classes)])
    if home is not None:
        home.start(start, emap, om)

    def detect(req: Any) -> Any:
        return DetectResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                            detections=cores.detector.detect(req), backend=cores.detector.name,
                            model=cores.detector.model_name, replica="cores")

    def values(req: Any) -> Any:
        return ValueResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                           values=target_values(cores.backend, req), backend=cores.backend.name,
                           model=cores.backend.model_name, replica="cores")

    # planner
    planner = PlannerTask.from_start(start, Thresholds.from_settings(s))
    assert planner is not None
    params = PlannerParams()
    memory = Memory()

    def render(step: int, at: Any) -> Frame:
        held = sim.episode.held_id
        cam = camera.camera_pose(at)
        out = renderer.render(cam, K, w, h, frozenset() if held is None else frozenset({held}))
        return Frame(episode_id=start.episode_id, step=step, pose=at, camera_pose=cam, intrinsics=K, rgb=out.rgb,
                     depth=out.depth, instances=out.instances, labels=renderer.labels(out.instances),
                     scene=scene.id, floor_area_m2=scene.floor_area_m2)

    goal: Goal | None = None
    before = None
    reason = f"step limit reached ({start.max_steps} steps)"
    for step in range(start.max_steps):
        # simulator: the motion of the goal, the frame at its pose, the goal's skill
        frame = render(step, pose)
        skill = None
        if goal is not None and before is not None and frame.instances is not None:
            skill = sim.after_goal(scene, before, goal, frame.instances)
            if skill is not None and skill.skill == "pick" and skill.success:
                frame = render(step, pose)  # the picked object is in the gripper now, not in view
        frame.skill = skill
        if frame.instances is not None:
            sim.observe(scene, pose, frame.instances)
        sim.record(step, pose, goal, frame.skill)
        # mapper
        emap.integrate(frame)
        if home is not None:
            home.offer_view(emap, frame)
            if step == 0:
                home.warm_objects(emap, om, frame, lambda: detect)
        det, val = ask_objects(om, emap, frame, detect, values)
        timing: dict[str, float] = {}
        layer, errors = fuse_frame(om, emap, frame, det, val, timing)
        for e in errors:
            log.warning("episode %s step %d: %s", start.episode_id, step, e)
        emap.compute_frontiers(layer)
        update = emap.map_update()
        update.skill = frame.skill
        attach_objects(om, emap, update, frame, timing)
        # stopper (max_steps): the last step's frame ends the episode
        if step + 1 >= start.max_steps:
            break
        # planner, with the simulator's refusals
        goal, plan = plan_task_step(planner, scene, update, memory, params, start, step)
        if plan.done or goal.pose is None:
            sim.episode.end_reason = goal.reason[:300]
            reason = f"task ended: {goal.reason or 'the planner is done'}"
            break
        memory = plan.memory
        before, pose = pose, goal.pose
    if home is not None:
        home.commit(emap, om)
    return "stopped", reason, sim.metrics(), sim.episode.trace_doc()


def plan_task_step(planner: Any, scene: Any, update: Any, memory: Any, params: Any, start: EpisodeStart,
                   step: int) -> tuple[Goal, Any]:
    """The planner service's goal for a task step (``_plan_and_publish``): the state machine's goal, planned
    again from its state before the step while the simulator refuses it
    (:func:`services.planner.refusals.plan_until_accepted`); the policy's own turn in place (or done) is
    published without task fields."""
    from eqa_app.core_runner import goal_refusal
    from services.planner.refusals import Refusals, plan_until_accepted
    from services.planner.sampling import step_rng

    refusals = Refusals(step, update.pose, len(update.frontiers), memory.copy(), params.turn_deg)
    state_before = planner.to_json()
    chosen: list[tuple[Goal, Any]] = []

    def attempt(r: Refusals) -> Any:
        goal, plan = planner.goal(start.episode_id, update, r.memory(), step_rng(start.seed, step, r.attempt),
                                  params, before=state_before if r.attempt else None)
        chosen.append((goal, plan))
        return plan

    plan = plan_until_accepted(refusals, attempt, lambda p: goal_refusal(scene, p))
    if chosen and chosen[-1][1] is plan:
        return chosen[-1][0], plan
    return Goal(episode_id=start.episode_id, step=step, pose=plan.pose, path=plan.path, frontier=plan.frontier,
                weights=plan.probabilities, done=plan.done, reason=plan.reason), plan


def cores_episode_id(task_id: str, max_steps: int) -> str:
    """The episode id of an in-process run of a task: a function of the task and its step budget, the same for
    every variant and pick limit. The simulated detector draws from (seed, episode id, step, instance), so a run
    gives the same trace every time, and the variants of a task meet the same detector draws (common random
    numbers for their paired comparison). The fleet takes fresh ids: its store keys and the services'
    ended-episode records are per id."""
    import hashlib

    return "task-" + hashlib.sha256(f"{task_id}|{max_steps}".encode()).hexdigest()[:12]


def run_tasks_cores(settings: Settings, jobs: list[Any], progress: bool = True,
                    on_result: Any = None, episode_ids: list[str] | None = None) -> list[TaskResult]:
    """Run ``(task, variant, max_steps, pick_limit)`` jobs in process, one after the other (the same contract
    as :func:`eqa_app.task_bench.run_tasks`). ``episode_ids``: one per job (default: :func:`cores_episode_id`, so a
    run of the same job gives the same trace)."""
    from eqa_app.task_results import TaskResult, task_seed

    out: list[TaskResult] = []
    cores = TaskCores.from_settings(settings)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="task episodes (in process)", unit="ep")
    try:
        for i, job in enumerate(jobs):
            task, variant, steps = job[0], job[1], job[2]
            limit = job[3] if len(job) > 3 else None
            eid = episode_ids[i] if episode_ids is not None else cores_episode_id(task.id, steps)
            start = task_start(task, variant, steps, limit, eid, "cores", task_seed(task.id))
            t0 = time.monotonic()
            try:
                state, reason, metrics, trace = run_task_episode(cores, start)
            except Exception as exc:
                log.exception("task %s (%s) failed in process", task.id, variant)
                state, reason, metrics, trace = "failed", f"{type(exc).__name__}: {exc}", {}, {}
            out.append(TaskResult(task.id, task.kind, variant, steps, metrics, state, reason,
                                  time.monotonic() - t0, limit, trace or None))
            if on_result is not None:
                on_result(out[-1])
            if bar is not None:
                bar.update(1)
    finally:
        cores.close()
        if bar is not None:
            bar.close()
    return out
