"""The stopper service: decides after every step whether the robot stops, and with which answer.

Consumes (any robot): ``EpisodeStart``, ``StepScores`` (mapper), ``Goal`` (planner; only ``done=True``
matters), ``EpisodeCancel`` and ``EpisodeEnd`` (an episode ended by someone else drops its state).
Publishes ``Decision`` (keys.STOPPER_DECISION) for every step and ``EpisodeEnd`` (keys.EPISODE_END) when it
stops. The rules are in :mod:`services.stopper.state` (decision), :mod:`services.stopper.conformal`
(Eq. 7-10) and :mod:`services.stopper.baselines` (Eq. 4, 5).

Persistence (``eqa.store``): the :class:`~services.stopper.state.EpisodeRecord` of every running episode is
written to ``eqa:stopper:episode:<episode_id>`` after each step, before the decision is published; on start
the service reloads them all, so a restarted stopper continues with the same running intersection. The
trace of each episode goes to ``eqa:trace:episode:<episode_id>`` (calibration harness), and the
``EpisodeEnd`` it published to ``eqa:stopper:end:<episode_id>`` (so a restarted gateway can reconcile).
Messages published while the stopper is down are not replayed by Zenoh: the gateway's watchdog covers that.

Rerun (``eqa.recording``): per step ``stopper/rho/<letter>`` (also under ``ENTITIES["scores"]``, i.e.
``stopper/scores/<letter>``), ``stopper/set_size``, ``stopper/relevance``, a text log of the prediction set
at ``ENTITIES["prediction_set"]`` (``stopper/prediction_set``) and the final answer at ``stopper/log``.
After a restart the recording continues in
``stopper-resume<k>.rrd`` next to ``stopper.rrd`` (a file sink cannot be appended to).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from eqa import keys, recording
from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    EpisodeState,
    Goal,
    StepScores,
)
from eqa.recording import EpisodeRecorder, recording_dir
from eqa.service import Service
from eqa.store import EPISODE_STATE_TTL_S, episode_end_key, task_metrics_key
from services.stopper.calibration import TraceStore, load_table
from services.stopper.conformal import ScoreError
from services.stopper.state import (
    EpisodeRecord,
    check_threshold,
    decide,
    end_message,
    fallback_reason,
    resolve_calibration,
)

log = logging.getLogger(__name__)

STATE_PREFIX = "eqa:stopper:episode:"
# Zenoh runs the callbacks of different subscriptions on different threads, so the scores of step 0 can
# overtake their EpisodeStart; they wait here (per episode, bounded, for a while) until it arrives.
_ENTITIES: dict[str, str] = getattr(recording, "ENTITIES", {})
PREDICTION_SET_ENTITY = _ENTITIES.get("prediction_set", "stopper/prediction_set")
SCORES_ENTITY = _ENTITIES.get("scores", "stopper/scores")
PENDING_TTL_S = 30.0
PENDING_MAX_EPISODES = 256
PENDING_MAX_STEPS = 64


class StopperService(Service):
    """Explore-EQA stopping rule (multi-step conformal prediction) and its baselines."""

    name = "stopper"
    description = "Decides when the robot stops exploring and what it answers (Explore-EQA section V)."

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.episodes: dict[str, EpisodeRecord] = {}
        self.recorders: dict[str, EpisodeRecorder] = {}
        self.traces: TraceStore | None = None
        self._pending: dict[str, list[tuple[float, str, StepScores]]] = {}

    # ---- lifecycle ----------------------------------------------------------------------------------------
    def setup(self) -> None:
        self.traces = TraceStore(self.store)
        self._reload()
        self.on(keys.EPISODE_START, self.on_start)
        self.on(keys.MAPPER_SCORES, self.on_scores)
        self.on(keys.PLANNER_GOAL, self.on_goal)
        self.on(keys.EPISODE_CANCEL, self.on_cancel)
        self.on(keys.EPISODE_END, self.on_end)

    def teardown(self) -> None:
        for rec in list(self.recorders.values()):
            rec.close()
        self.recorders.clear()

    def _reload(self) -> None:
        for key in self.store.keys(STATE_PREFIX):
            raw = self.store.get(key)
            if raw is None:
                continue
            try:
                rec = EpisodeRecord.model_validate_json(raw)
            except ValueError as exc:
                log.error("stored stopper state %s is invalid, dropping it: %s", key, exc)
                self.store.delete(key)
                continue
            rec.restarts += 1
            self.episodes[rec.episode_id] = rec
            self._save(rec)
            log.info("resumed episode %s at step %d (running set %s)", rec.episode_id, rec.last_step, rec.running)

    # ---- persistence --------------------------------------------------------------------------------------
    def _save(self, rec: EpisodeRecord) -> None:
        self.store.set(STATE_PREFIX + rec.episode_id, rec.model_dump_json().encode(), ttl_s=EPISODE_STATE_TTL_S)

    def _save_trace(self, rec: EpisodeRecord, end_reason: str | None = None) -> None:
        trace = rec.trace(end_reason)
        if trace is not None and self.traces is not None:
            self.traces.save_episode(rec.episode_id, trace)

    def _recorder(self, rec: EpisodeRecord) -> EpisodeRecorder:
        r = self.recorders.get(rec.episode_id)
        if r is None:
            name = "stopper" if rec.restarts == 0 else f"stopper-resume{rec.restarts}"
            r = EpisodeRecorder(self.settings, rec.episode_id, name, enabled=rec.record)
            self.recorders[rec.episode_id] = r
        return r

    def _recording(self, rec: EpisodeRecord) -> str | None:
        if rec.record and self.settings.record:
            return str(recording_dir(self.settings, rec.episode_id))
        return None

    # ---- handlers -----------------------------------------------------------------------------------------
    def on_start(self, robot: str, start: EpisodeStart) -> None:
        if start.episode_id in self.episodes:
            log.info("episode %s already started; ignoring a repeated EpisodeStart", start.episode_id)
            return
        rec = EpisodeRecord.from_start(start, robot)
        try:
            rec.threshold = check_threshold(start)
        except ValueError as exc:
            self._finish(rec, "failed", f"invalid stop threshold: {exc}", None)
            return
        if start.stop.rule == "cp":
            name = self.settings.calibration_name
            try:
                table, where = load_table(self.store, name)
            except ValueError as exc:  # bad table name in settings
                table, where = None, str(exc)
            choice, why = resolve_calibration(table, where, start.stop.eps, name, start.question.category)
            if choice is None:
                log.error("episode %s: %s", start.episode_id, why)
                self._finish(rec, "failed", why, None)
                return
            if choice.note:
                log.warning("episode %s: %s", start.episode_id, choice.note)
            rec.calibration = choice
        self.episodes[rec.episode_id] = rec
        self._save(rec)
        self._save_trace(rec)
        log.info(
            "episode %s started on %s: rule %s, %d steps max",
            rec.episode_id,
            robot,
            start.stop.rule,
            rec.max_steps,
        )
        early = sorted(self._pending.pop(rec.episode_id, []), key=lambda p: p[2].step)
        for _t, held_robot, scores in early:
            self.on_scores(held_robot, scores)

    def on_scores(self, robot: str, scores: StepScores) -> None:
        rec = self.episodes.get(scores.episode_id)
        if rec is None:
            self._hold(robot, scores)
            return
        if robot != rec.robot:
            log.warning(
                "scores of episode %s arrived for robot %s, expected %s; dropped",
                rec.episode_id,
                robot,
                rec.robot,
            )
            return
        work = rec.model_copy(deep=True)  # a failure below leaves the stored state untouched
        try:
            decision = decide(work, scores)
        except ScoreError as exc:
            reason = f"invalid scores at step {scores.step}: {exc}"
            log.error("episode %s: %s", rec.episode_id, reason)
            self._finish(rec, "failed", reason, None)
            return
        if decision is None:
            last = rec.last_decision
            if last is not None and last.step == scores.step and not last.stop:
                # The step was sent again (a message after it was lost): answer it again, nothing recomputed.
                log.info("episode %s: step %d sent again; its decision re-published", rec.episode_id, scores.step)
                self.publish(robot, keys.STOPPER_DECISION, last)
            else:
                log.info("episode %s: step %d already decided; duplicate scores ignored", rec.episode_id, scores.step)
            return
        work.last_decision = decision
        self.episodes[rec.episode_id] = work
        self._save_trace(work)
        self._log_rerun(work, decision)
        if decision.stop:
            self._finish(work, "stopped", decision.reason, decision.answer, decision)
        else:
            self._save(work)
            self.publish(robot, keys.STOPPER_DECISION, decision)

    def on_goal(self, robot: str, goal: Goal) -> None:
        if not goal.done:
            return
        rec = self.episodes.get(goal.episode_id)
        if rec is None:
            return
        if self._task_metrics(rec.episode_id) is not None:  # a task episode: the planner ends it (issue 17)
            self._finish(rec, "stopped", f"task ended: {goal.reason or 'the planner is done'}", None)
            return
        answer = rec.fallback()
        why = goal.reason or "nothing left to explore"
        if answer is None:
            self._finish(rec, "failed", f"the planner ended exploration before any step was scored: {why}", None)
            return
        self._finish(rec, "stopped", fallback_reason(f"planner ended exploration: {why}", answer), answer)

    def on_cancel(self, robot: str, cancel: EpisodeCancel) -> None:
        rec = self.episodes.get(cancel.episode_id)
        if rec is None:
            return
        self._finish(rec, "cancelled", cancel.reason, None)

    def on_end(self, robot: str, end: EpisodeEnd) -> None:
        """An episode ended elsewhere (gateway watchdog, ...): forget its state."""
        rec = self.episodes.pop(end.episode_id, None)
        if rec is not None:
            log.info("episode %s ended by another service (%s); state dropped", end.episode_id, end.reason)
            self._drop(rec, end.reason)

    # ---- helpers ------------------------------------------------------------------------------------------
    def _hold(self, robot: str, scores: StepScores) -> None:
        """Keep scores of a not (yet) started episode for ``PENDING_TTL_S``; drop those of ended ones."""
        now = time.monotonic()
        for eid in [e for e, items in self._pending.items() if now - items[0][0] > PENDING_TTL_S]:
            log.warning("scores for unknown episode %s dropped: no EpisodeStart within %.0f s", eid, PENDING_TTL_S)
            del self._pending[eid]
        if self.store.get(episode_end_key(scores.episode_id)) is not None:
            log.info("scores for ended episode %s (step %d) ignored", scores.episode_id, scores.step)
            return
        items = self._pending.get(scores.episode_id)
        if items is None:
            if len(self._pending) >= PENDING_MAX_EPISODES:
                log.warning("scores for unknown episode %s (step %d) dropped", scores.episode_id, scores.step)
                return
            items = self._pending[scores.episode_id] = []
        if len(items) < PENDING_MAX_STEPS:
            items.append((now, robot, scores))
            log.info("scores of episode %s step %d held until its EpisodeStart", scores.episode_id, scores.step)

    def _drop(self, rec: EpisodeRecord, reason: str) -> None:
        self.episodes.pop(rec.episode_id, None)
        self._save_trace(rec, end_reason=reason)
        self.store.delete(STATE_PREFIX + rec.episode_id)
        r = self.recorders.pop(rec.episode_id, None)
        if r is not None:
            r.close()

    def _task_metrics(self, episode_id: str) -> dict[str, float] | None:
        """The sim's phase metrics of a task episode (:func:`eqa.store.task_metrics_key`); None for a question
        episode."""
        raw = self.store.get_json(task_metrics_key(episode_id))
        return {str(k): float(v) for k, v in raw.items()} if isinstance(raw, dict) else None

    def _finish(
        self, rec: EpisodeRecord, state: EpisodeState, reason: str, answer: str | None, decision: Decision | None = None
    ) -> None:
        """End an episode: store the end and drop the state first, then publish (the last Decision, if any,
        and the EpisodeEnd)."""
        if answer is not None:
            self._recorder(rec).log("stopper/log", _text(f"final answer {answer}: {reason}"))
        end = end_message(rec, state, reason, answer, self._recording(rec))
        metrics = self._task_metrics(rec.episode_id)
        if metrics is not None:  # a task episode: its phase metrics, no answer
            end = end.model_copy(update={"metrics": metrics, "answer": None, "answer_text": None,
                                         "prediction_set": []})
        self.store.set(episode_end_key(rec.episode_id), end.model_dump_json().encode(), ttl_s=EPISODE_STATE_TTL_S)
        self._drop(rec, reason)
        if decision is not None:
            self.publish(rec.robot, keys.STOPPER_DECISION, decision)
        self.publish(rec.robot, keys.EPISODE_END, end)
        log.info("episode %s %s after %d steps: answer %s (%s)", rec.episode_id, state, end.steps, answer, reason)

    def _log_rerun(self, rec: EpisodeRecord, decision: Decision) -> None:
        r = self._recorder(rec)
        if not r.enabled:
            return
        import rerun as rr

        r.set_step(decision.step)
        r.log("stopper/relevance", rr.Scalars([rec.relevance[-1]]))
        for name, value in decision.scores.items():  # rho_y^t per letter (CP) or the rule's statistic
            r.log(f"{SCORES_ENTITY}/{name}", rr.Scalars([value]))
        if rec.stop.rule == "cp":
            for letter, rho in decision.scores.items():
                r.log(f"stopper/rho/{letter}", rr.Scalars([rho]))
            r.log("stopper/set_size", rr.Scalars([float(len(decision.prediction_set))]))
            text = (
                f"step {decision.step}: C^t = {{{', '.join(decision.step_set)}}}, running "
                f"{{{', '.join(decision.prediction_set)}}}; {'STOP' if decision.stop else 'continue'}"
            )
        else:
            text = f"step {decision.step}: {decision.reason}; {'STOP' if decision.stop else 'continue'}"
        r.log(PREDICTION_SET_ENTITY, rr.TextLog(text))


def _text(message: str) -> Any:
    import rerun as rr

    return rr.TextLog(message)
