"""Per-episode state of the stopper and the decision of one step (no I/O; the shell persists it).

:class:`EpisodeRecord` is everything the stopper knows about one running episode: the question and stop
configuration, the calibration threshold resolved when the episode started (so a new table does not change
a running episode), the scores of every step seen, and the running intersection of the causal prediction
sets. It is JSON (pydantic) so that it survives a restart of the stopper process.

:func:`decide` applies one step's :class:`eqa.messages.StepScores` to a record and returns the
:class:`eqa.messages.Decision`; :func:`end_message` builds the :class:`eqa.messages.EpisodeEnd`.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from eqa.messages import (
    Decision,
    EpisodeEnd,
    EpisodeStart,
    EpisodeState,
    Question,
    StepScores,
    StopConfig,
    Strategy,
    letters,
)
from services.stopper import baselines
from services.stopper.answer_memory import AnswerRule, memory_answer, rule_mismatch, transform
from services.stopper.calibration import CalibrationTable, Trace, TraceStep
from services.stopper.conformal import (
    check_scores,
    relevance_weighted_confidence,
    step_set,
)
from services.stopper.object_evidence import EvidenceParams, combine, layer_distribution

log = logging.getLogger(__name__)


class CalibrationChoice(BaseModel):
    """The q_hat an episode uses and why."""

    model_config = ConfigDict(extra="forbid")
    q_hat: float
    eps: float  # the eps of the table entry used (at or below the asked one)
    asked_eps: float
    n: int
    source: str
    note: str = ""
    backend: str | None = None  # the scorer backend whose scores the table was calibrated on
    mode: str | None = None  # ... and its mode: logprobs / sampling (issue 23)
    category: str | None = None  # Mondrian: the category whose own q_hat this is
    answer_rule: str | None = None  # the answer rule the table was calibrated with (issue 22; None = single)


# q_hat that keeps every label (kappa <= 2 always): a Mondrian group too small to certify the asked eps
KEEP_ALL_Q_HAT = 2.0


def resolve_calibration(
    table: CalibrationTable | None, where: str, eps: float, name: str, category: str | None = None
) -> tuple[CalibrationChoice | None, str]:
    """Pick ``q_hat`` for an episode asking ``eps``: the exact entry, else the nearest stored eps at or
    below it (said so in the note), else ``(None, reason telling the user to run eqa calibrate)``.

    A Mondrian table (``table.groups``) gives the question's category its own ``q_hat``; a category the
    table has no group for uses the marginal one (noted); a group too small to certify ``eps`` keeps every
    answer (``q_hat = 2``: the robot runs to its step limit, noted), never a less conservative set."""
    if table is not None and table.mondrian:
        marginal, why = resolve_calibration(table.model_copy(update={"groups": {}}), where, eps, name)
        if marginal is None:
            return None, why
        group = table.groups.get(category or "")
        if group is None:
            marginal.note = "; ".join(n for n in (marginal.note, f"no per-category calibration for category "
                                                  f"{category!r}: marginal q_hat") if n)
            return marginal, ""
        found = group.lookup(eps)
        if found is None:
            note = (f"category {category!r} has only {group.n} calibration episodes, too few for eps={eps:g}: "
                    f"keeping every answer (calibrate on more {category} questions)")
            return marginal.model_copy(update={"q_hat": KEEP_ALL_Q_HAT, "n": group.n, "note": note,
                                                "category": category}), ""
        entry, exact = found
        note = "" if exact else f"eps={eps:g} not calibrated for category {category!r}; using eps={entry.eps:g}"
        return marginal.model_copy(update={"q_hat": entry.q_hat, "eps": entry.eps, "n": group.n, "note": note,
                                            "category": category}), ""
    if table is None:
        return None, (
            f"no conformal calibration table named {name!r} ({where}): run `eqa calibrate --name {name}` "
            f"or choose another stop rule"
        )
    found = table.lookup(eps)
    if found is None:
        return None, (
            f"calibration table {name!r} has no eps at or below {eps:g} (stored: "
            f"{', '.join(f'{e:g}' for e in table.eps_grid)}): run `eqa calibrate --name {name} --eps {eps:g}`"
        )
    entry, exact = found
    note = (
        ""
        if exact
        else (
            f"eps={eps:g} is not calibrated in table {name!r}; using the nearest stored eps={entry.eps:g} "
            f"below it (more conservative)"
        )
    )
    backend = table.provenance.get("scorer_backend")
    mode = table.provenance.get("scorer_mode")
    rule = table.provenance.get("answer_rule")
    choice = CalibrationChoice(q_hat=entry.q_hat, eps=entry.eps, asked_eps=eps, n=table.n, source=where, note=note,
                               backend=str(backend) if backend else None, mode=str(mode) if mode else None,
                               answer_rule=str(rule) if rule else None)
    return choice, ""


def backend_mismatch(cal: CalibrationChoice, scores_backend: str | None) -> str:
    """A warning when the scores come from another scorer backend than the calibration did: the coverage
    guarantee (Claim 1) holds only for the model the table was calibrated on."""
    if not cal.backend or not scores_backend or scores_backend == cal.backend:
        return ""
    return (f"table calibrated on the {cal.backend} scorer, these scores come from {scores_backend}: "
            f"run `eqa calibrate` with this scorer for the guarantee")


def mode_mismatch(cal: CalibrationChoice, scores_mode: str | None) -> str:
    """A warning when the scores were read in another mode than the calibration's (issue 23): sampled
    frequencies and logprobs are different score functions, so Claim 1 holds only for the table's mode."""
    if not cal.mode or not scores_mode or scores_mode == cal.mode:
        return ""
    return (f"table calibrated in {cal.mode} mode, these scores come from {scores_mode} mode: "
            f"run `eqa calibrate` in this mode (EQA_REMOTE_MODE) for the guarantee")


class EpisodeRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")
    episode_id: str
    robot: str
    question: Question
    strategy: Strategy
    stop: StopConfig
    max_steps: int
    record: bool = True
    choices: list[str] = Field(default_factory=list)
    calibration: CalibrationChoice | None = None
    threshold: float | None = None  # baseline rules
    steps: list[int] = Field(default_factory=list)
    probs: list[list[float]] = Field(default_factory=list)
    relevance: list[float] = Field(default_factory=list)
    running: list[str] | None = None  # CP running intersection; None before the first step
    restarts: int = 0
    last_decision: Decision | None = None  # re-published when the step's scores come again
    # issue 22: answer memory (services/stopper/answer_memory.py), fixed at the episode's start; 0 = single view
    answer_memory: int = Field(default=0, ge=0, le=16)
    answer_fusion: str = "loglinear"
    # issue 22 item 2: pool the object layer's evidence (StepScores.object_evidence) into f; None = off
    object_evidence: tuple[float, float] | None = None  # (psi_min, weight)
    task: bool = False  # a task episode: the planner ends it, there is no answer to give

    @property
    def answer_rule(self) -> AnswerRule:
        return AnswerRule(self.answer_memory, self.answer_fusion)  # type: ignore[arg-type]

    @classmethod
    def from_start(cls, start: EpisodeStart, robot: str) -> EpisodeRecord:
        return cls(
            episode_id=start.episode_id,
            robot=robot,
            question=start.question,
            strategy=start.strategy,
            stop=start.stop,
            max_steps=start.max_steps,
            record=start.record,
            choices=list(start.question.choices),
            task=start.task is not None,
        )

    @property
    def last_step(self) -> int:
        return self.steps[-1] if self.steps else -1

    @property
    def labels(self) -> list[str]:
        return letters(len(self.choices)) if self.choices else []

    def trace(self, end_reason: str | None = None) -> Trace | None:
        """The calibration trace of this episode so far (None while its choices are unknown)."""
        if len(self.choices) < 2:
            return None
        q = self.question
        return Trace(
            question_id=q.id,
            scene=q.scene,
            category=q.category,
            choices=self.choices,
            answer=q.answer if q.answer in self.labels else None,
            max_steps=self.max_steps,
            strategy=self.strategy,
            steps=[TraceStep(answer_probs=p, relevance=r) for p, r in zip(self.probs, self.relevance, strict=True)],
            episode_id=self.episode_id,
            end_reason=end_reason,
            stop_rule=self.stop.rule,
        )

    def fallback(self) -> str | None:
        """``argmax f`` at the step of highest ``Rel`` (None before any step); with the answer memory on, the
        argmax of the pooled distribution of the K most relevant views (issue 22)."""
        if not self.probs:
            return None
        return self.labels[memory_answer(np.asarray(self.probs), np.asarray(self.relevance), self.answer_rule)]

    def answer_text(self, answer: str | None) -> str | None:
        if answer is None or answer not in self.labels:
            return None
        return self.choices[self.labels.index(answer)]


def _fmt_set(labels: list[str]) -> str:
    return "{" + ", ".join(labels) + "}"


def fallback_reason(why: str, answer: str, tag: str = "") -> str:
    """The reason of a stop that answers with :meth:`EpisodeRecord.fallback` (Explore-EQA's answer at a budget)."""
    return f"{why}; answering {answer}, the most likely answer of the most relevant step" + (f" ({tag})" if tag else "")


def decide(rec: EpisodeRecord, scores: StepScores) -> Decision | None:
    """Apply the scores of step ``scores.step`` to ``rec`` and return the decision of that step.

    Returns None (and leaves ``rec`` unchanged) for a step already seen (a duplicate). Raises
    :class:`services.stopper.conformal.ScoreError` for invalid scores, leaving ``rec`` unchanged.
    """
    if scores.step <= rec.last_step:
        return None
    if not rec.choices:  # a question without choices: the scorer proposed them (Explore-EQA section VI-A)
        n = len(scores.choices) or len(scores.answer_probs)
        choices = list(scores.choices) or [f"option {c}" for c in letters(max(2, n))]
    else:
        choices = rec.choices
    f = check_scores(scores.answer_probs, scores.relevance, len(choices))
    rel = float(scores.relevance)
    if rec.object_evidence is not None and scores.object_evidence is not None:
        # the answer distribution used from here on (and stored in the trace, so a calibration from the
        # stopper's traces covers the combined score) pools the VLM's with the object layer's
        params = EvidenceParams(psi_min=rec.object_evidence[0], weight=rec.object_evidence[1])
        f = combine(f, layer_distribution(scores.object_evidence, choices, params), params.weight)
    if scores.step != rec.last_step + 1:
        log.warning("episode %s: step %d follows step %d (steps missing)", rec.episode_id, scores.step, rec.last_step)
    rec.choices = choices
    rec.steps.append(scores.step)
    rec.probs.append([float(v) for v in f])
    rec.relevance.append(rel)
    labels = rec.labels
    at_limit = scores.step >= rec.max_steps - 1
    rule = rec.stop.rule
    argmax_now = labels[int(np.argmax(f))]

    if rule == "cp":
        cal = rec.calibration
        if cal is None:
            raise RuntimeError("cp episode without calibration")  # guarded at EpisodeStart
        rule_now = rec.answer_rule
        if rule_now.on:  # pooled scores of the K most relevant views so far (calibrated with the same rule)
            pf, pr = transform(np.asarray(rec.probs), np.asarray(rec.relevance), rule_now)
            rho = relevance_weighted_confidence(pf[-1], float(pr[-1]))
        else:
            rho = relevance_weighted_confidence(f, rel)
        mask = step_set(rho, cal.q_hat)
        cset = [y for y, keep in zip(labels, mask, strict=True) if keep]
        prev = labels if rec.running is None else rec.running
        running = [y for y in prev if y in cset]
        rec.running = running
        notes = [n for n in (cal.note, backend_mismatch(cal, scores.backend), mode_mismatch(cal, scores.mode),
                             rule_mismatch(cal.answer_rule, rule_now)) if n]
        if rule_now.on:
            notes.append(f"answer memory {rule_now.name}")
        tag = (f"eps={cal.eps:g}, q_hat={cal.q_hat:.4f}, N={cal.n}" + (f" of {cal.category}" if cal.category else "")
               + "".join(f"; {n}" for n in notes))
        answer = None
        if len(running) == 1:
            stop, answer = True, running[0]
            reason = f"one answer left in the prediction set: {answer} (CP {tag})"
        elif not running:
            stop, answer = True, rec.fallback()
            reason = fallback_reason("the prediction set is empty", answer, f"CP {tag}")
        elif at_limit:
            stop, answer = True, rec.fallback()
            why = f"step limit reached with {len(running)} answers left {_fmt_set(running)}"
            reason = fallback_reason(why, answer, f"CP {tag}")
        else:
            stop = False
            reason = f"{len(running)} answers left {_fmt_set(running)} (CP {tag})"
        return Decision(
            episode_id=rec.episode_id,
            step=scores.step,
            rule=rule,
            stop=stop,
            reason=reason,
            prediction_set=list(running),
            step_set=cset,
            scores={y: float(r) for y, r in zip(labels, rho, strict=True)},
            answer=answer,
            q_hat=cal.q_hat,
        )

    stat_scores: dict[str, float] = {}
    stop = False
    answer = None
    if rule == "entropy":
        thr = rec.threshold if rec.threshold is not None else baselines.threshold_for("entropy", None)
        hit, h = baselines.entropy_stops(f, thr)
        stat_scores = {"entropy": h, "relevance": rel}
        if hit:
            stop, answer = True, argmax_now
            reason = f"answer entropy {h:.4f} nats < threshold {thr:g} (Eq. 4); answering {answer}"
        else:
            reason = f"answer entropy {h:.4f} nats >= threshold {thr:g}"
    elif rule == "relevance":
        thr = rec.threshold if rec.threshold is not None else baselines.threshold_for("relevance", None)
        hit, r = baselines.relevance_stops(rel, thr)
        stat_scores = {"relevance": r, "entropy": baselines.entropy(f)}
        if hit:
            stop, answer = True, argmax_now
            reason = f"relevance {r:.4f} > threshold {thr:g} (Eq. 5); answering {answer}"
        else:
            reason = f"relevance {r:.4f} <= threshold {thr:g}"
    else:  # max_steps
        stat_scores = {"relevance": rel, "entropy": baselines.entropy(f)}
        reason = f"running to the step limit ({scores.step + 1}/{rec.max_steps})"
    if not stop and at_limit and rec.task:
        stop, reason = True, f"step limit reached ({rec.max_steps} steps)"
    elif not stop and at_limit:
        stop, answer = True, rec.fallback()
        reason = fallback_reason(f"step limit reached ({rec.max_steps} steps)", answer)
    return Decision(
        episode_id=rec.episode_id,
        step=scores.step,
        rule=rule,
        stop=stop,
        reason=reason,
        scores=stat_scores,
        answer=answer,
    )


def end_message(
    rec: EpisodeRecord, state: EpisodeState, reason: str, answer: str | None, recording: str | None = None
) -> EpisodeEnd:
    """The :class:`EpisodeEnd` of an episode. ``correct`` compares with the ground truth only now, after
    the answer was decided, and only when the question carries one."""
    truth = rec.question.answer
    correct = None if (truth is None or answer is None or state != "stopped") else (answer == truth)
    prediction = list(rec.running) if (rec.stop.rule == "cp" and rec.running is not None) else []
    return EpisodeEnd(
        episode_id=rec.episode_id,
        robot=rec.robot,
        state=state,
        reason=reason,
        answer=answer,
        answer_text=rec.answer_text(answer),
        prediction_set=prediction,
        steps=rec.last_step + 1,
        max_steps=rec.max_steps,
        correct=correct,
        recording=recording,
    )


def check_threshold(start: EpisodeStart) -> float | None:
    """The baseline threshold of an episode (validated), None for cp / max_steps."""
    if start.stop.rule in ("entropy", "relevance"):
        value = baselines.threshold_for(start.stop.rule, start.stop.threshold)
        if not math.isfinite(value):
            raise ValueError("threshold must be finite")
        return value
    return None
