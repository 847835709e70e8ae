"""The mapper service shell: Frame -> TSDF map, prompt points, scores, semantic values, frontiers.

Per step (one :class:`Frame`): validate and integrate it, project to 2D, compute the prompt points, ask the
scorer pool for the step's scores, write the semantic values (Eq. 3), compute the frontiers with their
Eq. A6 weights, publish :class:`MapUpdate` and :class:`StepScores`.
Beside the map the service holds its extensions (:mod:`services.mapper.extension`: one protocol, one plain
object each, called in the order of ``extensions``): the HELIOS object layer and per-target value layers of a
task episode, fed by detections and value prompts from the scorer pool (:mod:`services.mapper.object_shell`),
the object evidence of a question episode (:mod:`services.mapper.question_objects`) and the joint answer memory
(:mod:`services.mapper.answer_views`).

Per-episode state (:class:`eqa.episode_service.EpisodeService`, ``eqa:mapper:episode:{episode_id}``): the
episode's map as an incremental snapshot (:mod:`services.mapper.snapshots`: a header there, a full part and the
deltas since under ``eqa:mapper:part:{episode_id}:*``), written before the step's outputs are published; a
restarted mapper picks the episode up from there when the next frame arrives. A frame that overtakes its
``EpisodeStart`` waits for it (one per episode, bounded in bytes, for ``EARLY_FRAME_TTL_S``).

Errors go to ``MAPPER_ERROR`` as :class:`ErrorReply` with the reason: a bad frame (the map is unchanged), an
unknown episode, a scorer failure (the map update is still published, the stopper gets no scores for that
step). A frame of the last integrated step is the simulator sending that step again (``EQA_STEP_RESEND_S``:
no goal came back): its map update and scores are published again without integrating it twice; an older
frame is a stale re-delivery and is ignored.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from eqa import grid, keys
from eqa.bus import Bus
from eqa.episode_service import EpisodeService, StateParts
from eqa.messages import (
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    ErrorReply,
    Frame,
    ScoreRequest,
    ScoreResult,
    StepScores,
)
from eqa.recording import EpisodeRecorder
from eqa.service import SHELL_GROUPS
from eqa.settings import (
    HeliosSettings,
    HomeSettings,
    ObjectLayerSettings,
    PlannerSettings,
    ScorerSettings,
    SettingsGroup,
    StopperSettings,
)
from eqa.store import Store
from services.mapper import snapshots
from services.mapper.answer_views import AnswerViewsExtension
from services.mapper.episode_map import EpisodeMap, MapperConfig, Timer
from services.mapper.extension import (
    Detect,
    MapperContext,
    MapperExtension,
    Scorer,
    StepOutputs,
    Values,
    call_pool,
    failure,
)
from services.mapper.home_shell import HomeMemory
from services.mapper.object_shell import ObjectLayerExtension, task_map_config
from services.mapper.question_objects import QuestionObjectsExtension
from services.mapper.semantic_map import QUESTION_LAYER
from services.mapper.tsdf import FrameError

log = logging.getLogger(__name__)

EARLY_FRAME_TTL_S = 30.0
MADE_KEY = "made"  # the stored state's part with the last map update's sent_at and timings


class MapperService(EpisodeService[EpisodeMap]):
    """TSDF mapping, frontiers, prompt points and the semantic value map (Explore-EQA IV-B..D)."""

    name = "mapper"
    description = (
        "Mapper: TSDF fusion, 2D maps, frontiers with Eq. A6 weights, prompt points, semantic values."
    )
    error_stream = keys.MAPPER_ERROR
    hold_ttl_s = EARLY_FRAME_TTL_S
    hold_max_per_episode = 1  # the frame of step 0; a second one of an unknown episode is refused
    persist_answers = False  # the snapshot is the state; a resent step is answered from it (answer_again)
    state_ttl_s = 7 * 24 * 3600.0
    # PlannerSettings: Eq. A6 temperatures and view bins of the value layers; ScorerSettings: the pool's timeout;
    # HELIOS and its object layer; StopperSettings: joint answer memory and object evidence; homes
    settings_groups = (*SHELL_GROUPS, PlannerSettings, ScorerSettings, HeliosSettings, ObjectLayerSettings,
                       StopperSettings, HomeSettings)

    def __init__(self, settings: SettingsGroup, bus: Bus | None = None, store: Store | None = None, *,
                 scorer: Scorer | None = None, detector: Detect | None = None, values: Values | None = None) -> None:
        super().__init__(settings, bus, store)
        self.context = MapperContext(self.settings, self.bus, self.error, scorer=scorer, detector=detector,
                                     values=values)
        self.object_layer = ObjectLayerExtension(self.context)  # HELIOS object layer of task episodes
        self.question_objects = QuestionObjectsExtension(self.context)  # object evidence of question episodes
        self.answer_memory = AnswerViewsExtension(self.context)  # joint answer memory (EQA_ANSWER_MEMORY_MODE)
        # home memory and warm start: after the object layer, whose state it starts and writes back
        self.homes = HomeMemory(self.settings, lambda: self.store, self.scorer, objects=self.object_layer.maps.get,
                                detect=lambda: self.context.detect_and_values()[0])
        # the order of the calls and of the stored state's parts (a new extension goes at the end)
        self.extensions: list[MapperExtension] = [self.object_layer, self.question_objects, self.answer_memory,
                                                  self.homes]
        self.config = MapperConfig(
            tau_lsv=self.settings.tau_lsv,
            tau_gsv=self.settings.tau_gsv,
            tau_sv=self.settings.tau_sv,
            tau_sv_normal=self.settings.tau_sv_normal,
            view_bins=self.settings.view_bins,
            view_agree=self.settings.view_agree,
        )
        self.last_timing_ms: dict[str, float] = {}
        # runs the scorer round trip of a step while the handler thread does the score-independent work
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mapper-score")

    def setup_episodes(self) -> None:
        self.on_step(keys.SIM_FRAME, self.on_frame)

    def teardown(self) -> None:
        self._pool.shutdown(wait=True)
        for ext in self.extensions:
            ext.close()
        super().teardown()

    # ---- scorer -----------------------------------------------------------------------------------------
    def scorer(self) -> Scorer:
        return self.context.score()

    # ---- episode state ----------------------------------------------------------------------------------
    def start_episode(self, robot: str, start: EpisodeStart) -> EpisodeMap:
        log.info("episode %s: mapping for robot %s (strategy %s)", start.episode_id, robot, start.strategy)
        # a task episode's map sees low obstacles (task_map_config); a question's keeps the figures' map
        config = self.config if start.task is None else task_map_config(self.config)
        episode_map = EpisodeMap(start, config, layers=[QUESTION_LAYER])
        for ext in self.extensions:
            ext.begin(episode_map, None, restored=False)
        return episode_map

    def finish_episode(self, robot: str, msg: EpisodeCancel | EpisodeEnd, state: EpisodeMap) -> None:
        for ext in reversed(self.extensions):  # the home writes back the object layer before it is dropped
            ext.finish(state)
        log.info("episode %s finished (%s); map dropped", msg.episode_id, msg.kind)

    def dump_state(self, state: EpisodeMap, **extra: Any) -> Any:
        # The extensions' parts ride along ({"map": ..., "objects": ..., ...}); without any, the map's bytes. The
        # map is an incremental snapshot (snapshots.py): its header here, the full part and deltas as parts.
        header, write, delete = snapshots.snapshot_step(state)
        state_header: Any = header
        for ext in self.extensions:
            part = ext.dump(state.episode_id)
            if part is not None:
                state_header = snapshots.with_state_part(state_header, ext.state_key, part)
        if state.made is not None:
            state_header = snapshots.with_state_part(state_header, MADE_KEY, {
                "step": state.step, "sent_at": state.made[0], "timing_ms": dict(state.made[1])})
        return StateParts(state_header, write, delete)

    def load_state(self, episode_id: str, data: Any) -> EpisodeMap:
        data, made = snapshots.without_state_part(data, MADE_KEY)
        parts: dict[str, Any] = {}
        for ext in self.extensions:
            data, parts[ext.state_key] = snapshots.without_state_part(data, ext.state_key)
        if isinstance(data, dict):  # parts of an extension this mapper does not have
            log.warning("episode %s: stored parts %s belong to no extension here; left aside", episode_id,
                        sorted(k for k in data if k != "map"))
            data = data["map"]
        episode_map = snapshots.restore(data, lambda part: self.read_part(episode_id, part), self.config)
        if episode_map.start.task is not None:  # the task map's configuration, as at its start
            episode_map.config = task_map_config(episode_map.config)
        for ext in self.extensions:
            ext.begin(episode_map, parts[ext.state_key], restored=True)
        if isinstance(made, dict) and made.get("step") == episode_map.step:
            episode_map.made = (float(made["sent_at"]), {str(k): float(v) for k, v in dict(made["timing_ms"]).items()})
        log.info("episode %s: restored from snapshot at step %d", episode_id, episode_map.step)
        return episode_map

    def answered_step(self, episode_id: str, state: EpisodeMap) -> int:
        return state.step

    def answer_again(self, robot: str, state: EpisodeMap, msg: Frame) -> None:
        self._republish(robot, state, msg)

    def unknown_episode(self, robot: str, msg: Any, why: str) -> None:
        self.error(robot, msg.episode_id, getattr(msg, "step", None),
                   f"unknown episode: no EpisodeStart seen and no snapshot ({why})")

    def _error(self, robot: str, episode_id: str | None, step: int | None, reason: str) -> None:
        self.error(robot, episode_id, step, reason)

    # ---- handlers ---------------------------------------------------------------------------------------
    def on_frame(self, robot: str, episode_map: EpisodeMap, frame: Frame) -> None:
        t_start = time.perf_counter()
        timer = Timer()
        try:
            episode_map.integrate(frame, timer)
        except FrameError as exc:
            self._error(robot, frame.episode_id, frame.step, f"frame rejected, map unchanged: {exc}")
            return
        out = StepOutputs()
        for ext in self.extensions:  # e.g. the home's view memory re-scored at the first frame in a known home
            ext.observe(robot, episode_map, frame, out, timer.ms)

        # The scorer round trip is mostly waiting (another process, the bus): meanwhile this thread does the
        # step's work that does not depend on the scores: the frontier candidates. Same results, same order of
        # effects (snapshot saved before anything is published).
        pending = self._pool.submit(self._timed_score, robot, episode_map, frame)
        # the extensions' own requests (detections, value prompts) on their workers meanwhile
        pending_ext: list[Future[Any] | None] = [ext.submit(robot, episode_map, frame) for ext in self.extensions]
        t0 = time.perf_counter()
        candidates = episode_map.find_frontier_candidates()
        t0 = timer.lap("frontiers", t0)
        t0 = time.perf_counter()
        result, score_ms = pending.result()
        timer.lap("score_wait", t0)
        timer.ms["score"] = score_ms
        if result is not None:  # e.g. the joint answer memory: the answer over the K most relevant views
            for ext in self.extensions:
                result = ext.scores(episode_map, frame, result, out, timer.ms, again=False)
        t0 = time.perf_counter()
        if result is not None:
            try:
                episode_map.apply_scores(result.lsv, result.gsv)
            except ValueError as exc:
                self._error(robot, episode_map.episode_id, frame.step, f"semantic values not written: {exc}")
        t0 = timer.lap("semantic_values", t0)
        for ext, pending_one in zip(self.extensions, pending_ext, strict=True):
            ext.apply(robot, episode_map, frame, pending_one, out, timer.ms)
        episode_map.compute_frontiers(out.frontier_layer, timer=timer, candidates=candidates)
        # Persist before publishing: whatever a consumer has seen survives a crash of this process. The update's
        # time and timings are stored with the map, so one killed between the two is answered by its successor
        # with the same message, not a second one.
        episode_map.made = (time.time(), timer.ms)
        t0 = time.perf_counter()
        self._save(episode_map)
        timer.lap("snapshot", t0)
        timer.ms["step"] = (time.perf_counter() - t_start) * 1000.0
        update = episode_map.map_update()
        update.skill = frame.skill  # a task skill's outcome, passed on to the planner's state machine
        for ext in self.extensions:
            ext.attach(episode_map, update, frame)
        if result is None:  # not kept as the step's answer: a resent step is scored again (answer_again)
            self.publish(robot, keys.MAPPER_MAP, update)
        else:
            self.publish_step(episode_map.episode_id, keys.MAPPER_MAP, update, frame.step)
            self.publish_step(episode_map.episode_id, keys.MAPPER_SCORES,
                              self._step_scores(episode_map, frame, result, out), frame.step)
        t0 = time.perf_counter()
        self._record(episode_map, frame)
        timer.lap("record", t0)
        self.last_timing_ms = timer.ms

    def _republish(self, robot: str, episode_map: EpisodeMap, frame: Frame) -> None:
        """The frame of the last integrated step came again: the simulator got no goal back (a message after
        it was lost while a service restarted). Publish the step's map update and scores again from the stored
        map, without integrating the frame twice or writing its semantic values twice."""
        log.info("episode %s: frame %d sent again; its map update and scores re-published", episode_map.episode_id,
                 frame.step)
        update = episode_map.map_update({})
        update.skill = frame.skill
        for ext in self.extensions:
            ext.attach(episode_map, update, frame)
        self.publish(robot, keys.MAPPER_MAP, update)
        result = self._score(robot, episode_map, frame)
        if result is not None:
            out = StepOutputs()
            for ext in self.extensions:  # e.g. the stored joint answer, the first step's memory steps
                result = ext.scores(episode_map, frame, result, out, {}, again=True)
            self.publish(robot, keys.MAPPER_SCORES, self._step_scores(episode_map, frame, result, out))

    @staticmethod
    def _step_scores(episode_map: EpisodeMap, frame: Frame, result: ScoreResult, out: StepOutputs) -> StepScores:
        return StepScores(
            episode_id=episode_map.episode_id,
            step=frame.step,
            answer_probs=result.answer_probs,
            relevance=result.relevance,
            lsv=result.lsv,
            gsv=result.gsv,
            backend=result.backend,
            mode=result.mode,  # logprobs / sampling: the stopper warns on a calibration mismatch
            # a question without choices: the ones the scorer proposed (Explore-EQA section VI-A)
            choices=episode_map.start.question.choices or result.proposed_choices,
            object_evidence=out.object_evidence,  # the question's object layer (EQA_OBJECT_EVIDENCE)
            answer_views=out.answer_views,  # steps of the joint answer (EQA_ANSWER_MEMORY_MODE=joint)
            memory=out.memory,  # warm start: the home's views re-scored for this question (step 0)
            step_limit=out.step_limit,  # warm start: the question's budget in the explored house (step 0)
            warm=out.warm,  # warm start: the home's version and memory bounds (step 0; the stopper's table)
        )

    def _timed_score(self, robot: str, episode_map: EpisodeMap, frame: Frame) -> tuple[ScoreResult | None, float]:
        t0 = time.perf_counter()
        result = self._score(robot, episode_map, frame)
        return result, (time.perf_counter() - t0) * 1000.0

    def _score(self, robot: str, episode_map: EpisodeMap, frame: Frame) -> ScoreResult | None:
        request = ScoreRequest(
            episode_id=episode_map.episode_id,
            step=frame.step,
            # Ground truth never leaves for the scorer: it cannot read what it is not sent.
            question=episode_map.start.question.without_ground_truth(),
            rgb=frame.rgb,
            prompt_points=episode_map.prompts,
            instances=frame.instances,
            labels=frame.labels,
            depth=frame.depth,
            seed=episode_map.start.seed,
        )
        for ext in self.extensions:  # e.g. the IN_ROOM prompt of counting across views
            request = ext.score_request(episode_map, request)
        result = call_pool(self.scorer(), request)
        if isinstance(result, Exception | ErrorReply):
            self._error(robot, episode_map.episode_id, frame.step, f"scorer failed: {failure(result)}")
            return None
        return result

    def _save(self, episode_map: EpisodeMap, volume: dict[str, Any] | None = None) -> None:
        try:
            self.save(episode_map.episode_id, volume=volume)
        except Exception:
            log.exception("episode %s: snapshot not saved", episode_map.episode_id)

    # ---- monitoring -------------------------------------------------------------------------------------
    def _record(self, episode_map: EpisodeMap, frame: Frame) -> None:
        recorder = self.recorders.get(episode_map.episode_id)
        if recorder is None or recorder.stream is None:
            return
        self._record_map(episode_map, frame, recorder)
        for ext in self.extensions:
            ext.record(episode_map, frame, recorder)

    @staticmethod
    def _record_map(episode_map: EpisodeMap, frame: Frame, recorder: EpisodeRecorder) -> None:
        if episode_map.maps is None:
            return
        import rerun as rr

        m = episode_map.maps
        recorder.set_step(frame.step)
        occ = np.zeros(m.free.shape, dtype=np.uint8)  # 0 unknown, 128 free, 255 occupied (y up)
        occ[m.free] = 128
        occ[m.occupied] = 255
        recorder.log("map/occupancy", rr.Image(np.flipud(occ)))
        recorder.log("map/explored", rr.Image(np.flipud(m.explored.astype(np.uint8) * 255)))
        for name in episode_map.layers:
            recorder.log(f"map/value/{name}", rr.Image(np.flipud(episode_map.layer(name))))
        ny = m.free.shape[0]
        res = episode_map.resolution
        if episode_map.frontiers:
            cells = [grid.fractional_cell(f.x, f.y, episode_map.origin, res) for f in episode_map.frontiers]
            pos = [(c, ny - r) for r, c in cells]
            w = np.array([f.weight for f in episode_map.frontiers])
            recorder.log(
                "map/frontiers",
                rr.Points2D(
                    pos,
                    radii=1.0 + 2.0 * w / max(float(w.max()), 1e-9),
                    labels=[f"{f.weight:.2f}" for f in episode_map.frontiers],
                ),
            )
        if episode_map.prompts:
            recorder.log(
                "camera/prompt_points",
                rr.Points2D([(p.u, p.v) for p in episode_map.prompts], labels=[p.label for p in episode_map.prompts]),
            )
