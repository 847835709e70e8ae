"""Evaluate exploration strategies and stopping rules by replaying recorded full-length traces (pure).

Until it stops, a robot's path does not depend on the stopping rule, so one full-length run per question
serves every comparison (Explore-EQA section VII): the answer at a normalised budget ``b`` is ``argmax f`` at
the step of highest ``Rel`` among the first ``max(1, floor(b*T))`` steps (Fig. 7), and each stopping rule is
replayed step by step through the stopper's own decision function (:func:`services.stopper.state.decide`), so
the benchmark measures exactly what the service does.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from eqa.messages import MemoryScore, StepScores, StopConfig, letters
from eqa_app.stats import Z95, paired_diff_ci, sign_test_p
from services.stopper.calibration import CalibrationTable, Trace, calibrate
from services.stopper.conformal import fallback_answer
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide

BUDGETS = tuple(round(0.1 * k, 1) for k in range(1, 11))


def answer_within(trace: Trace, steps: int) -> str:
    """``argmax f`` at the step of highest ``Rel`` among the first ``steps`` steps."""
    n = max(1, min(steps, len(trace.steps)))
    f, rel = trace.arrays()
    return letters(len(trace.choices))[fallback_answer(f[:n], rel[:n])]


def correct_at_budget(trace: Trace, budget: float) -> bool:
    """Whether the answer within ``floor(budget * T)`` steps is right (Fig. 7)."""
    return answer_within(trace, math.floor(budget * trace.max_steps + 1e-9)) == trace.answer


def success_at_budgets(traces: Sequence[Trace], budgets: Sequence[float] = BUDGETS) -> list[float]:
    """Success rate at each normalised step budget (Fig. 7)."""
    if not traces:
        return [math.nan] * len(budgets)
    return [float(np.mean([correct_at_budget(t, b) for t in traces])) for b in budgets]


@dataclass(frozen=True)
class Paired:
    """Two strategies on the same questions at one budget: the questions only ``a`` gets right, only ``b``
    gets right, and the exact two-sided sign-test p-value over those discordant questions; ``n`` paired
    questions and the success difference ``diff`` = (a_only - b_only) / n with its 95 % confidence interval
    (:func:`paired_diff_ci`)."""

    budget: float
    a_only: int
    b_only: int
    p_value: float
    n: int = 0
    diff: float = 0.0
    ci_low: float = 0.0
    ci_high: float = 0.0


def paired_comparison(a: Sequence[Trace], b: Sequence[Trace], budgets: Sequence[float]) -> list[Paired]:
    """Paired comparison of two strategies' runs of the same questions (matched by question id). With the
    oracle's draws seeded per (question, step), two runs of a question differ only where the robots went, so
    the discordant questions carry the whole difference."""
    b_by_id = {t.question_id: t for t in b}
    pairs = [(t, b_by_id[t.question_id]) for t in a if t.question_id in b_by_id]
    out = []
    for budget in budgets:
        ra = [correct_at_budget(x, budget) for x, _ in pairs]
        rb = [correct_at_budget(y, budget) for _, y in pairs]
        a_only = sum(x and not y for x, y in zip(ra, rb, strict=True))
        b_only = sum(y and not x for x, y in zip(ra, rb, strict=True))
        d, lo, hi = paired_diff_ci(a_only, b_only, len(pairs))
        out.append(Paired(budget, a_only, b_only, sign_test_p(a_only, b_only), len(pairs), d, lo, hi))
    return out


def pool_paired(groups: Sequence[Sequence[Paired]]) -> list[Paired]:
    """Paired comparisons of several seeds pooled budget by budget: discordant counts and n add up (the
    questions of different seeds are different questions), then the sign test and the interval."""
    out = []
    for rows in zip(*groups, strict=True):
        a = sum(r.a_only for r in rows)
        b = sum(r.b_only for r in rows)
        n = sum(r.n for r in rows)
        d, lo, hi = paired_diff_ci(a, b, n)
        out.append(Paired(rows[0].budget, a, b, sign_test_p(a, b), n, d, lo, hi))
    return out


def first_evidence_steps(traces: Sequence[Trace], threshold: float = 0.3) -> list[float | None]:
    """Per episode, the normalised step ``(k + 1) / T`` by which relevance first reached ``threshold`` (the
    scorer saw evidence of the answer within that share of the budget), None when it never did."""
    out: list[float | None] = []
    for t in traces:
        k = next((i for i, s in enumerate(t.steps) if s.relevance >= threshold), None)
        out.append(None if k is None else (k + 1) / t.max_steps)
    return out


def evidence_cdf(traces: Sequence[Trace], budgets: Sequence[float], threshold: float = 0.3) -> list[float]:
    """Share of episodes that saw the evidence within each normalised budget (the first-evidence CDF)."""
    first = first_evidence_steps(traces, threshold)
    if not first:
        return [math.nan] * len(budgets)
    return [float(np.mean([f is not None and f <= b + 1e-9 for f in first])) for b in budgets]


def median_first_evidence(traces: Sequence[Trace], threshold: float = 0.3) -> float | None:
    """Median over all episodes of the normalised first-evidence step (episodes that never saw it count as
    later than T); None when more than half never saw it."""
    first = sorted(math.inf if f is None else f for f in first_evidence_steps(traces, threshold))
    if not first:
        return None
    m = first[(len(first) - 1) // 2]
    return None if math.isinf(m) else float(m)


def paired_first_evidence(a: Sequence[Trace], b: Sequence[Trace], threshold: float = 0.3) -> Paired:
    """Which of two strategies saw the evidence sooner on the same questions (never = later than T): the
    questions where ``a`` was strictly sooner, where ``b`` was, the sign test, and the mean difference of
    the first-evidence share of T (``b - a``, never counted as 1.0) with a 95 % interval."""
    b_by_id = {t.question_id: t for t in b}
    pairs = [(t, b_by_id[t.question_id]) for t in a if t.question_id in b_by_id]
    fa = first_evidence_steps([x for x, _ in pairs], threshold)
    fb = first_evidence_steps([y for _, y in pairs], threshold)
    ia = [math.inf if v is None else v for v in fa]
    ib = [math.inf if v is None else v for v in fb]
    a_first = sum(x < y for x, y in zip(ia, ib, strict=True))
    b_first = sum(y < x for x, y in zip(ia, ib, strict=True))
    diffs = np.array([min(y, 1.0) - min(x, 1.0) for x, y in zip(ia, ib, strict=True)])
    n = len(diffs)
    if n == 0:
        return Paired(1.0, 0, 0, 1.0, 0, math.nan, math.nan, math.nan)
    d = float(diffs.mean())
    se = float(diffs.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return Paired(1.0, a_first, b_first, sign_test_p(a_first, b_first), n, d, d - Z95 * se, d + Z95 * se)


def first_evidence(traces: Sequence[Trace], threshold: float = 0.3) -> float:
    """Mean normalised step (step / T) at which relevance first reaches ``threshold``, over the episodes where
    it does: how early a strategy finds the evidence it finds."""
    first = [(next((k for k, s in enumerate(t.steps) if s.relevance >= threshold), None), t.max_steps)
             for t in traces]
    shares = [k / n for k, n in first if k is not None]
    return float(np.mean(shares)) if shares else math.nan


def evidence_share(traces: Sequence[Trace], threshold: float = 0.3) -> float:
    """Share of episodes whose best relevance reaches ``threshold`` (the scorer saw evidence of the answer)."""
    if not traces:
        return math.nan
    return float(np.mean([max((s.relevance for s in t.steps), default=0.0) >= threshold for t in traces]))


@dataclass(frozen=True)
class EvidenceSplit:
    """Success at one budget split by whether the evidence was seen within it (Rel >= threshold), and what that
    split explains of a gap between two strategies: ``n_seen`` episodes saw it (``success_seen`` of them were
    right), ``n_unseen`` did not (``success_unseen``); ``lift`` = success_seen - success_unseen is what one more
    episode that sees the evidence is worth on average."""

    budget: float
    n_seen: int
    success_seen: float
    n_unseen: int
    success_unseen: float

    @property
    def lift(self) -> float:
        return self.success_seen - self.success_unseen


def success_by_evidence(traces: Sequence[Trace], budget: float = 1.0, threshold: float = 0.3) -> EvidenceSplit:
    """Success at ``budget`` among the episodes that saw the evidence within it and among those that did not:
    the answer rule (argmax f at the most relevant step, Fig. 7) guesses from priors when it never saw it, so a
    strategy that sees the evidence in dE more episodes gains about dE x lift in success."""
    first = first_evidence_steps(traces, threshold)
    seen = [correct_at_budget(t, budget) for t, f in zip(traces, first, strict=True) if f is not None and
            f <= budget + 1e-9]
    unseen = [correct_at_budget(t, budget) for t, f in zip(traces, first, strict=True) if f is None or
              f > budget + 1e-9]
    return EvidenceSplit(budget, len(seen), float(np.mean(seen)) if seen else math.nan, len(unseen),
                         float(np.mean(unseen)) if unseen else math.nan)


@dataclass(frozen=True)
class Replay:
    answer: str | None
    steps: int  # steps used (the stop step + 1)
    max_steps: int
    correct: bool
    prediction_set: tuple[str, ...] = ()

    @property
    def normalized_steps(self) -> float:
        return self.steps / self.max_steps


def replay(trace: Trace, stop: StopConfig, calibration: CalibrationChoice | None = None) -> Replay:
    """Run the stopper's decision rule over a recorded trace, step by step, as the service would."""
    episode = EpisodeRecord(
        episode_id="replay",
        robot="replay",
        question={"text": "replay", "choices": trace.choices, "scene": trace.scene, "answer": trace.answer},
        strategy="semantic",
        stop=stop,
        max_steps=trace.max_steps,
        record=False,
        choices=list(trace.choices),
        calibration=calibration,
        threshold=stop.threshold,
    )
    # a warm trace's memory steps reach the stopper with step 0, as the mapper sends them (StepScores.memory)
    m = trace.memory_steps
    memory = [MemoryScore(answer_probs=s.answer_probs, relevance=s.relevance) for s in trace.steps[:m]]
    for t, s in enumerate(trace.steps[m:]):
        d = decide(episode, StepScores(episode_id="replay", step=t, answer_probs=s.answer_probs, relevance=s.relevance,
                                   memory=memory if t == 0 else []))
        if d is not None and d.stop:
            return Replay(d.answer, t + 1, trace.max_steps, d.answer == trace.answer, tuple(d.prediction_set))
    # The run ended before the stop rule fired (the planner found nothing left to explore): fallback answer.
    answer = episode.fallback()
    return Replay(answer, len(trace.steps) - m, trace.max_steps, answer == trace.answer, tuple(episode.running or ()))


@dataclass(frozen=True)
class CurvePoint:
    rule: str
    parameter: float
    success: float
    mean_normalized_steps: float
    coverage: float | None = None  # CP: share of episodes whose sequence-level set holds the truth


def cp_curve(table: CalibrationTable, test: Sequence[Trace]) -> list[CurvePoint]:
    """Success vs mean normalised steps over the table's eps grid, with empirical coverage (Fig. 9)."""
    from services.stopper.conformal import relevance_weighted_confidence, sequence_set

    out = []
    for entry in table.entries:
        cal = CalibrationChoice(q_hat=entry.q_hat, eps=entry.eps, asked_eps=entry.eps, n=table.n, source="bench")
        runs = [replay(t, StopConfig(rule="cp", eps=entry.eps), cal) for t in test]
        covered = []
        for t in test:
            f, rel = t.arrays()
            rhos = np.stack([relevance_weighted_confidence(f[i], rel[i]) for i in range(len(rel))])
            covered.append(bool(sequence_set(rhos, entry.q_hat)[letters(len(t.choices)).index(t.answer)]))
        out.append(_point("cp", entry.eps, runs, float(np.mean(covered))))
    return out


def threshold_curve(rule: str, thresholds: Iterable[float], test: Sequence[Trace]) -> list[CurvePoint]:
    """Success vs mean normalised steps of the entropy (Eq. 4) or relevance (Eq. 5) rule over thresholds."""
    return [_point(rule, thr, [replay(t, StopConfig(rule=rule, threshold=thr)) for t in test]) for thr in thresholds]


def _point(rule: str, parameter: float, runs: Sequence[Replay], coverage: float | None = None) -> CurvePoint:
    return CurvePoint(
        rule=rule,
        parameter=float(parameter),
        success=float(np.mean([r.correct for r in runs])) if runs else math.nan,
        mean_normalized_steps=float(np.mean([r.normalized_steps for r in runs])) if runs else math.nan,
        coverage=coverage,
    )


def calibrate_traces(traces: Sequence[Trace], eps_grid: Sequence[float], name: str) -> CalibrationTable:
    return calibrate(list(traces), list(eps_grid), name=name)


def by_group(traces: Sequence[Trace], key: str | None = None, groups: dict[str, str] | None = None
             ) -> dict[str, list[Trace]]:
    """Traces grouped by category (``key="category"``) or by a given question-id -> group map."""
    out: dict[str, list[Trace]] = defaultdict(list)
    for t in traces:
        g = groups.get(t.question_id) if groups is not None else getattr(t, key or "category")
        out[str(g)].append(t)
    return dict(sorted(out.items()))


def area_bin(area_m2: float, width: float = 100.0) -> str:
    lo = int(area_m2 // width * width)
    return f"{lo}-{lo + int(width)}"


SIZE_CLASSES = ("small", "medium", "large")


def size_cuts(areas: Iterable[float]) -> tuple[float, float]:
    """Floor-area cut points (m²) of the small / medium / large house classes: the tertiles of the distinct
    houses' areas, so that each class holds about a third of the houses of the benchmark at hand."""
    vals = np.unique(np.asarray(list(areas), dtype=np.float64))
    if vals.size == 0:
        return (math.inf, math.inf)
    lo, hi = np.quantile(vals, [1 / 3, 2 / 3])
    return float(lo), float(hi)


def size_class(area_m2: float, cuts: tuple[float, float]) -> str:
    """``small`` up to the first cut, ``medium`` up to the second, ``large`` above (:func:`size_cuts`)."""
    return SIZE_CLASSES[0] if area_m2 <= cuts[0] else SIZE_CLASSES[1] if area_m2 <= cuts[1] else SIZE_CLASSES[2]
