"""The stopper service: decides after every step whether the robot stops, and with which answer.

Consumes (any robot): ``EpisodeStart``, ``StepScores`` (mapper), ``Goal`` (planner; only ``done=True``
matters), ``EpisodeCancel`` and ``EpisodeEnd`` (an episode ended by someone else drops its state).
Publishes ``Decision`` (keys.STOPPER_DECISION) for every step and ``EpisodeEnd`` (keys.EPISODE_END) when it
stops. The rules are in :mod:`services.stopper.state` (decision), :mod:`services.stopper.conformal`
(Eq. 7-10) and :mod:`services.stopper.baselines` (Eq. 4, 5).

Persistence (:class:`eqa.episode_service.EpisodeService`): the :class:`~services.stopper.state.EpisodeRecord`
of every running episode is written to ``eqa:stopper:episode:<episode_id>`` after each step, before the decision
is published; a restarted stopper reloads it when the episode's next message comes and continues with the same
running intersection. Scores that overtake their ``EpisodeStart`` wait for it (the base). The
trace of each episode goes to ``eqa:trace:episode:<episode_id>`` (calibration harness), and the
``EpisodeEnd`` it published to ``eqa:stopper:end:<episode_id>`` (so a restarted gateway can reconcile).
Messages published while the stopper is down are not replayed by Zenoh: the gateway's watchdog covers that.

Rerun (``eqa.recording``): per step ``stopper/rho/<letter>`` (also under ``ENTITIES["scores"]``, i.e.
``stopper/scores/<letter>``), ``stopper/set_size``, ``stopper/relevance``, a text log of the prediction set
at ``ENTITIES["prediction_set"]`` (``stopper/prediction_set``) and the final answer at ``stopper/log``; a task
episode's outcome (:func:`eqa.task_traces.task_outcome`) at ``ENTITIES["task_outcome"]`` (``task/outcome``).
After a restart the recording continues in
``stopper-resume<k>.rrd`` next to ``stopper.rrd`` (a file sink cannot be appended to).
"""

from __future__ import annotations

import logging
from typing import Any

from eqa import keys, recording
from eqa.bus import Bus
from eqa.episode_service import EpisodeService
from eqa.messages import (
    Decision,
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    EpisodeState,
    Goal,
    StepScores,
)
from eqa.recording import recording_dir
from eqa.service import SHELL_GROUPS
from eqa.settings import HomeSettings, SettingsGroup, StopperSettings
from eqa.store import (
    EPISODE_STATE_TTL_S,
    Store,
    episode_end_key,
    episode_state_key,
    stored_end,
    task_metrics_key,
)
from eqa.task_traces import kind_of_metrics, task_outcome
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

STATE_PREFIX = episode_state_key("stopper", "")
_ENTITIES: dict[str, str] = getattr(recording, "ENTITIES", {})
PREDICTION_SET_ENTITY = _ENTITIES.get("prediction_set", "stopper/prediction_set")
SCORES_ENTITY = _ENTITIES.get("scores", "stopper/scores")
TASK_OUTCOME_ENTITY = _ENTITIES.get("task_outcome", "task/outcome")


class StopperService(EpisodeService[EpisodeRecord]):
    """Explore-EQA stopping rule (multi-step conformal prediction) and its baselines."""

    name = "stopper"
    description = "Decides when the robot stops exploring and what it answers (Explore-EQA section V)."
    hold_max_episodes = 256
    settings_groups = (*SHELL_GROUPS, StopperSettings, HomeSettings)  # HomeSettings: the warm starts' CP table

    def __init__(self, settings: SettingsGroup, bus: Bus | None = None, store: Store | None = None) -> None:
        super().__init__(settings, bus, store)
        self.traces: TraceStore | None = None

    # ---- lifecycle ----------------------------------------------------------------------------------------
    def setup_episodes(self) -> None:
        self.traces = TraceStore(self.store)
        self.on_step(keys.MAPPER_SCORES, self.on_scores)
        self.on_step(keys.PLANNER_GOAL, self.on_goal, resend=False, hold=False)

    # ---- persistence --------------------------------------------------------------------------------------
    def dump_state(self, state: EpisodeRecord, **extra: Any) -> dict[str, Any]:
        return state.model_dump(mode="json")

    def load_state(self, episode_id: str, data: Any) -> EpisodeRecord:
        episode = EpisodeRecord.model_validate(data)
        episode.restarts += 1
        log.info("resumed episode %s at step %d (running set %s)", episode.episode_id, episode.last_step,
                 episode.running)
        return episode

    def answered_step(self, episode_id: str, state: EpisodeRecord) -> int:
        return state.last_step

    def answer_again(self, robot: str, state: EpisodeRecord, msg: Any) -> None:
        last = state.last_decision
        if last is not None and last.step == msg.step and not last.stop:
            # The step was sent again (a message after it was lost): answer it again, nothing recomputed.
            log.info("episode %s: step %d sent again; its decision re-published", state.episode_id, msg.step)
            self.publish(robot, keys.STOPPER_DECISION, last)
        else:
            log.info("episode %s: step %d already decided; duplicate scores ignored", state.episode_id, msg.step)

    def _save_trace(self, episode: EpisodeRecord, end_reason: str | None = None) -> None:
        trace = episode.trace(end_reason)
        if trace is not None and self.traces is not None:
            self.traces.save_episode(episode.episode_id, trace)

    def _recording(self, episode: EpisodeRecord) -> str | None:
        if episode.record and self.settings.record:
            return str(recording_dir(self.settings, episode.episode_id))
        return None

    # ---- handlers -----------------------------------------------------------------------------------------
    def start_episode(self, robot: str, start: EpisodeStart) -> EpisodeRecord | None:
        episode = EpisodeRecord.from_start(start, robot)
        episode.answer_memory = self.settings.answer_memory_k  # (answer_memory.py); fixed for the episode
        episode.answer_fusion = self.settings.answer_memory_fusion
        # pooled into f by object_evidence.py: existence (whole map) with EQA_OBJECT_EVIDENCE, counting (in the
        # asked room's extent) with EQA_ANSWER_COUNTING=views; the mapper sends the evidence of the same settings
        categories = (["existence"] if self.settings.object_evidence else []) + (
            ["counting"] if self.settings.answer_counting == "views" else [])
        if categories:
            episode.object_evidence = (self.settings.object_evidence_psi_min, self.settings.object_evidence_weight)
            episode.evidence_categories = categories  # type: ignore[assignment]
        try:
            episode.threshold = check_threshold(start)
        except ValueError as exc:
            self._finish(episode, "failed", f"invalid stop threshold: {exc}", None)
            return None
        if start.stop.rule == "cp":
            choice, why = self._calibration(self.settings.calibration_name, start)
            if choice is None:
                log.error("episode %s: %s", start.episode_id, why)
                self._finish(episode, "failed", why, None)
                return None
            if choice.note:
                log.warning("episode %s: %s", start.episode_id, choice.note)
            episode.calibration = choice
            if start.home is not None and start.task is None:
                # a question in a home is warm only if its home held memory, which the mapper says with its first
                # step (StepScores.warm); the warm table is resolved now, as the cold one, and taken then
                home_name = self.settings.home_calibration_name
                if home_name:
                    episode.warm_calibration, why = self._calibration(home_name, start)
                    episode.warm_missing = why
                else:
                    episode.warm_missing = ("no warm table is named (EQA_HOME_CALIBRATION_NAME is empty): calibrate "
                                            "one on warm traces and name it there")
        self._save_trace(episode)
        log.info(
            "episode %s started on %s: rule %s, %d steps max",
            episode.episode_id,
            robot,
            start.stop.rule,
            episode.max_steps,
        )
        return episode

    def _calibration(self, name: str, start: EpisodeStart) -> tuple[Any, str]:
        """The q_hat of table ``name`` for the episode (:func:`resolve_calibration`), or None and why not."""
        try:
            table, where = load_table(self.store, name)
        except ValueError as exc:  # bad table name in settings
            table, where = None, str(exc)
        return resolve_calibration(table, where, start.stop.eps, name, start.question.category)

    def on_scores(self, robot: str, episode: EpisodeRecord, scores: StepScores) -> None:
        if robot != episode.robot:
            log.warning(
                "scores of episode %s arrived for robot %s, expected %s; dropped",
                episode.episode_id,
                robot,
                episode.robot,
            )
            return
        work = episode.model_copy(deep=True)  # a failure below leaves the stored state untouched
        try:
            decision = decide(work, scores)
        except ScoreError as exc:
            reason = f"invalid scores at step {scores.step}: {exc}"
            log.error("episode %s: %s", episode.episode_id, reason)
            self._finish(episode, "failed", reason, None)
            return
        if decision is None:
            self.answer_again(robot, episode, scores)
            return
        if decision.warm_calibrated is False and not episode.probs:  # once, at the first step of a warm start
            log.warning("episode %s: %s", episode.episode_id,
                        work.calibration.note if work.calibration else "stopping not calibrated for warm starts")
        work.last_decision = decision
        self.episodes[episode.episode_id] = work
        self._save_trace(work)
        self._log_rerun(work, decision)
        if decision.stop:
            self._finish(work, "stopped", decision.reason, decision.answer, decision)
        else:
            self.publish_step(episode.episode_id, keys.STOPPER_DECISION, decision, decision.step, save=True)

    def on_goal(self, robot: str, episode: EpisodeRecord, goal: Goal) -> None:
        if not goal.done:
            return
        if self._task_metrics(episode.episode_id) is not None:  # a task episode: the planner ends it
            self._finish(episode, "stopped", f"task ended: {goal.reason or 'the planner is done'}", None)
            return
        answer = episode.fallback()
        why = goal.reason or "nothing left to explore"
        if answer is None:
            self._finish(episode, "failed", f"the planner ended exploration before any step was scored: {why}", None)
            return
        self._finish(episode, "stopped", fallback_reason(f"planner ended exploration: {why}", answer), answer)

    def finish_episode(self, robot: str, msg: EpisodeCancel | EpisodeEnd, state: EpisodeRecord) -> None:
        if isinstance(msg, EpisodeCancel):
            self._finish(state, "cancelled", msg.reason, None)
            return
        # An episode ended elsewhere (gateway watchdog, ...): keep its trace, forget its state.
        log.info("episode %s ended by another service (%s); state dropped", msg.episode_id, msg.reason)
        self._drop(state, msg.reason)

    # ---- helpers ------------------------------------------------------------------------------------------
    def _drop(self, episode: EpisodeRecord, reason: str) -> None:
        self._save_trace(episode, end_reason=reason)
        self.drop(episode.episode_id)

    def _task_metrics(self, episode_id: str) -> dict[str, float] | None:
        """The sim's phase metrics of a task episode (:func:`eqa.store.task_metrics_key`); None for a question
        episode."""
        raw = self.store.get_json(task_metrics_key(episode_id))
        return {str(k): float(v) for k, v in raw.items()} if isinstance(raw, dict) else None

    def ended_before(self, robot: str, episode_id: str) -> None:
        """Publish the stored ``EpisodeEnd`` again: a step input came after the end was stored, so the instance
        that stored it may have been killed before publishing it (everyone takes a repeated end as one)."""
        end = stored_end(self.store, episode_id)
        if end is None:
            return
        log.info("episode %s: a step came after its end was stored; the stored end published again", episode_id)
        self.publish(robot, keys.EPISODE_END, end)

    def _finish(
        self, episode: EpisodeRecord, state: EpisodeState, reason: str, answer: str | None,
        decision: Decision | None = None,
    ) -> None:
        """End an episode: store the end and drop the state first, then publish (the last Decision, if any,
        and the EpisodeEnd)."""
        r = self.recorders.get(episode.episode_id)
        if answer is not None and r is not None:
            r.log("stopper/log", _text(f"final answer {answer}: {reason}"))
        end = end_message(episode, state, reason, answer, self._recording(episode))
        metrics = self._task_metrics(episode.episode_id)
        if metrics is not None:  # a task episode: its phase metrics, no answer
            reason = reason.split("; answering")[0]
            end = end_message(episode, state, reason, None, self._recording(episode))
            end = end.model_copy(update={"metrics": metrics, "answer": None, "answer_text": None,
                                         "prediction_set": []})
            if r is not None and r.enabled:
                out = task_outcome(kind_of_metrics(metrics), metrics, state, reason, end.steps, end.max_steps)
                r.log(TASK_OUTCOME_ENTITY, _text(f"task {out['text']} ({reason})",
                                                      "INFO" if out["success"] else "WARN"))
        self.store.set(episode_end_key(episode.episode_id), end.model_dump_json().encode(), ttl_s=EPISODE_STATE_TTL_S)
        self._drop(episode, reason)
        if decision is not None:
            self.publish(episode.robot, keys.STOPPER_DECISION, decision)
        self.publish(episode.robot, keys.EPISODE_END, end)
        log.info("episode %s %s after %d steps: answer %s (%s)", episode.episode_id, state, end.steps, answer, reason)

    def _log_rerun(self, episode: EpisodeRecord, decision: Decision) -> None:
        r = self.recorders.get(episode.episode_id)
        if r is None or not r.enabled:
            return
        import rerun as rr

        r.set_step(decision.step)
        r.log("stopper/relevance", rr.Scalars([episode.relevance[-1]]))
        for name, value in decision.scores.items():  # rho_y^t per letter (CP) or the rule's statistic
            r.log(f"{SCORES_ENTITY}/{name}", rr.Scalars([value]))
        if episode.stop.rule == "cp":
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


def _text(message: str, level: str = "INFO") -> Any:
    import rerun as rr

    return rr.TextLog(message, level=level)
