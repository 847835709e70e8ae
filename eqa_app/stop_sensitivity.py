"""Stopping under a miscalibrated perception model: record each episode's perceptions once, re-score offline.

SIMULATED PERCEPTION MODEL, not a VLM. The oracle's miscalibration modes (``OracleParams.miscal_*``, documented
in ``services/vlm_scorer/backends/oracle.py``) change only the answer distribution f and the relevance Rel of a
step, never LSV / GSV, so the robot's path is the same at every level. This tool therefore:

1. **records** full-length episodes (``max_steps``) with the pure cores in one process per worker (sim render ->
   mapper -> oracle scorer -> planner, the functions the services call; no bus, no store, as
   ``eqa_app/benches/tune_oracle.py``), keeping per step what the oracle perceived: the target instances and the
   related-but-wrong ones with their image share and distance, the view's clutter, and the level-0 scores;
2. **re-scores** those perceptions at any miscalibration level (the draws are seeded per (question, step) as in
   the service; at level 0 the re-scored f and Rel are checked equal to the recorded ones) into
   :class:`services.stopper.calibration.Trace` objects that the benchmark's evaluation replays through the
   stopper's own decision function.

3. **sweeps** each mode's level, calibrates CP per benchmark seed on its calibration split, and compares CP
   (marginal and per-category), the relevance threshold and the entropy threshold on the test splits
   (:func:`sweep`; ``eqa bench stop --miscalibration ...`` prints, stores and plots it).

Operating points are chosen on the tuning seed (:data:`eqa.seeds.TUNING_SEED`) and evaluated on the evaluation
seeds (:data:`eqa.seeds.EVALUATION_SEEDS`), pooled and per seed, with paired comparisons on the same episodes.

    python -m eqa_app.stop_sensitivity record --seeds 11 1 2 3 --limit 90   # once (minutes)
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import pickle
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from eqa.seeds import EVALUATION_SEEDS
from eqa_app.core_runner import StepHooks
from eqa_app.stats import paired_outcomes, wilson_ci

log = logging.getLogger("stop_sensitivity")

DEFAULT_DIR = Path("var/sensitivity")


@dataclasses.dataclass
class PerceptionStep:
    targets: list[Any]  # oracle View tuples (label, image share, distance)
    related: list[Any]
    clutter: float
    probs: list[float]  # level-0 scores as the service computed them
    relevance: float


@dataclasses.dataclass
class PerceptionEpisode:
    question: Any  # eqa.messages.Question (with its ground truth; the oracle never reads it)
    seed: int
    strategy: str
    steps: list[PerceptionStep]
    seconds: float = 0.0


def benchmark_questions(seed: int, split: str, limit: int | None, scenes_dir: Any, bench: Any = None) -> list[Any]:
    """The ``split`` questions of benchmark ``seed`` (``bench``: the benchmark, when already loaded); ``limit``
    keeps the category mix (round-robin)."""
    if bench is None:
        from services.sim.questions import benchmark

        bench = benchmark(seed=seed, scenes_dir=scenes_dir)
    from services.sim.questions import category_round_robin

    qs = {"calibration": bench.calibration, "test": bench.test}[split]
    return list(qs) if limit is None or limit >= len(qs) else category_round_robin(qs, limit)


class _Perceptions(StepHooks):
    """The per-step record of :func:`run_episode` (a :class:`eqa_app.core_runner.StepHooks`): what the oracle
    perceived, and with strategy ``cp_guided`` the stopper's decision steering the planner."""

    def __init__(self, oracle: Any, target: Any, stopper: Any = None) -> None:
        self.oracle, self.target, self.stopper = oracle, target, stopper
        self.steps: list[PerceptionStep] = []

    def scored(self, step: int, frame: Any, request: Any, scores: Any) -> None:
        oracle, target = self.oracle, self.target
        self.steps.append(PerceptionStep(oracle.target_views(request, target), oracle.related_views(request, target),
                                         oracle.clutter(request), list(scores.answer_probs), float(scores.relevance)))

    def steer(self, step: int, step_map: Any, scores: Any) -> Any:
        if self.stopper is None:
            return step_map
        from eqa.messages import StepScores
        from services.planner.cp_guided import guided_map
        from services.stopper.state import decide

        episode = self.stopper
        decision = decide(episode, StepScores(episode_id=episode.episode_id, step=step,
                                              answer_probs=scores.answer_probs, relevance=scores.relevance))
        if decision is None or decision.stop:
            return None
        return guided_map(step_map, decision)


def run_episode(args: tuple[Any, ...]) -> PerceptionEpisode:
    """One full-length episode with the pure cores in this process (:func:`eqa_app.core_runner.run_episode_loop`).

    ``args`` = (question, strategy, width, height[, q_hat]): with strategy ``cp_guided`` the stopper's decision
    (:func:`services.stopper.state.decide` with ``q_hat``) is taken every step, as the planner service receives
    it, the frontier weights are re-tempered by its prediction set, and the episode ends when CP stops."""
    from eqa.messages import EpisodeStart
    from eqa.settings import Settings
    from eqa_app.benchmark_runner import question_seed
    from eqa_app.core_runner import EpisodeCores, run_episode_loop
    from services.mapper.episode_map import EpisodeMap
    from services.planner.step import PlannerParams
    from services.sim.render import Renderer
    from services.sim.service import load_scene
    from services.vlm_scorer.backends.oracle import OracleBackend, parse_target

    question, strategy, w, h = args[:4]
    q_hat = args[4] if len(args) > 4 else None
    stopper = None
    if strategy == "cp_guided":
        from eqa.messages import StopConfig
        from services.stopper.state import CalibrationChoice, EpisodeRecord

        if q_hat is None:
            raise ValueError("cp_guided needs the q_hat of the stopping rule")
    t0 = time.monotonic()
    settings = Settings()
    scene = load_scene(settings, question.scene)
    oracle = OracleBackend.from_settings(settings)
    if oracle.p.miscalibrated:
        raise RuntimeError("record with the oracle at miscalibration level 0 (unset EQA_ORACLE_MISCAL_*)")
    seed = question_seed(question.id)
    start = EpisodeStart(episode_id=f"sens-{question.id}", robot="r0", question=question, strategy=strategy,
                         max_steps=question.max_steps, seed=seed)
    if strategy == "cp_guided":
        stopper = EpisodeRecord.from_start(start.model_copy(update={"stop": StopConfig(rule="cp", eps=0.2)}), "r0")
        stopper.calibration = CalibrationChoice(q_hat=q_hat, eps=0.2, asked_eps=0.2, n=1, source="in-process")
    cores = EpisodeCores(scene, Renderer(scene), oracle, EpisodeMap(start), PlannerParams(), w, h)
    perceptions = _Perceptions(oracle, parse_target(question), stopper)
    run_episode_loop(question, strategy, cores, episode_id=start.episode_id, seed=seed, hooks=perceptions)
    return PerceptionEpisode(question, seed, strategy, perceptions.steps, time.monotonic() - t0)


def recording_path(out: Path, seed: int, split: str, strategy: str, size: str) -> Path:
    """One file per seed, split, strategy and image size, holding every question recorded so far (a smaller
    ``--limit`` reuses a larger run: the round-robin order of :func:`benchmark_questions` is the same)."""
    return out / f"seed{seed}-{split}-{strategy}-{size}.pkl"


def record(questions: list[Any], strategy: str, w: int, h: int, workers: int, path: Path,
           progress: bool = True, q_hat: float | None = None) -> list[PerceptionEpisode]:
    """Record ``questions`` (resumable: a partial file is extended, never recomputed)."""
    from tqdm import tqdm

    done: list[PerceptionEpisode] = load_recording(path) if path.is_file() else []
    have = {e.question.id for e in done}
    todo = [q for q in questions if q.id not in have]
    if todo:
        t0 = time.monotonic()
        path.parent.mkdir(parents=True, exist_ok=True)
        with ProcessPoolExecutor(workers) as pool, tqdm(total=len(questions), initial=len(questions) - len(todo),
                                                       desc=path.stem, unit="ep", file=sys.stderr,
                                                       disable=not progress) as bar:
            for i, ep in enumerate(pool.map(run_episode, [(q, strategy, w, h, q_hat) for q in todo])):
                done.append(ep)
                bar.update(1)
                if i % 10 == 9:  # checkpoint
                    _write(path, done)
        _write(path, done)
        log.info("%s: %d episodes in %.1f min", path.name, len(todo), (time.monotonic() - t0) / 60)
    by_id = {e.question.id: e for e in done}
    return [by_id[q.id] for q in questions if q.id in by_id]


class _Unpickler(pickle.Unpickler):
    """Recordings made by running this file as a script name its classes ``__main__``."""

    def find_class(self, module: str, name: str) -> Any:
        if module in ("__main__", "stop_sensitivity") and name in ("PerceptionEpisode", "PerceptionStep"):
            return globals()[name]
        return super().find_class(module, name)


def load_recording(path: Path) -> list[PerceptionEpisode]:
    """A recording written by :func:`record` (a pickle of our own making: never load one from elsewhere)."""
    with open(path, "rb") as fh:
        return _Unpickler(fh).load()


def _write(path: Path, episodes: list[PerceptionEpisode]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(pickle.dumps(episodes))
    tmp.replace(path)


def rescore(ep: PerceptionEpisode, params: Any, check_level0: bool = False) -> Any:
    """The episode's :class:`Trace` under the oracle knobs ``params`` (f and Rel re-drawn as the service
    draws them). ``check_level0``: assert that the level-0 re-score equals what was recorded."""

    from eqa.messages import Question
    from services.stopper.calibration import Trace, TraceStep
    from services.vlm_scorer.backends.oracle import OracleBackend, parse_target

    q: Question = ep.question
    oracle = OracleBackend(params)
    t = parse_target(q)
    blind = q.without_ground_truth()
    choices = list(q.choices)
    steps = []
    for step, s in enumerate(ep.steps):
        req = _Req(ep.seed, step, blind)
        probs, rel = oracle.miscalibrated_scores(req, choices, t, s.targets, s.related, s.clutter)
        if check_level0 and (probs != s.probs or rel != s.relevance):
            raise AssertionError(f"{q.id} step {step}: level-0 re-score differs from the recorded scores")
        steps.append(TraceStep(answer_probs=probs, relevance=rel))
    return Trace(question_id=q.id, scene=q.scene, category=q.category, choices=choices, answer=q.answer,
                 max_steps=q.max_steps, strategy=ep.strategy, steps=steps)


@dataclasses.dataclass
class _Req:
    """What the oracle's answer and relevance draws read of a ScoreRequest (seed, step, question)."""

    seed: int
    step: int
    question: Any


@dataclasses.dataclass
class _Level0:
    """An episode's level-0 draws, computed once: answer distributions, relevance, evidence quality."""

    probs: list[list[float]]
    relevance: list[float]
    quality: list[float]


_LEVEL0: dict[tuple[str, int], _Level0] = {}


def _level0(ep: PerceptionEpisode) -> _Level0:
    import numpy as np

    from services.vlm_scorer.backends.oracle import OracleBackend, _h, parse_target

    key = (ep.question.id, ep.seed)
    if key not in _LEVEL0:
        oracle = OracleBackend()
        q = ep.question.without_ground_truth()
        t = parse_target(q)
        probs, rel, qual = [], [], []
        for step, s in enumerate(ep.steps):
            rng = np.random.default_rng([ep.seed, _h(q.id), step])
            f, quality, right = oracle._answer(rng, _Req(ep.seed, step, q), list(q.choices), t,
                                               oracle.seen_targets(s.targets))
            probs.append(f)
            rel.append(oracle._relevance(rng, quality, right))
            qual.append(quality)
        _LEVEL0[key] = _Level0(probs, rel, qual)
    return _LEVEL0[key]


def rescore_arrays(ep: PerceptionEpisode, params: Any) -> tuple[Any, Any]:
    """``(f, Rel)`` arrays of the episode under ``params``: the same numbers as :func:`rescore` (a test checks
    it), computed from the episode's level-0 draws; only a step where a related object is taken for the target
    is drawn again in full."""
    import numpy as np

    from services.vlm_scorer.backends.oracle import OracleBackend, parse_target

    base = _level0(ep)
    oracle = OracleBackend(params)
    q = ep.question.without_ground_truth()
    t = parse_target(q)
    choices = list(q.choices)
    f, rel = [], []
    for step, s in enumerate(ep.steps):
        req = _Req(ep.seed, step, q)
        if s.related and oracle.related_confused(req, s.related):
            probs, r = oracle.miscalibrated_scores(req, choices, t, s.targets, s.related, s.clutter)
        else:
            probs = oracle.confident_when_irrelevant(base.probs[step], base.quality[step])
            r = oracle.biased_relevance(base.relevance[step], t.type, s.clutter)
        f.append(probs)
        rel.append(r)
    return np.asarray(f, dtype=np.float64), np.asarray(rel, dtype=np.float64)


# ---- fast replay of the stopping rules (the stopper's decide(), vectorised; tests check they agree) -------


@dataclasses.dataclass(frozen=True)
class Outcome:
    """One episode under one rule and parameter."""

    correct: bool
    norm_steps: float
    covered: bool | None = None  # CP: the sequence-level set holds the truth


@dataclasses.dataclass
class Episode:
    """A re-scored trace as arrays."""

    qid: str
    category: str
    f: Any  # (T, K)
    rel: Any  # (T,)
    truth: int
    max_steps: int

    @classmethod
    def of(cls, trace: Any) -> Episode:
        from eqa.messages import letters

        f, rel = trace.arrays()
        return cls(trace.question_id, trace.category or "", f, rel, letters(len(trace.choices)).index(trace.answer),
                   trace.max_steps)


def replay_fast(ep: Episode, rule: str, parameter: float) -> Outcome:
    """What :func:`services.stopper.state.decide` does step by step, on arrays
    (:func:`services.stopper.replay.replay_arrays`): ``rule`` is ``cp`` (parameter = q_hat), ``relevance``,
    ``entropy`` (parameter = threshold) or ``max_steps``."""
    from services.stopper.replay import replay_arrays

    stop = replay_arrays(ep.f, ep.rel, ep.max_steps, rule, parameter)
    return Outcome(stop.answer == ep.truth, (stop.step + 1) / ep.max_steps, stop.covers(ep.truth))


# ---- the sweep ---------------------------------------------------------------------------------------------

MODES = ("category", "view", "related", "irrelevant", "all")
DEFAULT_LEVELS = (0.0, 0.25, 0.5, 0.75, 1.0)
EPS_SWEEP = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.6, 0.7, 0.8)
RELEVANCE_SWEEP = (0.9, 0.8, 0.7, 0.6, 0.5, 0.45, 0.4, 0.35, 0.3, 0.25, 0.2, 0.175, 0.15, 0.125, 0.1, 0.075, 0.05)
ENTROPY_SWEEP = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 1.1, 1.3)
SUCCESS_TOL = 0.02  # an operating point must reach the run-to-limit success minus this on the tuning seed
COVERAGE_EPS = 0.2  # the eps whose per-category coverage is reported


def params_at(mode: str, level: float) -> Any:
    from services.vlm_scorer.backends.oracle import MISCALIBRATION_MODES, OracleParams

    names = MISCALIBRATION_MODES if mode == "all" else (f"miscal_{mode}",)
    if not all(n in MISCALIBRATION_MODES for n in names):
        raise ValueError(f"unknown miscalibration mode {mode!r}; choose from {', '.join(MODES)}")
    return dataclasses.replace(OracleParams(), **{n: level for n in names})


@dataclasses.dataclass
class SeedData:
    seed: int
    calibration: list[PerceptionEpisode]
    test: list[PerceptionEpisode]


def _rules(table: Any) -> dict[str, list[tuple[float, Any]]]:
    """(parameter, how to get the per-episode CP threshold) for each rule; CP parameters are eps."""
    from services.stopper.state import resolve_calibration

    marginal = table.model_copy(update={"groups": {}})
    cache: dict[tuple[float, bool, str], float] = {}

    def cp(eps: float, mondrian: bool) -> Any:
        def q(ep: Episode) -> float:
            key = (eps, mondrian, ep.category)
            if key not in cache:
                choice, _ = resolve_calibration(table if mondrian else marginal, "sweep", eps, "sweep", ep.category)
                assert choice is not None
                cache[key] = choice.q_hat
            return cache[key]
        return q

    out: dict[str, list[tuple[float, Any]]] = {
        "cp": [(e, cp(e, False)) for e in table.eps_grid],
        "cp_mondrian": [(e, cp(e, True)) for e in table.eps_grid],
        "relevance": [(r, r) for r in RELEVANCE_SWEEP],
        "entropy": [(h, h) for h in ENTROPY_SWEEP],
    }
    return out


def _episode(ep: PerceptionEpisode, params: Any) -> Episode:
    from eqa.messages import letters

    f, rel = rescore_arrays(ep, params)
    q = ep.question
    return Episode(q.id, q.category or "", f, rel, letters(len(q.choices)).index(q.answer), q.max_steps)


def sweep_table(cal: list[Episode], grid: list[float]) -> Any:
    """The calibration table of these episodes, marginal and per category (what ``calibrate(...,
    by_category=True)`` computes from traces: the same kappas, quantiles and groups)."""
    from services.stopper.calibration import CalibrationEntry, CalibrationTable, mondrian_groups
    from services.stopper.conformal import conformal_quantile, nonconformity, quantile_rank

    kappas = [nonconformity(e.f, e.rel, e.truth) for e in cal]
    cats = [e.category for e in cal]
    entries = [CalibrationEntry(eps=x, q_hat=conformal_quantile(kappas, x), k=quantile_rank(len(kappas), x))
               for x in grid]
    return CalibrationTable(name="sweep", n=len(kappas), kappas=kappas, question_ids=[e.qid for e in cal],
                            entries=entries, groups=mondrian_groups(kappas, cats, grid), categories=cats)


def evaluate_seed(data: SeedData, params: Any) -> dict[str, Any]:
    """Calibrate on the seed's calibration split (marginal and per category), replay every rule and parameter
    on its test split; per-episode outcomes keyed by rule -> parameter."""
    cal = [_episode(e, params) for e in data.calibration]
    test = [_episode(e, params) for e in data.test]
    grid = [e for e in EPS_SWEEP if _defined(len(cal), e)]
    table = sweep_table(cal, grid)
    runs: dict[str, dict[float, list[Outcome]]] = {}
    for rule, plist in _rules(table).items():
        base = "cp" if rule.startswith("cp") else rule
        runs[rule] = {p: [replay_fast(ep, base, how(ep) if callable(how) else how) for ep in test]
                      for p, how in plist}
    runs["max_steps"] = {1.0: [replay_fast(ep, "max_steps", 0.0) for ep in test]}
    return {"runs": runs, "categories": [ep.category for ep in test], "n_cal": len(cal), "n_test": len(test),
            "q_hat": {f"{e.eps:g}": e.q_hat for e in table.entries}}


def _defined(n: int, eps: float) -> bool:
    from services.stopper.conformal import CalibrationError, quantile_rank

    try:
        quantile_rank(n, eps)
    except CalibrationError:
        return False
    return True


def _mean(xs: Any) -> float:
    import numpy as np

    return float(np.mean(xs)) if len(xs) else math.nan


def choose_operating_point(runs: dict[float, list[Outcome]], target: float) -> float:
    """The parameter with the fewest mean steps among those reaching ``target`` success (else the most
    successful one) - applied on the tuning seed only."""
    ok = [(p, _mean([o.norm_steps for o in r])) for p, r in runs.items() if _mean([o.correct for o in r]) >= target]
    if ok:
        return min(ok, key=lambda x: (x[1], x[0]))[0]
    return max(runs, key=lambda p: (_mean([o.correct for o in runs[p]]), -_mean([o.norm_steps for o in runs[p]])))


def paired_steps(a: list[Outcome], b: list[Outcome], seed: int = 0, n_boot: int = 2000) -> dict[str, float]:
    """Mean per-episode difference of normalised steps (a - b) with a paired bootstrap 95 % CI and its sign
    test, and the exact sign test of the success discordance (only a right / only b right)
    (:func:`eqa_app.stats.paired_outcomes`)."""
    r = paired_outcomes(a, b, seed, n_boot)
    return {"mean_diff": r["steps_diff"], "ci_low": r["steps_ci_low"], "ci_high": r["steps_ci_high"],
            "steps_sign_p": r["steps_sign_p"], "a_only_right": r["a_only"], "b_only_right": r["b_only"],
            "success_sign_p": r["p"]}


def sweep(seeds: dict[int, SeedData], tuning_seed: int, eval_seeds: list[int], modes: list[str],
          levels: list[float], progress: bool = True) -> dict[str, Any]:
    """The sensitivity study (module docstring): per mode and level, operating points chosen on
    ``tuning_seed``, evaluated on ``eval_seeds`` pooled and per seed."""
    from tqdm import tqdm

    from eqa.seeds import check_tuning_seed

    check_tuning_seed(tuning_seed)
    results: dict[str, Any] = {"tuning_seed": tuning_seed, "evaluation_seeds": eval_seeds,
                               "evaluation_seeds_declared": list(EVALUATION_SEEDS), "levels": levels, "modes": {},
                               "success_tol": SUCCESS_TOL, "coverage_eps": COVERAGE_EPS,
                               "n": {str(s): {"calibration": len(d.calibration), "test": len(d.test)}
                                     for s, d in seeds.items()}}
    cache: dict[float, dict[int, Any]] = {}
    jobs = [(m, lv) for m in modes for lv in levels]
    for mode, level in tqdm(jobs, desc="miscalibration sweep", unit="level", file=sys.stderr, disable=not progress):
        key = 0.0 if level == 0 else None
        if key is not None and key in cache:
            per_seed = cache[key]
        else:
            params = params_at(mode, level)
            per_seed = {s: evaluate_seed(d, params) for s, d in seeds.items()}
            if key is not None:
                cache[key] = per_seed
        results["modes"].setdefault(mode, []).append(_summarise(per_seed, tuning_seed, eval_seeds, level))
    return results


RULES = ("cp", "cp_mondrian", "relevance", "entropy")


def _summarise(per_seed: dict[int, Any], tuning_seed: int, eval_seeds: list[int], level: float) -> dict[str, Any]:
    tune = per_seed[tuning_seed]["runs"]
    target = _mean([o.correct for o in tune["max_steps"][1.0]]) - SUCCESS_TOL
    chosen = {rule: choose_operating_point(tune[rule], target) for rule in RULES}
    row: dict[str, Any] = {"level": level, "tuning_target_success": target, "chosen": chosen, "pooled": {},
                           "per_seed": {}, "paired": {}, "coverage": {}}

    def pooled(rule: str, p: float) -> list[Outcome]:
        return [o for s in eval_seeds for o in per_seed[s]["runs"][rule][p]]

    outcomes = {rule: pooled(rule, chosen[rule]) for rule in RULES}
    outcomes["max_steps"] = pooled("max_steps", 1.0)
    for rule, outs in outcomes.items():
        k = sum(o.correct for o in outs)
        row["pooled"][rule] = {"n": len(outs), "success": k / max(len(outs), 1), "success_ci": wilson_ci(k, len(outs)),
                               "mean_norm_steps": _mean([o.norm_steps for o in outs]),
                               "steps_saved": 1.0 - _mean([o.norm_steps for o in outs])}
    for s in eval_seeds:
        row["per_seed"][str(s)] = {
            rule: {"success": _mean([o.correct for o in per_seed[s]["runs"][rule][p]]),
                   "mean_norm_steps": _mean([o.norm_steps for o in per_seed[s]["runs"][rule][p]])}
            for rule, p in [*chosen.items(), ("max_steps", 1.0)]}
    for other in ("relevance", "entropy", "cp"):
        for mine in ("cp", "cp_mondrian"):
            if mine != other:
                row["paired"][f"{mine}_vs_{other}"] = paired_steps(outcomes[mine], outcomes[other])
    # coverage of the sequence-level set at COVERAGE_EPS and at the chosen eps: marginal, Mondrian, per category
    for rule in ("cp", "cp_mondrian"):
        for name, eps in (("at_eps", COVERAGE_EPS), ("at_chosen", chosen[rule])):
            cov: dict[str, Any] = {"eps": eps}
            outs = pooled(rule, eps) if eps in per_seed[eval_seeds[0]]["runs"][rule] else []
            cats = [c for s in eval_seeds for c in per_seed[s]["categories"]]
            cov["marginal"] = _mean([o.covered for o in outs])
            cov["n"] = len(outs)
            by: dict[str, list[bool]] = {}
            for o, c in zip(outs, cats, strict=False):
                by.setdefault(c, []).append(bool(o.covered))
            cov["by_category"] = {c: {"n": len(v), "coverage": _mean(v)} for c, v in sorted(by.items())}
            row["coverage"][f"{rule}_{name}"] = cov
    # curve reading (no tuning): the pooled evaluation curves' fewest steps at the run-to-limit success
    full = row["pooled"]["max_steps"]["success"]
    row["curve_steps_at_full_success"] = {}
    for rule in RULES:
        pts = [(_mean([o.norm_steps for o in pooled(rule, p)]), _mean([o.correct for o in pooled(rule, p)]))
               for p in per_seed[eval_seeds[0]]["runs"][rule]]
        ok = [st for st, su in pts if su >= full - SUCCESS_TOL]
        row["curve_steps_at_full_success"][rule] = min(ok) if ok else None
    return row


# ---- output --------------------------------------------------------------------------------------------------

LABEL = "simulated perception model, not a VLM"


def print_results(results: dict[str, Any]) -> None:
    ns = results["n"]
    print(f"Stopping under miscalibration ({LABEL}); operating points chosen on tuning seed {results['tuning_seed']}"
          f" (success >= run-to-limit - {results['success_tol']}), evaluated on seeds "
          f"{', '.join(map(str, results['evaluation_seeds']))} pooled "
          f"(test n = {sum(ns[str(s)]['test'] for s in results['evaluation_seeds'])}; calibration n per seed "
          f"{', '.join(str(ns[str(s)]['calibration']) for s in results['evaluation_seeds'])})")
    for mode, rows in results["modes"].items():
        print(f"\nmode {mode}:  level | success / steps saved: limit | CP | CP-Mondrian | relevance | entropy |"
              f" CP - relevance steps (95% CI) | coverage marginal / Mondrian at eps {results['coverage_eps']}")
        for r in rows:
            p = r["pooled"]
            pr = r["paired"]["cp_vs_relevance"]
            cells = " | ".join(f"{p[k]['success']:.3f}/{p[k]['steps_saved']:+.3f}"
                               for k in ("max_steps", "cp", "cp_mondrian", "relevance", "entropy"))
            cm, cmo = r["coverage"]["cp_at_eps"]["marginal"], r["coverage"]["cp_mondrian_at_eps"]["marginal"]
            ci = f"{pr['mean_diff']:+.3f} [{pr['ci_low']:+.3f}, {pr['ci_high']:+.3f}]"
            print(f"  {r['level']:4.2f} | {cells} | {ci} succ {pr['a_only_right']}/{pr['b_only_right']} "
                  f"p {pr['success_sign_p']:.2g} | {cm:.3f} / {cmo:.3f}")
            cur = r["curve_steps_at_full_success"]
            print("         curves, fewest norm. steps at run-to-limit success - tol: " + ", ".join(
                f"{k} {'never' if v is None else f'{v:.3f}'}" for k, v in cur.items()))


def plot_results(results: dict[str, Any], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = list(results["modes"])
    fig, axes = plt.subplots(len(modes), 3, figsize=(13, 2.6 * len(modes) + 0.8), squeeze=False)
    colors = {"cp": "tab:blue", "cp_mondrian": "tab:cyan", "relevance": "tab:orange", "entropy": "tab:green",
              "max_steps": "gray"}
    names = {"cp": "CP", "cp_mondrian": "CP per category", "relevance": "relevance thr.", "entropy": "entropy thr.",
             "max_steps": "run to limit"}
    for i, mode in enumerate(modes):
        rows = results["modes"][mode]
        lv = [r["level"] for r in rows]
        ax0, ax1, ax2 = axes[i]
        for rule in RULES:
            curve = [r["curve_steps_at_full_success"][rule] for r in rows]
            ax0.plot(lv, [math.nan if c is None else 1.0 - c for c in curve], marker="o", color=colors[rule],
                     label=names[rule])
            ax1.plot(lv, [r["pooled"][rule]["steps_saved"] for r in rows], marker="o", color=colors[rule])
        for rule, ls in (("cp", "-"), ("cp_mondrian", ":")):
            ax2.plot(lv, [r["coverage"][f"{rule}_at_eps"]["marginal"] for r in rows], marker="o", ls=ls,
                     color=colors[rule], label=f"{names[rule]} (marginal)")
            worst = [min((c["coverage"] for c in r["coverage"][f"{rule}_at_eps"]["by_category"].values()),
                         default=math.nan) for r in rows]
            ax2.plot(lv, worst, marker="x", ls=ls, color=colors[rule], alpha=0.5,
                     label=f"{names[rule]} (worst category)")
        ax2.axhline(1 - results["coverage_eps"], color="k", lw=0.8, ls="--", label="1 - eps")
        ax0.set(ylabel=f"{mode}\nsteps saved at equal success", ylim=(-0.05, 1))
        ax1.set(ylabel="steps saved, tuned points", ylim=(-0.05, 1))
        if i == 0:
            ax0.set_title(f"curves of the evaluation seeds: fewest steps reaching run-to-limit success - "
                          f"{results['success_tol']}", fontsize=8)
            ax1.set_title(f"operating points chosen on tuning seed {results['tuning_seed']} (success in the JSON)",
                          fontsize=8)
            ax2.set_title("coverage of the sequence-level set", fontsize=8)
        ax2.set(ylabel=f"CP coverage, eps {results['coverage_eps']}", ylim=(0, 1.02))
        for ax in (ax0, ax1, ax2):
            ax.grid(alpha=0.3)
            ax.set_xlabel("miscalibration level")
        if i == 0:
            ax0.legend(fontsize=7)
            ax2.legend(fontsize=6)
    ns = results["n"]
    n_test = sum(ns[str(s)]["test"] for s in results["evaluation_seeds"])
    fig.suptitle(f"Stopping under miscalibration ({LABEL}): operating points at equal success chosen on tuning seed "
                 f"{results['tuning_seed']}, evaluated on seeds {', '.join(map(str, results['evaluation_seeds']))} "
                 f"(n = {n_test} test episodes)", fontsize=9)
    fig.tight_layout()
    path = out / "stop_miscalibration.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def load_seeds(out: Path, seeds: list[int], limit: int | None, strategy: str, size: str, workers: int,
               scenes_dir: Any, progress: bool = True, loader: Any = None) -> dict[int, SeedData]:
    """Each seed's recorded calibration and test splits (recorded now when missing). ``loader(seed)``: the
    benchmark of a seed (``eqa bench`` passes its cached one; building one loads ~170 houses)."""
    from services.sim.questions import benchmark

    w, h = (int(v) for v in size.split("x"))
    data = {}
    for seed in seeds:
        parts = []
        bench = loader(seed) if loader is not None else benchmark(seed=seed, scenes_dir=scenes_dir)
        for split in ("calibration", "test"):
            lim = limit if split == "calibration" or limit is None else max(1, limit * 2 // 3)
            qs = benchmark_questions(seed, split, lim, scenes_dir, bench)
            parts.append(record(qs, strategy, w, h, workers, recording_path(out, seed, split, strategy, size),
                                progress))
        data[seed] = SeedData(seed, *parts)
    return data


def run(modes: list[str], levels: list[float], limit: int | None, out: Path, recordings: Path, strategy: str,
        size: str, workers: int, progress: bool = True, eval_seeds: list[int] | None = None,
        loader: Any = None) -> int:
    """``eqa bench stop --miscalibration``: record what is missing, sweep, print, store JSON and the plot.
    ``eval_seeds``: a subset of :data:`eqa.seeds.EVALUATION_SEEDS` (default all of them)."""
    import json

    from eqa.seeds import TUNING_SEED
    from eqa.settings import Settings

    eval_seeds = list(eval_seeds or EVALUATION_SEEDS)
    if not set(eval_seeds) <= set(EVALUATION_SEEDS):
        raise ValueError(f"evaluation seeds must be among {EVALUATION_SEEDS} (eqa.seeds), got {eval_seeds}")

    for m in modes:
        params_at(m, 0.0)  # validates the mode name
    if any(not 0.0 <= lv <= 1.0 for lv in levels):
        raise ValueError("miscalibration levels must lie in [0, 1]")
    levels = sorted(set(levels) | {0.0})
    settings = Settings()
    seeds = [TUNING_SEED, *eval_seeds]
    data = load_seeds(recordings, seeds, limit, strategy, size, workers, settings.scenes_path, progress, loader)
    results = sweep(data, TUNING_SEED, eval_seeds, modes, levels, progress)
    results.update({"scorer": f"oracle ({LABEL})", "strategy": strategy, "size": size, "limit_per_seed": limit})
    out.mkdir(parents=True, exist_ok=True)
    (out / "stop_miscalibration.json").write_text(json.dumps(results, indent=1))
    path = plot_results(results, out)
    print_results(results)
    print(f"results: {out / 'stop_miscalibration.json'}; plot: {path}")
    return 0


# ---- cp_guided against semantic -----------------------------------------------------------

GUIDED_EPS = 0.2  # the product's default eps (eqa ask / make demo), fixed in advance, not tuned


def compare_guided(recordings: Path, seeds: list[int], limit: int | None, size: str, workers: int, out: Path,
                   progress: bool = True, loader: Any = None) -> dict[str, Any]:
    """Steps to a single-answer CP set, and success, of ``cp_guided`` against ``semantic`` on each seed's test
    split: both stop by CP at :data:`GUIDED_EPS` with the q_hat calibrated on the seed's ``semantic``
    calibration split (level-0 perception); ``semantic`` is replayed from its full-length recording,
    ``cp_guided`` runs live (its path depends on the decisions). Paired on the same questions."""
    import json

    from eqa.settings import Settings
    from services.stopper.calibration import calibrate
    from services.vlm_scorer.backends.oracle import OracleParams

    settings = Settings()
    w, h = (int(v) for v in size.split("x"))
    data = load_seeds(recordings, seeds, limit, "semantic", size, workers, settings.scenes_path, progress, loader)
    res: dict[str, Any] = {"eps": GUIDED_EPS, "seeds": seeds, "per_seed": {}, "label": LABEL}
    pooled_sem: list[Outcome] = []
    pooled_gui: list[Outcome] = []
    for seed, d in data.items():
        table = calibrate([rescore(e, OracleParams()) for e in d.calibration], [GUIDED_EPS], name="guided")
        q_hat = table.entries[0].q_hat
        qs = [e.question for e in d.test]
        guided = record(qs, "cp_guided", w, h, workers,
                        recording_path(recordings, seed, "test", f"cp_guided-eps{GUIDED_EPS:g}", size), progress, q_hat)
        sem = [replay_fast(Episode.of(rescore(e, OracleParams())), "cp", q_hat) for e in d.test]
        gui = [replay_fast(Episode.of(rescore(e, OracleParams())), "cp", q_hat) for e in guided]
        single = [sum(1 for o in outs if o.norm_steps < 1.0) for outs in (sem, gui)]
        def summary(outs: list[Outcome], stopped: int) -> dict[str, Any]:
            return {"success": _mean([o.correct for o in outs]), "mean_norm_steps": _mean([o.norm_steps for o in outs]),
                    "stopped_before_limit": stopped}

        res["per_seed"][str(seed)] = {
            "n": len(sem), "q_hat": q_hat, "semantic": summary(sem, single[0]), "cp_guided": summary(gui, single[1]),
            "paired_guided_vs_semantic": paired_steps(gui, sem)}
        pooled_sem += sem
        pooled_gui += gui
    res["pooled"] = {"n": len(pooled_sem),
                     "semantic": {"success": _mean([o.correct for o in pooled_sem]),
                                  "mean_norm_steps": _mean([o.norm_steps for o in pooled_sem])},
                     "cp_guided": {"success": _mean([o.correct for o in pooled_gui]),
                                   "mean_norm_steps": _mean([o.norm_steps for o in pooled_gui])},
                     "paired_guided_vs_semantic": paired_steps(pooled_gui, pooled_sem)}
    out.mkdir(parents=True, exist_ok=True)
    (out / "cp_guided.json").write_text(json.dumps(res, indent=1))
    p = res["pooled"]
    pr = p["paired_guided_vs_semantic"]
    print(f"cp_guided vs semantic, CP eps {GUIDED_EPS} ({LABEL}), seeds {', '.join(map(str, seeds))}, n = {p['n']}:")
    for name in ("semantic", "cp_guided"):
        print(f"  {name:<10} success {p[name]['success']:.3f}  mean normalised steps {p[name]['mean_norm_steps']:.3f}")
    print(f"  cp_guided - semantic steps {pr['mean_diff']:+.3f} [{pr['ci_low']:+.3f}, {pr['ci_high']:+.3f}] "
          f"(sign p {pr['steps_sign_p']:.2g}); right only with cp_guided / only with semantic "
          f"{pr['a_only_right']} / {pr['b_only_right']} (p {pr['success_sign_p']:.2g})")
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="record perceptions of the calibration and test splits")
    r.add_argument("--seeds", type=int, nargs="+", default=[11, 1, 2, 3])
    r.add_argument("--limit", type=int, default=None, help="questions per split and seed (category mix kept); "
                   "the test split gets 2/3 of it, as eqa bench stop")
    r.add_argument("--strategy", default="semantic")
    r.add_argument("--size", default="320x240")
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--out", type=Path, default=DEFAULT_DIR)
    g = sub.add_parser("guided", help="cp_guided against semantic on the evaluation seeds' test splits")
    g.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    g.add_argument("--limit", type=int, default=None, help="as for record (the same recordings are reused)")
    g.add_argument("--size", default="320x240")
    g.add_argument("--workers", type=int, default=1)
    g.add_argument("--recordings", type=Path, default=DEFAULT_DIR)
    g.add_argument("--out", type=Path, default=Path("var/bench"))
    w = sub.add_parser("sweep", help="the sensitivity study (as eqa bench stop --miscalibration)")
    w.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    w.add_argument("--levels", nargs="+", type=float, default=list(DEFAULT_LEVELS))
    w.add_argument("--eval-seeds", type=int, nargs="+", default=None)
    w.add_argument("--limit", type=int, default=None)
    w.add_argument("--size", default="320x240")
    w.add_argument("--workers", type=int, default=1)
    w.add_argument("--recordings", type=Path, default=DEFAULT_DIR)
    w.add_argument("--out", type=Path, default=Path("var/bench"))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from eqa.settings import Settings

    if args.cmd == "sweep":
        return run(args.modes, args.levels, args.limit, args.out, args.recordings, "semantic", args.size,
                   args.workers, eval_seeds=args.eval_seeds)
    if args.cmd == "guided":
        compare_guided(args.recordings, args.seeds, args.limit, args.size, args.workers, args.out)
        return 0
    load_seeds(args.out, args.seeds, args.limit, args.strategy, args.size, args.workers, Settings().scenes_path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
