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
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from eqa.messages import (
    Decision,
    EpisodeEnd,
    EpisodeStart,
    EpisodeState,
    MemoryBounds,
    ObjectEvidence,
    Question,
    StepScores,
    StopConfig,
    Strategy,
    WarmStart,
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
from services.stopper.object_evidence import EvidenceParams, budget_answer, combine, layer_distribution

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
    mode: str | None = None  # ... and its mode: logprobs / sampling
    category: str | None = None  # Mondrian: the category whose own q_hat this is
    answer_rule: str | None = None  # the answer rule the table was calibrated with (None = single)
    # how the table's counting traces were answered: "views" (counting across views), "frame", None (unrecorded)
    answer_counting: str | None = None
    # the episodes the table was calibrated on (provenance "home"): cold, warm (with the memory bounds of their
    # warm starts, None when the traces did not record them) or unknown (a table that records neither)
    table_kind: Literal["cold", "warm", "unknown"] = "unknown"
    warm_bounds: MemoryBounds | None = None
    warm_calibrated: bool | None = None  # in a warm episode: whether this table holds for its warm start


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
    counting = table.provenance.get("answer_counting")
    kind, bounds = table_home(table)
    choice = CalibrationChoice(q_hat=entry.q_hat, eps=entry.eps, asked_eps=eps, n=table.n, source=where, note=note,
                               backend=str(backend) if backend else None, mode=str(mode) if mode else None,
                               answer_rule=str(rule) if rule else None, table_kind=kind, warm_bounds=bounds,
                               answer_counting=str(counting) if counting else None)
    return choice, ""


WARM_NOT_CALIBRATED = "warm start: stopping not calibrated for warm starts"


def table_home(table: CalibrationTable) -> tuple[Literal["cold", "warm", "unknown"], MemoryBounds | None]:
    """Whether ``table`` was calibrated on cold or warm episodes, and the memory bounds of the warm ones
    (``provenance["home"]``, written by :func:`services.stopper.calibration.calibrate`)."""
    home = table.provenance.get("home")
    if not isinstance(home, dict) or not isinstance(home.get("warm"), bool):
        return "unknown", None
    if not home["warm"]:
        return "cold", None
    try:
        bounds = MemoryBounds.model_validate(home["bounds"]) if home.get("bounds") else None
    except ValueError:
        bounds = None
    return "warm", bounds


def _noted(cal: CalibrationChoice, note: str, **update: object) -> CalibrationChoice:
    return cal.model_copy(update={"note": "; ".join(n for n in (cal.note, note) if n), **update})


def calibration_for_start(episode: EpisodeRecord, warm: WarmStart | None) -> None:
    """At an episode's first step, the table its stopping runs on. A cold start (``warm`` None: no home, or the
    first question in an empty home) keeps the cold table; a warm start takes the warm table the stopper
    resolved at the start (``episode.warm_calibration``, ``EQA_HOME_CALIBRATION_NAME``) when there is one, else
    keeps the cold table. Either way a warm start is marked ``warm_calibrated`` (in every Decision): False, with
    the reason in the calibration's note (so in every decision's and the end's reason), when its stopping is not
    calibrated for it: no warm table, a table of cold episodes, a table that records no memory bounds, or one
    whose bounds differ from the episode's. Memory steps add terms to Eq. 9's min over steps, so a cold table's
    q_hat says nothing of a warm episode's coverage (Claim 1 needs exchangeable calibration traces)."""
    cal = episode.calibration
    if cal is None:
        return
    if warm is None:
        if cal.table_kind == "warm":
            episode.calibration = _noted(cal, "the table was calibrated on warm starts; this episode starts cold")
        return
    episode.warm = warm
    table = episode.warm_calibration
    if table is None:
        why = episode.warm_missing or "no warm table"
        episode.calibration = _noted(cal, f"{WARM_NOT_CALIBRATED}: {why}; stopping on the cold table",
                                     warm_calibrated=False)
        return
    problems = []
    if table.table_kind == "cold":
        problems.append(f"table {table.source} was calibrated on cold episodes")
    elif table.warm_bounds is None:
        problems.append(f"table {table.source} records no memory bounds")
    else:
        diff = table.warm_bounds.differences(warm.bounds)
        if diff:
            problems.append(f"memory bounds differ from table {table.source}'s (table vs episode: {', '.join(diff)})")
    if problems:
        episode.calibration = _noted(table, f"{WARM_NOT_CALIBRATED}: {'; '.join(problems)}", warm_calibrated=False)
    else:
        episode.calibration = table.model_copy(update={"warm_calibrated": True})



def backend_mismatch(cal: CalibrationChoice, scores_backend: str | None) -> str:
    """A warning when the scores come from another scorer backend than the calibration did: the coverage
    guarantee (Claim 1) holds only for the model the table was calibrated on."""
    if not cal.backend or not scores_backend or scores_backend == cal.backend:
        return ""
    return (f"table calibrated on the {cal.backend} scorer, these scores come from {scores_backend}: "
            f"run `eqa calibrate` with this scorer for the guarantee")


def mode_mismatch(cal: CalibrationChoice, scores_mode: str | None) -> str:
    """A warning when the scores were read in another mode than the calibration's: sampled
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
    # answer memory (services/stopper/answer_memory.py), fixed at the episode's start; 0 = single view
    answer_memory: int = Field(default=0, ge=0, le=16)
    answer_fusion: str = "loglinear"
    # pool the object layer's evidence (StepScores.object_evidence) into f; None = off
    object_evidence: tuple[float, float] | None = None  # (psi_min, weight)
    # the evidence categories pooled: existence with EQA_OBJECT_EVIDENCE, counting with EQA_ANSWER_COUNTING=views
    evidence_categories: list[Literal["counting", "existence"]] = Field(
        default_factory=lambda: ["counting", "existence"])
    # counting across views: the VLM's own f of every step and the layer's latest counting evidence, for the
    # answer at a budget (object_evidence.budget_answer: f(x^t*) pooled with the count of every view so far)
    vlm_probs: list[list[float]] = Field(default_factory=list)
    count_latest: ObjectEvidence | None = None
    task: bool = False  # a task episode: the planner ends it, there is no answer to give
    # warm start: the leading entries of probs / relevance are the home's re-scored views (StepScores.memory),
    # decided on before step 0 and not counted as steps
    memory_steps: int = Field(default=0, ge=0)
    # a question in a home: the warm table resolved at the start (None: none, warm_missing says why), taken at
    # the first step if that step says the episode started warm (calibration_for_start); warm: that start
    warm_calibration: CalibrationChoice | None = None
    warm_missing: str = ""
    warm: WarmStart | None = None

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
            memory_steps=self.memory_steps,
            warm=self.warm,
            answer_counting="views" if self.count_latest is not None else None,
        )

    def fallback(self) -> str | None:
        """``argmax f`` at the step of highest ``Rel`` (None before any step); with the answer memory on, the
        argmax of the pooled distribution of the K most relevant views."""
        if not self.probs:
            return None
        if (self.count_latest is not None and self.object_evidence is not None and not self.answer_rule.on
                and len(self.vlm_probs) == len(self.probs)):
            # counting across views: the answer at a budget pools f(x^t*) with the count of every view so far
            params = EvidenceParams(psi_min=self.object_evidence[0], weight=self.object_evidence[1])
            return self.labels[budget_answer(self.vlm_probs, self.relevance, self.count_latest, self.choices, params)]
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


@dataclass(frozen=True)
class RuleStep:
    """What a stop rule decides on: the episode (this step already recorded in it), the step's scores, its
    answer distribution ``f`` (the object layer's evidence pooled in when on) and relevance ``Rel``."""

    episode: EpisodeRecord
    scores: StepScores
    f: np.ndarray
    relevance: float

    @property
    def labels(self) -> list[str]:
        return self.episode.labels

    @property
    def at_limit(self) -> bool:
        return self.scores.step >= self.episode.max_steps - 1

    @property
    def argmax(self) -> str:
        return self.labels[int(np.argmax(self.f))]


StopRuleFn = Callable[[RuleStep], Decision]


def counting_mismatch(cal: CalibrationChoice, episode: EpisodeRecord) -> str:
    """A warning when a counting question is answered by another counting rule than the table's counting traces
    were: the pooled f of counting across views is another score function, so Claim 1 holds only for a table
    calibrated on traces of the same rule (a table that records none is taken as the single-frame rule)."""
    counts = episode.count_latest is not None
    if not counts and episode.question.category != "counting":
        return ""
    have = cal.answer_counting or "frame"
    now = "views" if counts else "frame"
    if have == now:
        return ""
    return (f"table calibrated with counting rule {have}, this counting question is answered with {now}: run "
            f"`eqa calibrate` with EQA_ANSWER_COUNTING={now} for the guarantee")


def _cp_tag(episode: EpisodeRecord, cal: CalibrationChoice, scores: StepScores, rule_now: AnswerRule) -> str:
    notes = [n for n in (cal.note, backend_mismatch(cal, scores.backend), mode_mismatch(cal, scores.mode),
                         rule_mismatch(cal.answer_rule, rule_now), counting_mismatch(cal, episode)) if n]
    if rule_now.on:
        notes.append(f"answer memory {rule_now.name}")
    return (f"eps={cal.eps:g}, q_hat={cal.q_hat:.4f}, N={cal.n}" + (f" of {cal.category}" if cal.category else "")
            + "".join(f"; {n}" for n in notes))


def cp_rule(step: RuleStep) -> Decision:
    """Conformal stopping (Explore-EQA Eq. 7-9): the step's prediction set of calibrated relevance-weighted
    confidences, intersected with the running set; stop when one answer is left (or none, or at the limit)."""
    episode, scores, labels = step.episode, step.scores, step.labels
    cal = episode.calibration
    if cal is None:
        raise RuntimeError("cp episode without calibration")  # guarded at EpisodeStart
    rule_now = episode.answer_rule
    if rule_now.on:  # pooled scores of the K most relevant views so far (calibrated with the same rule)
        pf, pr = transform(np.asarray(episode.probs), np.asarray(episode.relevance), rule_now)
        rho = relevance_weighted_confidence(pf[-1], float(pr[-1]))
    else:
        rho = relevance_weighted_confidence(step.f, step.relevance)
    mask = step_set(rho, cal.q_hat)
    cset = [y for y, keep in zip(labels, mask, strict=True) if keep]
    prev = labels if episode.running is None else episode.running
    running = [y for y in prev if y in cset]
    episode.running = running
    tag = _cp_tag(episode, cal, scores, rule_now)
    answer = None
    if len(running) == 1:
        stop, answer = True, running[0]
        reason = f"one answer left in the prediction set: {answer} (CP {tag})"
    elif not running:
        stop, answer = True, episode.fallback()
        reason = fallback_reason("the prediction set is empty", answer, f"CP {tag}")
    elif step.at_limit:
        stop, answer = True, episode.fallback()
        why = f"step limit reached with {len(running)} answers left {_fmt_set(running)}"
        reason = fallback_reason(why, answer, f"CP {tag}")
    else:
        stop = False
        reason = f"{len(running)} answers left {_fmt_set(running)} (CP {tag})"
    return Decision(
        episode_id=episode.episode_id,
        step=scores.step,
        rule=episode.stop.rule,
        stop=stop,
        reason=reason,
        prediction_set=list(running),
        step_set=cset,
        scores={y: float(r) for y, r in zip(labels, rho, strict=True)},
        answer=answer,
        q_hat=cal.q_hat,
        warm_calibrated=cal.warm_calibrated,
    )


def _baseline(step: RuleStep, hit: bool, reason: str, stat_scores: dict[str, float]) -> Decision:
    """A baseline rule's decision: answer argmax f when it fires, else at the step limit the fallback answer."""
    episode = step.episode
    stop, answer = hit, step.argmax if hit else None
    if not stop and step.at_limit and episode.task:  # a task: the planner ends it, there is no answer to give
        stop, reason = True, f"step limit reached ({episode.max_steps} steps)"
    elif not stop and step.at_limit:
        stop, answer = True, episode.fallback()
        reason = fallback_reason(f"step limit reached ({episode.max_steps} steps)", answer)
    return Decision(episode_id=episode.episode_id, step=step.scores.step, rule=episode.stop.rule, stop=stop,
                    reason=reason, scores=stat_scores, answer=answer)


def _threshold(episode: EpisodeRecord, rule: str) -> float:
    return episode.threshold if episode.threshold is not None else baselines.threshold_for(rule, None)


def entropy_rule(step: RuleStep) -> Decision:
    """Stop when the answer entropy falls under the threshold (Explore-EQA Eq. 4)."""
    thr = _threshold(step.episode, "entropy")
    hit, h = baselines.entropy_stops(step.f, thr)
    said = f"< threshold {thr:g} (Eq. 4); answering {step.argmax}" if hit else f">= threshold {thr:g}"
    return _baseline(step, hit, f"answer entropy {h:.4f} nats {said}", {"entropy": h, "relevance": step.relevance})


def relevance_rule(step: RuleStep) -> Decision:
    """Stop when the step's relevance exceeds the threshold (Explore-EQA Eq. 5)."""
    thr = _threshold(step.episode, "relevance")
    hit, r = baselines.relevance_stops(step.relevance, thr)
    said = f"> threshold {thr:g} (Eq. 5); answering {step.argmax}" if hit else f"<= threshold {thr:g}"
    return _baseline(step, hit, f"relevance {r:.4f} {said}", {"relevance": r, "entropy": baselines.entropy(step.f)})


def max_steps_rule(step: RuleStep) -> Decision:
    """Run to the step limit and answer there (Explore-EQA's answer at a budget)."""
    reason = f"running to the step limit ({step.scores.step + 1}/{step.episode.max_steps})"
    return _baseline(step, False, reason, {"relevance": step.relevance, "entropy": baselines.entropy(step.f)})


STOP_RULES: dict[str, StopRuleFn] = {
    "cp": cp_rule,
    "entropy": entropy_rule,
    "relevance": relevance_rule,
    "max_steps": max_steps_rule,
}


def _record_step(episode: EpisodeRecord, scores: StepScores, memory: bool = False) -> RuleStep:
    """Check the step's scores and record them in ``episode`` (unchanged when they are invalid); a ``memory``
    step (a remembered view of the home, before step 0) is recorded in the scores but not as a step."""
    if not episode.choices:  # a question without choices: the scorer proposed them (Explore-EQA section VI-A)
        n = len(scores.choices) or len(scores.answer_probs)
        choices = list(scores.choices) or [f"option {c}" for c in letters(max(2, n))]
    else:
        choices = episode.choices
    f = check_scores(scores.answer_probs, scores.relevance, len(choices))
    rel = float(scores.relevance)
    vlm = [float(v) for v in f]
    ev = scores.object_evidence
    if episode.object_evidence is not None and ev is not None and ev.category in episode.evidence_categories:
        # the answer distribution used from here on (and stored in the trace, so a calibration from the
        # stopper's traces covers the combined score) pools the VLM's with the object layer's
        params = EvidenceParams(psi_min=episode.object_evidence[0], weight=episode.object_evidence[1])
        f = combine(f, layer_distribution(ev, choices, params), params.weight)
        if ev.category == "counting":
            if episode.count_latest is None:  # the steps before pooled nothing: their f is the VLM's
                episode.vlm_probs = [list(p) for p in episode.probs]
            episode.count_latest = ev
    if episode.count_latest is not None:
        episode.vlm_probs.append(vlm)
    if memory:
        episode.choices = choices
        episode.memory_steps += 1
        episode.probs.append([float(v) for v in f])
        episode.relevance.append(rel)
        return RuleStep(episode, scores, f, rel)
    if scores.step != episode.last_step + 1:
        log.warning("episode %s: step %d follows step %d (steps missing)", episode.episode_id, scores.step,
                    episode.last_step)
    episode.choices = choices
    episode.steps.append(scores.step)
    episode.probs.append([float(v) for v in f])
    episode.relevance.append(rel)
    return RuleStep(episode, scores, f, rel)


def decide(episode: EpisodeRecord, scores: StepScores) -> Decision | None:
    """Apply the scores of step ``scores.step`` to ``episode`` and return the decision of that step, by the
    episode's stop rule (:data:`STOP_RULES`).

    Returns None (and leaves ``episode`` unchanged) for a step already seen (a duplicate). Raises
    :class:`services.stopper.conformal.ScoreError` for invalid scores, leaving ``episode`` unchanged.
    """
    if scores.step <= episode.last_step:
        return None
    rule = STOP_RULES[episode.stop.rule]
    if not episode.probs and not episode.task and episode.stop.rule == "cp":
        calibration_for_start(episode, scores.warm)
    if scores.step_limit is not None and not episode.probs and not episode.task:
        # a question in a home whose map explored part of the house: its budget is what appendix B gives the
        # floor left (eqa.budget.warm_step_limit); the trace's max_steps is this limit, so a table calibrated on
        # such traces saw the same budget
        episode.max_steps = min(episode.max_steps, int(scores.step_limit))
    if scores.memory and not episode.probs:
        # Warm start: the home's remembered views re-scored for this question are the episode's first steps
        # (the same rule, the same running intersection of Eq. 9), so a question the memory already answers
        # stops before the first move. The trace keeps them (Trace.memory_steps): a table calibrated on warm
        # traces covers exactly this sequence.
        for m in scores.memory:
            mem = scores.model_copy(update={"answer_probs": m.answer_probs, "relevance": m.relevance, "memory": [],
                                            "object_evidence": None})
            decision = rule(_record_step(episode, mem, memory=True))
            if decision.stop:  # decided at step 0 on the memory alone; step 0's scores are kept in the trace
                _record_step(episode, scores)
                return decision
    return rule(_record_step(episode, scores))


def end_message(
    episode: EpisodeRecord, state: EpisodeState, reason: str, answer: str | None, recording: str | None = None
) -> EpisodeEnd:
    """The :class:`EpisodeEnd` of an episode. ``correct`` compares with the ground truth only now, after
    the answer was decided, and only when the question carries one."""
    truth = episode.question.answer
    correct = None if (truth is None or answer is None or state != "stopped") else (answer == truth)
    prediction = list(episode.running) if (episode.stop.rule == "cp" and episode.running is not None) else []
    return EpisodeEnd(
        episode_id=episode.episode_id,
        robot=episode.robot,
        state=state,
        reason=reason,
        answer=answer,
        answer_text=episode.answer_text(answer),
        prediction_set=prediction,
        steps=episode.last_step + 1,
        max_steps=episode.max_steps,
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
