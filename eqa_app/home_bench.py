"""``eqa bench home``: sequences of questions in one house, asked cold (every episode from an empty map) and warm
(each question starts from the home's memory of the ones before it: :mod:`services.mapper.home_shell`).

Per benchmark seed, house ``i`` of the seed's generated houses (``gen-{seed*10000+i}``) gives a sequence of
``--questions`` questions (round-robin over the five categories, :func:`services.sim.questions.benchmark_candidates`);
houses ``0 .. --cal-houses - 1`` are the seed's calibration houses, the next ``--test-houses`` its test houses.

Every episode runs full length with the services' step functions in one process
(:func:`eqa_app.core_runner.run_episode_loop`, the ``cores`` runner of ``eqa bench``), so its trace serves both
calibration and the coverage check; the *home* of a warm sequence is written back at the step where the
stopper's own rule (:func:`services.stopper.state.decide`, CP at ``--eps``) stops it, through the mapper's
:class:`~services.mapper.home_shell.HomeMemory` on a store of its own: the next question sees what the robot had
seen when it answered, not what a full-length run saw. Steps to stop and success are the stopper's replay of
each trace (:func:`eqa_app.evaluation.replay`, memory steps included and not counted as steps).

Passes (each episode's result is a JSON file under ``--out/runs``; a run again skips those that exist):

1. cold traces of every question of every house (their own seed per question, as ``eqa bench``);
2. the cold CP table from the calibration houses' cold traces (pooled over ``--seeds``);
3. warm sequences of the calibration houses, homes written back at the cold table's stops;
4. the warm CP table from their warm traces of positions 2.. (the memory steps in them);
5. warm sequences of the test houses, homes written back at the warm table's stops.

With ``--changes K`` the house changes K seeded rounds between questions (:func:`sequence`), and the questions
the changes affect are reported apart: their wrong-singleton rate (:func:`wrong_singleton`), warm vs cold on the
same questions (:func:`singletons`).

With ``--tasks`` the sequences are the tasks of task houses (:func:`run_task_house`): each run cold and warm
(the HELIOS object layer kept in the home, :mod:`services.mapper.home_objects`), paired per task on steps, FindObj,
Pick, FindRec and SR (``home-tasks.json``, ``rows-tasks.json``); no calibration is involved.

Reported (``home.json``): steps to stop and success per position, cold vs warm on the same test questions,
paired (sign tests on steps and on success, with the success difference's interval), the steps ratio of
positions 2..N, CP coverage per eps on warm test episodes against 1 - eps (Wilson intervals), memory size.
SIMULATED PERCEPTION MODEL (the oracle scorer), not a VLM, unless ``--scorer`` says otherwise.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from eqa_app.core_runner import StepHooks

log = logging.getLogger(__name__)

EPS_GRID = (0.1, 0.2, 0.3)  # CP tables of the bench (0.1 needs >= 9 calibration episodes)


def sequence(seed: int, index: int, n: int, scenes_dir: Path, changes: int = 0) -> list[Any]:
    """The ``n`` questions asked in house ``index`` of benchmark ``seed``: the house's candidates, one category
    after the other in the benchmark's category order, the first question of each category first. With
    ``changes`` = K > 0 the house changes between questions: question ``p`` (1-based) is asked in the house after
    ``(p - 1) * K`` rounds of :mod:`services.sim.changes` (``gen-<seed>-c<k>``), with that house's ground truth
    (:func:`services.sim.change_impact.rederive`); a candidate without one there is passed over."""
    return [q for q, _ in changed_sequence(seed, index, n, scenes_dir, changes)]


def changed_sequence(seed: int, index: int, n: int, scenes_dir: Path, changes: int = 0) -> list[tuple[Any, Any]]:
    """:func:`sequence` as pairs (the question asked, the same question in the base house)."""
    from services.sim.change_impact import rederive
    from services.sim.changes import changed_scene_id
    from services.sim.library import load_or_generate
    from services.sim.questions import CATEGORIES, benchmark_candidates, category_round_robin

    cands = benchmark_candidates(seed, index, scenes_dir)
    order: list[Any] = category_round_robin([q for c in CATEGORIES for q in cands[c]], None, categories=CATEGORIES)
    if changes <= 0:
        return [(q, q) for q in order[:n]]
    out: list[tuple[Any, Any]] = []
    rest = iter(order)
    for pos in range(n):
        k = pos * changes
        scene = load_or_generate(changed_scene_id(order[0].scene, k), scenes_dir)
        for q in rest:
            asked = q if k == 0 else rederive(q, scene)
            if asked is not None:
                out.append((asked, q))
                break
        else:
            break
    return out


def impacts(pairs: list[tuple[Any, Any]], scenes_dir: Path, changes: int) -> list[dict[str, Any]]:
    """Per question of a changed sequence (``pairs`` from :func:`changed_sequence` with ``changes`` rounds between
    questions): its rounds ``k`` and whether the changes since the home's first question affect it
    (:func:`services.sim.change_impact.impact`: its answer or its evidence changed, so a view the home remembers
    may show what is no longer true)."""
    from services.sim.change_impact import impact
    from services.sim.changes import changes_of, parse_changed_id
    from services.sim.library import load_or_generate

    if changes <= 0 or not pairs:
        return [{"k": 0, "affected": False, "answer_changed": False} for _ in pairs]
    base = load_or_generate(pairs[0][1].scene, scenes_dir)
    made = changes_of(base, changes * (len(pairs) - 1))
    out = []
    for asked, q in pairs:
        parsed = parse_changed_id(asked.scene)
        k = 0 if parsed is None else parsed[1]
        if k == 0:
            out.append({"k": 0, "affected": False, "answer_changed": False})
            continue
        imp = impact(q, [c for c in made if c.round <= k], load_or_generate(asked.scene, scenes_dir))
        out.append({"k": k, "affected": imp.affected, "answer_changed": imp.answer_changed})
    return out


def _calibration(q_hat: float | None, eps: float) -> Any:
    from services.stopper.state import CalibrationChoice

    return None if q_hat is None else CalibrationChoice(q_hat=q_hat, eps=eps, asked_eps=eps, n=0, source="bench home")


class _Warm(StepHooks):
    """The mapper's home hooks in the in-process loop (the service's order: candidate keyframe, then at the first
    frame the warm start, then the frame's own values), the trace, and the stopper deciding online when the
    home is written back."""

    def __init__(self, memory: Any, emap: Any, record: Any) -> None:
        from services.stopper.calibration import TraceStep

        self.step_type = TraceStep
        self.memory, self.emap, self.record = memory, emap, record
        self.steps: list[Any] = []
        self.memory_steps = 0
        self.stop_step: int | None = None
        self.committed: Any = None

    def scored(self, step: int, frame: Any, request: Any, scores: Any) -> None:
        from eqa.messages import StepScores
        from services.stopper.state import decide

        self.memory.offer_view(self.emap, frame)
        mem = self.memory.warm(self.emap, frame) if step == 0 else []
        if step == 0:
            self.memory_steps = len(mem)
            self.steps += [self.step_type(answer_probs=m.answer_probs, relevance=m.relevance) for m in mem]
        self.steps.append(self.step_type(answer_probs=list(scores.answer_probs), relevance=float(scores.relevance)))
        if self.stop_step is None and self.record is not None:
            limit = self.memory.step_limit(self.emap.episode_id) if step == 0 else None
            d = decide(self.record, StepScores(episode_id=self.emap.episode_id, step=step,
                                               answer_probs=scores.answer_probs, relevance=scores.relevance,
                                               memory=mem, step_limit=limit))
            if d is not None and d.stop:
                self.stop_step = step
                self.committed = self.memory.commit(self.emap)  # the home as the robot had it when it answered


def run_house(args: tuple[int, int, int, str, float, float | None, dict[str, Any], str, int]) -> list[dict[str, Any]]:
    """The warm sequence of one house: per question its trace (memory steps first) and the home after it."""
    from eqa.messages import EpisodeStart, StopConfig
    from eqa.settings import Settings
    from eqa.store import EmbeddedStore
    from eqa_app.benchmark_runner import question_seed
    from eqa_app.core_runner import EpisodeCores, run_episode_loop
    from services.mapper.episode_map import EpisodeMap, MapperConfig
    from services.mapper.home_shell import HomeMemory
    from services.planner.step import PlannerParams
    from services.sim.library import load_or_generate
    from services.sim.render import Renderer
    from services.stopper.calibration import Trace
    from services.stopper.state import EpisodeRecord
    from services.vlm_scorer.backends import make_backend

    seed, index, n, strategy, eps, warm_q_hat, settings_dump, cold_q_hat_text, changes = args
    cold_q_hat = float(cold_q_hat_text)
    settings = Settings.model_validate(settings_dump)
    questions = sequence(seed, index, n, settings.scenes_path, changes)
    scorer = make_backend(settings)
    scene = renderer = None
    home = f"h-bench-{seed}-{index}"
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        store = EmbeddedStore(Path(tmp) / "home.sqlite")
        memory = HomeMemory(settings, lambda: store, lambda: scorer.score)
        try:
            for pos, q in enumerate(questions):
                if scene is None or scene.id != q.scene:  # a house that changed since the last question
                    scene = load_or_generate(q.scene, settings.scenes_path)
                    renderer = Renderer(scene)
                qseed = question_seed(q.id)
                start = EpisodeStart(episode_id=f"home-{q.id}", robot="cores", question=q, strategy=strategy,
                                     max_steps=q.max_steps, seed=qseed, record=False, home=home,
                                     stop=StopConfig(rule="cp", eps=eps))
                emap = EpisodeMap(start, MapperConfig(tau_lsv=settings.tau_lsv, tau_gsv=settings.tau_gsv,
                                                      tau_sv=settings.tau_sv, tau_sv_normal=settings.tau_sv_normal,
                                                      view_bins=settings.view_bins, view_agree=settings.view_agree))
                memory.start(start, emap)
                loaded = memory.episodes[start.episode_id].loaded_cells
                warm = memory.warm_start(start.episode_id)  # (None for the first question: a cold start)
                record = EpisodeRecord.from_start(start, "cores")
                q_hat = cold_q_hat if pos == 0 or warm_q_hat is None else warm_q_hat
                record.calibration = _calibration(q_hat, eps)
                hooks = _Warm(memory, emap, record)
                t0 = time.perf_counter()
                reason = run_episode_loop(q, strategy, EpisodeCores(scene, renderer, scorer, emap, PlannerParams(),
                                                                    settings.sim_width, settings.sim_height),
                                          episode_id=start.episode_id, seed=qseed, hooks=hooks)
                if hooks.stop_step is None:
                    hooks.committed = memory.commit(emap)
                # a warm budget (EQA_HOME_WARM_BUDGET) is the trace's max_steps: what the episode could have run
                limit = record.max_steps
                trace = Trace(question_id=q.id, scene=q.scene, category=q.category, choices=q.choices, answer=q.answer,
                              max_steps=limit, strategy=strategy, steps=hooks.steps[: hooks.memory_steps + limit],
                              episode_id=start.episode_id, end_reason=reason, stop_rule="max_steps",
                              memory_steps=hooks.memory_steps, warm=warm)
                index_after = hooks.committed
                out.append({"position": pos + 1, "trace": trace.model_dump(mode="json"), "loaded_cells": loaded,
                            "views": 0 if index_after is None else len(index_after.views),
                            "bytes": 0 if index_after is None else index_after.map_bytes + index_after.view_bytes,
                            "seconds": time.perf_counter() - t0})
        finally:
            store.close()
    return out


def run_cold(args: tuple[Any, str, dict[str, Any]]) -> dict[str, Any]:
    from eqa_app.core_runner import core_episode

    return core_episode(args).model_dump(mode="json")


# ---- the passes ---------------------------------------------------------------------------------------------
def _houses(seeds: list[int], cal: int, test: int) -> list[tuple[int, int, str]]:
    return [(s, i, "calibration" if i < cal else "test") for s in seeds for i in range(cal + test)]


def _run_all(fn: Any, jobs: list[Any], paths: list[Path], workers: int) -> None:
    """Run ``fn`` on every job, writing each result to its path as soon as it is done (an interrupted run, run
    again, does only what is missing)."""

    def write(path: Path, value: Any) -> None:
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(value))
        tmp.replace(path)

    if workers <= 1 or len(jobs) <= 1:
        for job, path in zip(jobs, paths, strict=True):
            write(path, fn(job))
        return
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(fn, job): path for job, path in zip(jobs, paths, strict=True)}
        for fut in as_completed(futures):
            write(futures[fut], fut.result())


def _table(traces: list[Any], grid: tuple[float, ...], name: str, eps: float) -> Any:
    """The CP table of ``traces`` at the eps of ``grid`` (and ``eps``) whose quantile ``traces`` define."""
    from eqa_app.bench_common import _quantile_defined
    from services.stopper.calibration import calibrate

    usable = sorted({e for e in (*grid, eps) if _quantile_defined(len(traces), e)})
    if eps not in usable:
        raise ValueError(f"{len(traces)} calibration episodes for {name} do not define q_hat at eps={eps:g}: "
                         f"use more calibration houses or a larger --eps")
    return calibrate(traces, usable, name=name)


def run(args: argparse.Namespace, settings: Any) -> dict[str, Any]:
    from eqa.messages import StopConfig
    from eqa.seeds import seed_role
    from eqa_app import evaluation as ev
    from services.stopper.calibration import Trace

    out = Path(args.out)
    runs = out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    dump = settings.model_dump(mode="json")
    houses = _houses(args.seeds, args.cal_houses, args.test_houses)
    changes = int(getattr(args, "changes", 0) or 0)
    pairs = {(s, i): changed_sequence(s, i, args.questions, settings.scenes_path, changes) for s, i, _ in houses}
    seqs = {house: [q for q, _ in p] for house, p in pairs.items()}
    impact = {house: impacts(p, settings.scenes_path, changes) for house, p in pairs.items()}
    size = f"{settings.sim_width}x{settings.sim_height}"

    # 1. cold traces of every question
    cold_jobs = [(q, args.strategy, dump) for (s, i, _) in houses for q in seqs[(s, i)]
                 if not (runs / f"cold-{args.strategy}-{size}-{q.id}.json").is_file()]
    _run_all(run_cold, cold_jobs, [runs / f"cold-{args.strategy}-{size}-{j[0].id}.json" for j in cold_jobs],
             args.workers)
    cold = {q.id: Trace.model_validate_json((runs / f"cold-{args.strategy}-{size}-{q.id}.json").read_text())
            for (s, i, _) in houses for q in seqs[(s, i)]}

    # 2. the cold table
    cal_cold = [cold[q.id] for (s, i, role) in houses if role == "calibration" for q in seqs[(s, i)]]
    cold_table = _table(cal_cold, EPS_GRID, "home-cold", args.eps)
    cold_q = {e.eps: e.q_hat for e in cold_table.entries}

    def warm_runs(role: str, warm_q_hat: float | None) -> dict[tuple[int, int], list[dict[str, Any]]]:
        knobs = [cold_q[args.eps], warm_q_hat, size, args.questions, args.strategy, settings.home_max_views,
                 settings.home_warm_views, settings.home_memory_steps]
        if changes or settings.home_stale_weight < 1.0:  # (without them the tags of earlier runs stay valid)
            knobs += [changes, settings.home_stale_weight, settings.home_stale_age_s]
        if settings.home_warm_budget < 1.0:
            knobs += ["budget", settings.home_warm_budget]
            if settings.home_warm_area != "explored":
                knobs += ["area", settings.home_warm_area]
        tag = hashlib.sha256(json.dumps(knobs).encode()).hexdigest()[:10]
        todo = [(s, i) for (s, i, r) in houses if r == role]
        paths = {h: runs / f"warm-{role}-s{h[0]}-h{h[1]}-{tag}.json" for h in todo}
        jobs = [(s, i, args.questions, args.strategy, args.eps, warm_q_hat, dump, repr(cold_q[args.eps]), changes)
                for (s, i) in todo if not paths[(s, i)].is_file()]
        _run_all(run_house, jobs, [paths[(j[0], j[1])] for j in jobs], args.workers)
        return {h: json.loads(paths[h].read_text()) for h in todo}

    # 3.-4. warm calibration sequences (homes written at the cold table's stops) and the warm table
    warm_cal = warm_runs("calibration", None)
    cal_warm = [Trace.model_validate(r["trace"]) for seq in warm_cal.values() for r in seq if r["position"] > 1]
    warm_table = _table(cal_warm, EPS_GRID, "home-warm", args.eps)
    warm_q = {e.eps: e.q_hat for e in warm_table.entries}

    # 5. warm test sequences (homes written at the warm table's stops)
    warm_test = warm_runs("test", warm_q[args.eps])

    cold_cal = _calibration(cold_q[args.eps], args.eps)
    warm_cal_choice = _calibration(warm_q[args.eps], args.eps)
    stop = StopConfig(rule="cp", eps=args.eps)
    rows = []
    diagnosis = {"warm": 0, "warm_with_cold_table": 0, "warm_without_memory_steps": 0, "cold": 0}
    for (s, i), seq in sorted(warm_test.items()):
        for r in seq:
            wt = Trace.model_validate(r["trace"])
            ct = cold[wt.question_id]
            w = ev.replay(wt, stop, cold_cal if r["position"] == 1 else warm_cal_choice)
            c = ev.replay(ct, stop, cold_cal)
            m = ev.replay(budget_matched(ct, wt.max_steps), stop, cold_cal)
            if r["position"] > 1:  # what the warm steps owe to the warm table and to the memory steps
                bare = wt.model_copy(update={"steps": wt.steps[wt.memory_steps:], "memory_steps": 0})
                diagnosis["warm"] += w.steps
                diagnosis["warm_with_cold_table"] += ev.replay(wt, stop, cold_cal).steps
                diagnosis["warm_without_memory_steps"] += ev.replay(bare, stop, warm_cal_choice).steps
                diagnosis["cold"] += c.steps
            imp = impact[(s, i)][r["position"] - 1]
            rows.append({"seed": s, "house": i, "position": r["position"], "question": wt.question_id,
                         "category": wt.category, "cold_steps": c.steps, "warm_steps": w.steps,
                         "cold_correct": c.correct, "warm_correct": w.correct, "memory_steps": wt.memory_steps,
                         "matched_steps": m.steps, "matched_correct": m.correct,
                         "max_steps": ct.max_steps, "warm_max_steps": wt.max_steps, "views": r["views"],
                         "bytes": r["bytes"],
                         "loaded_cells": r["loaded_cells"], "k": imp["k"], "affected": imp["affected"],
                         "answer_changed": imp["answer_changed"], "answer": wt.answer,
                         "cold_set": list(c.prediction_set), "warm_set": list(w.prediction_set),
                         "cold_wrong_singleton": wrong_singleton(c.prediction_set, wt.answer),
                         "warm_wrong_singleton": wrong_singleton(w.prediction_set, wt.answer)})
    results = summarise(rows, args, settings, cold_table, warm_table,
                        [Trace.model_validate(r["trace"]) for seq in warm_test.values() for r in seq
                         if r["position"] > 1])
    results["seed_roles"] = {str(s): seed_role(s) for s in args.seeds}
    results["n_calibration"] = {"cold": len(cal_cold), "warm": len(cal_warm)}
    # steps of positions 2.. over the cold steps, the warm traces replayed with the cold table (not calibrated
    # for them: a diagnosis of how much the warm table's larger q_hat costs) and without their memory steps
    results["steps_diagnosis"] = {k: v / max(diagnosis["cold"], 1) for k, v in diagnosis.items()}
    (out / "home.json").write_text(json.dumps(results, indent=2))
    (out / "rows.json").write_text(json.dumps(rows, indent=1))
    return results


def budget_matched(cold: Any, limit: int) -> Any:
    """The cold trace ``cold`` as if it had run under a warm question's step limit ``limit``: its first ``limit``
    steps, answered at that limit. Replayed, it is the cold episode with the warm episode's budget, so warm
    against it measures what the memory (map and remembered views) saves; warm against the cold trace as it ran
    mixes that with the smaller budget (:data:`services.mapper.home_shell` ``EQA_HOME_WARM_BUDGET``)."""
    if cold.memory_steps:
        raise ValueError(f"trace {cold.question_id} has memory steps: not a cold trace")
    n = max(1, min(int(limit), cold.max_steps))
    return cold.model_copy(update={"max_steps": n, "steps": cold.steps[:n]})


def matched(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``rows`` with the budget-matched cold episode (:func:`budget_matched`) in the place of the cold one."""
    return [{**r, "cold_steps": r["matched_steps"], "cold_correct": r["matched_correct"]} for r in rows]


def wrong_singleton(prediction_set: Any, answer: str) -> bool:
    """The episode ended with one answer in its CP prediction set, and not the true one: a wrong answer given
    with the rule's full confidence."""
    return len(prediction_set) == 1 and prediction_set[0] != answer


def singletons(sel: list[dict[str, Any]]) -> dict[str, Any]:
    """Wrong-singleton rates (:func:`wrong_singleton`), warm vs cold on the same questions: Wilson intervals, the
    paired sign test over the questions where only one of them is a wrong singleton, the difference's interval."""
    from eqa_app import stats

    n = len(sel)
    if n == 0:
        return {"n": 0}
    kc = sum(r["cold_wrong_singleton"] for r in sel)
    kw = sum(r["warm_wrong_singleton"] for r in sel)
    w_only = sum(1 for r in sel if r["warm_wrong_singleton"] and not r["cold_wrong_singleton"])
    c_only = sum(1 for r in sel if r["cold_wrong_singleton"] and not r["warm_wrong_singleton"])
    diff, lo, hi = stats.paired_diff_ci(w_only, c_only, n)
    kwc, kcc = sum(r["warm_correct"] for r in sel), sum(r["cold_correct"] for r in sel)
    return {"n": n, "cold_wrong_singleton": kc / n, "warm_wrong_singleton": kw / n,
            "cold_ci": list(stats.wilson_ci(kc, n)), "warm_ci": list(stats.wilson_ci(kw, n)),
            "paired": {"warm_only": w_only, "cold_only": c_only, "p_value": stats.sign_test_p(w_only, c_only),
                       "diff": diff, "ci_low": lo, "ci_high": hi},
            "cold_success": kcc / n, "warm_success": kwc / n}


def _steps_ratio(warm: Any, cold: Any, axis: int = -1) -> Any:
    """Total warm steps over total cold steps (vectorised over bootstrap resamples)."""
    import numpy as np

    return warm.sum(axis=axis) / np.maximum(cold.sum(axis=axis), 1e-9)


def paired(sel: list[dict[str, Any]]) -> dict[str, Any]:
    """Warm against cold on the same episodes ``sel`` (rows with ``cold_steps``, ``warm_steps``, ``cold_correct``,
    ``warm_correct``, ``memory_steps``): mean steps, the steps ratio with its bootstrap interval, the sign test on
    steps, success rates with Wilson intervals and the paired sign test on success."""
    import numpy as np

    from eqa_app import stats

    n = len(sel)
    if n == 0:
        return {"n": 0}
    cs = np.array([r["cold_steps"] for r in sel], dtype=float)
    ws = np.array([r["warm_steps"] for r in sel], dtype=float)
    fewer, more = int((ws < cs).sum()), int((ws > cs).sum())
    a_only = sum(1 for r in sel if r["warm_correct"] and not r["cold_correct"])
    b_only = sum(1 for r in sel if r["cold_correct"] and not r["warm_correct"])
    diff, lo, hi = stats.paired_diff_ci(a_only, b_only, n)
    ratio_ci = stats.bootstrap_ci(_steps_ratio, [ws, cs], n_boot=2000, seed=0)
    kw, kc = sum(r["warm_correct"] for r in sel), sum(r["cold_correct"] for r in sel)
    return {
        "n": n, "cold_steps_mean": float(cs.mean()), "warm_steps_mean": float(ws.mean()),
        "steps_ratio": float(ws.sum() / max(cs.sum(), 1e-9)),
        "steps_ratio_ci": list(ratio_ci),
        "steps_sign_test": {"warm_fewer": fewer, "warm_more": more, "p_value": stats.sign_test_p(fewer, more)},
        "cold_success": kc / n, "warm_success": kw / n,
        "cold_success_ci": list(stats.wilson_ci(kc, n)), "warm_success_ci": list(stats.wilson_ci(kw, n)),
        "success_paired": {"warm_only": a_only, "cold_only": b_only, "p_value": stats.sign_test_p(a_only, b_only),
                           "diff": diff, "ci_low": lo, "ci_high": hi},
        "memory_steps_mean": float(np.mean([r["memory_steps"] for r in sel])),
    }


def summarise(rows: list[dict[str, Any]], args: argparse.Namespace, settings: Any, cold_table: Any, warm_table: Any,
              warm_traces: list[Any]) -> dict[str, Any]:
    import numpy as np

    from eqa.messages import letters
    from eqa_app import stats
    from eqa_app.bench_common import scorer_label
    from services.stopper.conformal import relevance_weighted_confidence, sequence_set

    per_position = {str(p): paired([r for r in rows if r["position"] == p])
                    for p in sorted({r["position"] for r in rows})}
    later = paired([r for r in rows if r["position"] > 1])
    coverage = []
    for entry in warm_table.entries:
        hits = []
        for t in warm_traces:
            f, rel = t.arrays()
            rhos = np.stack([relevance_weighted_confidence(f[i], rel[i]) for i in range(len(rel))])
            hits.append(bool(sequence_set(rhos, entry.q_hat)[letters(len(t.choices)).index(t.answer)]))
        k, n = sum(hits), len(hits)
        p = k / n if n else math.nan
        coverage.append({"eps": entry.eps, "q_hat": entry.q_hat, "target": 1 - entry.eps, "coverage": p, "n": n,
                         "se": math.sqrt(p * (1 - p) / n) if n else math.nan, "wilson": list(stats.wilson_ci(k, n))})
    sizes = [r for r in rows if r["views"]]
    return {
        "scorer": scorer_label(settings),
        "runner": "cores (in-process step functions; the mapper's HomeMemory on an embedded store)",
        "seeds": list(args.seeds), "cal_houses": args.cal_houses, "test_houses": args.test_houses,
        "questions_per_house": args.questions, "eps": args.eps, "strategy": args.strategy,
        "size": f"{settings.sim_width}x{settings.sim_height}",
        "home_max_views": settings.home_max_views, "home_warm_views": settings.home_warm_views,
        "home_memory_steps": settings.home_memory_steps,
        "q_hat": {"cold": {f"{e.eps:g}": e.q_hat for e in cold_table.entries},
                  "warm": {f"{e.eps:g}": e.q_hat for e in warm_table.entries}},
        "positions": per_position, "positions_2_on": later, "warm_coverage": coverage,
        # the headline: warm against the same cold traces capped at each question's warm limit (memory's own
        # saving); "positions_2_on" above is warm against cold as it ran (memory and the smaller budget together)
        "positions_budget_matched": {str(p): paired(matched([r for r in rows if r["position"] == p]))
                                     for p in sorted({r["position"] for r in rows})},
        "positions_2_on_budget_matched": paired(matched([r for r in rows if r["position"] > 1])),
        "budget_matched_vs_cold": paired([{**r, "warm_steps": r["matched_steps"], "warm_correct": r["matched_correct"]}
                                          for r in rows if r["position"] > 1]),
        "changes": getattr(args, "changes", 0) or 0,
        "home_stale_weight": settings.home_stale_weight, "home_stale_age_s": settings.home_stale_age_s,
        "home_warm_budget": settings.home_warm_budget,
        "home_warm_area": settings.home_warm_area,
        "wrong_singletons": {
            "changed": singletons([r for r in rows if r["position"] > 1 and r.get("affected")]),
            "unchanged": singletons([r for r in rows if r["position"] > 1 and not r.get("affected")]),
            "positions_2_on": singletons([r for r in rows if r["position"] > 1]),
        },
        "memory": {"views_mean": float(np.mean([r["views"] for r in sizes])) if sizes else 0.0,
                   "bytes_mean": float(np.mean([r["bytes"] for r in sizes])) if sizes else 0.0,
                   "bytes_max": int(max((r["bytes"] for r in sizes), default=0))},
        "done_bar": {
            "steps_at_most_half": bool(later.get("steps_ratio", math.inf) <= 0.5),
            "budget_matched_steps_at_most_0.6": bool(
                paired(matched([r for r in rows if r["position"] > 1])).get("steps_ratio", math.inf) <= 0.6),
            "success_not_worse": bool(later.get("n", 0) and later["success_paired"]["ci_high"] >= 0),
            "coverage_within_se": all(c["coverage"] + c["se"] >= c["target"] for c in coverage if c["n"]),
        },
    }


# ---- task sequences (--tasks) ----------------------------------------------------------------------------------
TASK_METRICS = ("FindObj", "Pick", "FindRec", "SR")


def task_budget(task: Any, cap: int | None) -> int:
    return min(task.max_steps or 1, cap) if cap else (task.max_steps or 1)


def run_task_house(args: tuple[int, int, bool, dict[str, Any], int | None, bool]) -> list[dict[str, Any]]:
    """The tasks of one task house (:func:`services.sim.tasks.house_tasks`, in order) run one after the other in
    process (:func:`eqa_app.task_cores.run_task_episode`, the ``helios`` agent), each cold (no home) or warm (all
    in one home, on a store of its own, through the mapper's :class:`~services.mapper.home_shell.HomeMemory`).
    A task's episode id and seed are the same cold and warm, so both meet the same simulated detector draws. With
    ``repeat`` the house's object search is asked once more at the end (an episode id of its own: other detector
    draws than its first run), the case of a task asking for what an earlier one searched."""
    from eqa.settings import Settings
    from eqa.store import EmbeddedStore
    from eqa_app.task_cores import TaskCores, cores_episode_id, run_task_episode, task_start
    from eqa_app.task_results import task_seed
    from services.mapper.home_shell import HomeMemory
    from services.sim.tasks import house_tasks

    seed, index, warm, settings_dump, cap, repeat = args
    settings = Settings.model_validate(settings_dump)
    tasks = [(t, "") for t in house_tasks(seed, index, settings.scenes_path)]
    if repeat:
        tasks += [(t, "-again") for t, _ in tasks if t.kind == "find_object"][:1]
    cores = TaskCores.from_settings(settings)
    home = f"h-task-{seed}-{index}"
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        store = EmbeddedStore(Path(tmp) / "home.sqlite")
        memory = HomeMemory(settings, lambda: store, lambda: cores.backend.score)
        try:
            for pos, (task, again) in enumerate(tasks):
                steps = task_budget(task, cap)
                start = task_start(task, "helios", steps, None, cores_episode_id(task.id, steps) + again, "cores",
                                   task_seed(task.id))
                before = memory.read_index(home) if warm else None
                if warm:
                    start = start.model_copy(update={"home": home})
                t0 = time.perf_counter()
                try:
                    state, reason, metrics, trace = run_task_episode(cores, start, memory if warm else None)
                except Exception as exc:
                    log.exception("task %s (%s) failed in process", task.id, "warm" if warm else "cold")
                    state, reason, metrics, trace = "failed", f"{type(exc).__name__}: {exc}", {}, {}
                out.append({"position": pos + 1, "task": task.id + again, "kind": task.kind, "again": bool(again),
                            "classes": [c for c in (task.object, task.start_receptacle, task.goal_receptacle) if c],
                            "state": state, "reason": reason, "metrics": metrics,
                            "steps": len(trace.get("steps", [])), "max_steps": steps,
                            "home_gaussians": 0 if before is None else before.gaussians,
                            "home_views": 0 if before is None else len(before.views),
                            "home_bytes": 0 if before is None else
                            before.map_bytes + before.objects_bytes + before.view_bytes,
                            "seconds": time.perf_counter() - t0})
        finally:
            store.close()
            cores.close()
    return out


def run_tasks(args: argparse.Namespace, settings: Any) -> dict[str, Any]:
    """``--tasks``: the task houses ``0 .. --test-houses - 1`` of each seed, cold and warm (:func:`run_task_house`),
    paired per task (module doc of this bench for the questions' counterpart)."""
    from eqa.seeds import seed_role

    out = Path(args.out)
    runs = out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    dump = settings.model_dump(mode="json")
    cap = args.task_steps
    knobs = [settings.sim_width, settings.sim_height, cap, settings.home_max_views, settings.home_warm_views,
             settings.helios_max_gaussians, *(["repeat"] if args.repeat else [])]
    tag = hashlib.sha256(json.dumps(knobs).encode()).hexdigest()[:10]
    warm_tag = tag  # a cold episode has no home: the home's own knobs tag the warm runs only
    if settings.home_redetect_views != settings.home_warm_views:  # (equal: the tags of earlier runs stay valid)
        extra = [*knobs, "redetect", settings.home_redetect_views]
        warm_tag = hashlib.sha256(json.dumps(extra).encode()).hexdigest()[:10]
    if settings.home_restore_objects != "evidence":
        extra = [warm_tag, "restore", settings.home_restore_objects]
        warm_tag = hashlib.sha256(json.dumps(extra).encode()).hexdigest()[:10]
    houses = [(s, i) for s in args.seeds for i in range(args.test_houses)]
    paths = {(s, i, w): runs / f"task-{'warm' if w else 'cold'}-s{s}-h{i}-{warm_tag if w else tag}.json"
             for s, i in houses for w in (False, True)}
    jobs = [(s, i, w, dump, cap, bool(args.repeat)) for (s, i, w), p in paths.items() if not p.is_file()]
    _run_all(run_task_house, jobs, [paths[(j[0], j[1], j[2])] for j in jobs], args.workers)
    rows = []
    for s, i in houses:
        cold = json.loads(paths[(s, i, False)].read_text())
        warm = json.loads(paths[(s, i, True)].read_text())
        for c, w in zip(cold, warm, strict=True):
            row = {"seed": s, "house": i, "position": c["position"], "task": c["task"], "kind": c["kind"],
                   "again": bool(c.get("again", False)),
                   "classes": c["classes"], "cold_steps": c["steps"], "warm_steps": w["steps"],
                   "max_steps": c["max_steps"], "cold_state": c["state"], "warm_state": w["state"],
                   "cold_correct": bool(c["metrics"].get("SR", 0.0)), "warm_correct": bool(w["metrics"].get("SR", 0.0)),
                   "memory_steps": 0, "home_gaussians": w["home_gaussians"], "home_views": w["home_views"],
                   "home_bytes": w["home_bytes"]}
            for m in TASK_METRICS:
                if m in c["metrics"]:
                    row[f"cold_{m}"], row[f"warm_{m}"] = c["metrics"][m], w["metrics"][m]
            rows.append(row)
    results = summarise_tasks(rows, args, settings)
    results["seed_roles"] = {str(s): seed_role(s) for s in args.seeds}
    (out / "home-tasks.json").write_text(json.dumps(results, indent=2))
    (out / "rows-tasks.json").write_text(json.dumps(rows, indent=1))
    return results


def metric_pairs(sel: list[dict[str, Any]], metric: str) -> dict[str, Any]:
    """One task metric warm vs cold on the same tasks (those that have it): rates with Wilson intervals and the
    paired sign test."""
    from eqa_app import stats

    have = [r for r in sel if f"cold_{metric}" in r]
    n = len(have)
    if n == 0:
        return {"n": 0}
    kc = sum(1 for r in have if r[f"cold_{metric}"] > 0)
    kw = sum(1 for r in have if r[f"warm_{metric}"] > 0)
    w_only = sum(1 for r in have if r[f"warm_{metric}"] > 0 >= r[f"cold_{metric}"])
    c_only = sum(1 for r in have if r[f"cold_{metric}"] > 0 >= r[f"warm_{metric}"])
    diff, lo, hi = stats.paired_diff_ci(w_only, c_only, n)
    return {"n": n, "cold": kc / n, "warm": kw / n, "cold_ci": list(stats.wilson_ci(kc, n)),
            "warm_ci": list(stats.wilson_ci(kw, n)), "warm_only": w_only, "cold_only": c_only,
            "p_value": stats.sign_test_p(w_only, c_only), "diff": diff, "ci_low": lo, "ci_high": hi}


def summarise_tasks(rows: list[dict[str, Any]], args: argparse.Namespace, settings: Any) -> dict[str, Any]:
    from eqa_app.bench_common import scorer_label

    later = [r for r in rows if r["position"] > 1 and not r.get("again")]  # (--repeat: the repeat is apart)
    return {
        "scorer": scorer_label(settings),
        "detector": ("detector: oracle (simulated perception model, not a VLM/detector)"
                     if settings.detector_backend == "oracle" else f"detector: {settings.detector_backend}"),
        "runner": "cores (in-process task step functions; the mapper's HomeMemory on an embedded store)",
        "agent": "helios", "seeds": list(args.seeds), "houses_per_seed": args.test_houses,
        "task_steps_cap": args.task_steps, "size": f"{settings.sim_width}x{settings.sim_height}",
        "home_max_views": settings.home_max_views, "home_redetect_views": settings.home_redetect_views,
        "home_restore_objects": settings.home_restore_objects,
        "positions": {str(p): paired([r for r in rows if r["position"] == p])
                      for p in sorted({r["position"] for r in rows})},
        "positions_2_on": paired(later),
        "positions_2_on_by_kind": {k: paired([r for r in later if r["kind"] == k])
                                   for k in sorted({r["kind"] for r in later})},
        "metrics_2_on": {m: metric_pairs(later, m) for m in TASK_METRICS},
        "asked_again": paired([r for r in rows if r.get("again")]),  # --repeat: a search asked a second time
        "position_1_identical": all(r["cold_steps"] == r["warm_steps"] and r["cold_correct"] == r["warm_correct"]
                                    for r in rows if r["position"] == 1),
        "failed_runs": sum(1 for r in rows for k in ("cold_state", "warm_state") if r[k] == "failed"),
        "home_at_start_2_on": {k: float(sum(r[k] for r in later) / max(len(later), 1))
                               for k in ("home_gaussians", "home_views", "home_bytes")},
    }


def print_task_results(res: dict[str, Any]) -> None:
    print(f"task sequences: seeds {res['seeds']}, {res['houses_per_seed']} houses per seed, agent helios, step cap "
          f"{res['task_steps_cap']} ({res['scorer']}; {res['detector']})")
    print("position  n   cold steps  warm steps  ratio  cold SR  warm SR")
    for pos, p in res["positions"].items():
        if p.get("n"):
            print(f"{pos:>8}  {p['n']:<3} {p['cold_steps_mean']:<11.2f} {p['warm_steps_mean']:<11.2f} "
                  f"{p['steps_ratio']:<6.2f} {p['cold_success']:<8.3f} {p['warm_success']:.3f}")
    later = res["positions_2_on"]
    if later.get("n"):
        print(f"positions 2..: n {later['n']}, steps ratio {later['steps_ratio']:.3f} {later['steps_ratio_ci']}, "
              f"warm fewer {later['steps_sign_test']['warm_fewer']} more {later['steps_sign_test']['warm_more']}, "
              f"sign test p {later['steps_sign_test']['p_value']:.3g}")
    for m, v in res["metrics_2_on"].items():
        if v.get("n"):
            print(f"  {m}: n {v['n']}, cold {v['cold']:.3f} warm {v['warm']:.3f}; warm-only {v['warm_only']}, "
                  f"cold-only {v['cold_only']}, p {v['p_value']:.3g}")
    again = res.get("asked_again", {})
    if again.get("n"):
        print(f"object search asked again (n {again['n']}): steps cold {again['cold_steps_mean']:.1f} warm "
              f"{again['warm_steps_mean']:.1f} (ratio {again['steps_ratio']:.3f} {again['steps_ratio_ci']}, warm fewer "
              f"{again['steps_sign_test']['warm_fewer']} more {again['steps_sign_test']['warm_more']}, p "
              f"{again['steps_sign_test']['p_value']:.3g}); SR cold {again['cold_success']:.3f} warm "
              f"{again['warm_success']:.3f} (p {again['success_paired']['p_value']:.3g})")
    print(f"position 1 identical cold and warm: {res['position_1_identical']}; failed runs {res['failed_runs']}")


def print_results(res: dict[str, Any]) -> None:
    print(f"home sequences: seeds {res['seeds']}, {res['test_houses']} test houses per seed, "
          f"{res['questions_per_house']} questions each, eps {res['eps']}, {res['changes']} rounds of changes "
          f"between questions, stale weight {res['home_stale_weight']:g}, warm budget "
          f"{res.get('home_warm_budget', 1.0):g} ({res.get('home_warm_area', 'explored')} floor, {res['scorer']})")
    print("position  n   cold steps  warm steps  ratio  cold succ  warm succ  memory steps")
    for pos, p in res["positions"].items():
        if p.get("n"):
            print(f"{pos:>8}  {p['n']:<3} {p['cold_steps_mean']:<11.2f} {p['warm_steps_mean']:<11.2f} "
                  f"{p['steps_ratio']:<6.2f} {p['cold_success']:<10.3f} {p['warm_success']:<10.3f} "
                  f"{p['memory_steps_mean']:.1f}")
    for name, key in (("budget-matched cold (memory's own saving)", "positions_2_on_budget_matched"),
                      ("cold as run (memory and budget)", "positions_2_on")):
        later = res.get(key, {})
        if later.get("n"):
            sp = later["success_paired"]
            print(f"positions 2.., warm vs {name}: steps ratio {later['steps_ratio']:.3f} "
                  f"[{later['steps_ratio_ci'][0]:.3f}, {later['steps_ratio_ci'][1]:.3f}], warm fewer "
                  f"{later['steps_sign_test']['warm_fewer']} more {later['steps_sign_test']['warm_more']}, sign test p "
                  f"{later['steps_sign_test']['p_value']:.3g}; successes warm "
                  f"{round(later['warm_success'] * later['n'])} vs {round(later['cold_success'] * later['n'])}, "
                  f"warm-cold {sp['diff']:+.3f} [{sp['ci_low']:+.3f}, "
                  f"{sp['ci_high']:+.3f}] p {sp['p_value']:.3g}")
    budget = res.get("budget_matched_vs_cold", {})
    if budget.get("n"):
        print(f"the budget alone (budget-matched cold vs cold): steps ratio {budget['steps_ratio']:.3f} "
              f"[{budget['steps_ratio_ci'][0]:.3f}, {budget['steps_ratio_ci'][1]:.3f}], successes "
              f"{round(budget['warm_success'] * budget['n'])} vs {round(budget['cold_success'] * budget['n'])}")
    for name, w in res["wrong_singletons"].items():
        if w.get("n"):
            print(f"wrong singletons, {name} questions (n {w['n']}): warm {w['warm_wrong_singleton']:.3f} "
                  f"{[round(v, 3) for v in w['warm_ci']]} vs cold {w['cold_wrong_singleton']:.3f} "
                  f"{[round(v, 3) for v in w['cold_ci']]}; warm-only {w['paired']['warm_only']}, cold-only "
                  f"{w['paired']['cold_only']}, p {w['paired']['p_value']:.3g}; success warm {w['warm_success']:.3f}"
                  f" cold {w['cold_success']:.3f}")
    for c in res["warm_coverage"]:
        print(f"warm coverage eps {c['eps']:g}: {c['coverage']:.3f} +- {c['se']:.3f} vs {c['target']:.2f} (n {c['n']})")
    if "steps_diagnosis" in res:
        print("steps over cold, positions 2..: " + ", ".join(f"{k} {v:.3f}" for k, v in res["steps_diagnosis"].items()))
    print(f"memory: {res['memory']['views_mean']:.1f} views, {res['memory']['bytes_mean'] / 1e6:.2f} MB mean per home")


def cmd_home(args: argparse.Namespace) -> int:
    from eqa.messages import eps_in_bounds
    from eqa.service import setup_logging
    from eqa_app.bench_common import _settings
    from eqa_app.cli import UsageError
    from services.sim.changes import MAX_ROUNDS

    if not (1 <= args.cal_houses <= 100 and 1 <= args.test_houses <= 100 and 1 <= args.questions <= 10):
        raise UsageError("--cal-houses and --test-houses must be 1..100, --questions 1..10")
    if not eps_in_bounds(args.eps) or not 1 <= args.workers <= 16:
        raise UsageError("--eps must be in (0, 1), --workers 1..16")
    if args.changes < 0 or args.changes * (args.questions - 1) > MAX_ROUNDS:
        raise UsageError(f"--changes times (--questions - 1) must be 0..{MAX_ROUNDS} (rounds of a changed house)")
    for name in ("stale_weight", "warm_budget"):
        if getattr(args, name) is not None and not 0 <= getattr(args, name) <= 1:
            raise UsageError(f"--{name.replace('_', '-')} must be in [0, 1]")
    for name in ("home_views", "memory_steps", "redetect_views"):
        if getattr(args, name) is not None and not 0 <= getattr(args, name) <= 256:
            raise UsageError(f"--{name.replace('_', '-')} must be 0..256")
    settings = _settings(args)
    if args.home_views is not None:
        settings = settings.model_copy(update={"home_max_views": args.home_views, "home_warm_views": args.home_views})
    if args.memory_steps is not None:
        settings = settings.model_copy(update={"home_memory_steps": args.memory_steps})
    if args.redetect_views is not None:
        settings = settings.model_copy(update={"home_redetect_views": args.redetect_views})
    if args.stale_weight is not None:
        settings = settings.model_copy(update={"home_stale_weight": args.stale_weight})
    if args.warm_budget is not None:
        settings = settings.model_copy(update={"home_warm_budget": args.warm_budget})
    if args.warm_area is not None:
        settings = settings.model_copy(update={"home_warm_area": args.warm_area})
    if args.restore_objects is not None:
        settings = settings.model_copy(update={"home_restore_objects": args.restore_objects})
    setup_logging(settings.log_level, "eqa-bench")
    logging.getLogger("services.mapper.home_shell").setLevel(logging.WARNING)
    if args.tasks:
        if args.task_steps is not None and not 1 <= args.task_steps <= 10_000:
            raise UsageError("--task-steps must be 1..10000")
        tres = run_tasks(args, settings)
        print_task_results(tres)
        print(f"results: {Path(args.out) / 'home-tasks.json'}")
        return 0
    res = run(args, settings)
    print_results(res)
    print(f"results: {Path(args.out) / 'home.json'}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("home", help="questions in a known house: cold vs warm start from the home's memory",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3], metavar="SEED",
                   help="benchmark seeds (evaluation 1 2 3, tuning 11: eqa.seeds); default 1 2 3")
    p.add_argument("--cal-houses", type=int, default=3, help="calibration houses per seed (default 3)")
    p.add_argument("--test-houses", type=int, default=4, help="test houses per seed (default 4)")
    p.add_argument("--questions", type=int, default=5, help="questions per house (default 5)")
    p.add_argument("--eps", type=float, default=0.2, help="CP eps the stopper runs at (default 0.2)")
    p.add_argument("--strategy", default="semantic", choices=("semantic", "fbe"), help="exploration strategy")
    p.add_argument("--home-views", type=int, default=None,
                   help="view memory size (EQA_HOME_MAX_VIEWS and EQA_HOME_WARM_VIEWS; default from the environment)")
    p.add_argument("--memory-steps", type=int, default=None,
                   help="memory steps given to the stopper (EQA_HOME_MEMORY_STEPS; default from the environment)")
    p.add_argument("--changes", type=int, default=0, metavar="K",
                   help="rounds of seeded house changes between questions (services.sim.changes: question p is asked "
                   "in gen-<seed>-c<(p-1)K>); reports the wrong-singleton rate on questions the changes affect")
    p.add_argument("--stale-weight", type=float, default=None,
                   help="weight of stale remembered views' evidence (EQA_HOME_STALE_WEIGHT; default from the "
                   "environment)")
    p.add_argument("--warm-budget", type=float, default=None,
                   help="least share of max_steps of a warm question (EQA_HOME_WARM_BUDGET, eqa/budget.py; 1 = the "
                   "full budget; default from the environment)")
    p.add_argument("--tasks", action="store_true",
                   help="task sequences instead of questions: the tasks of task houses 0 .. --test-houses - 1 of each "
                   "seed (services.sim.tasks.house_tasks) in order, cold vs warm in one home (the HELIOS object layer "
                   "kept); the CP options do not apply")
    p.add_argument("--repeat", action="store_true",
                   help="with --tasks: ask each house's object search once more at the end of its sequence")
    p.add_argument("--task-steps", type=int, default=None,
                   help="with --tasks: cap of each task's step budget (default: the task's own)")
    p.add_argument("--redetect-views", type=int, default=None,
                   help="with --tasks: remembered views re-detected for a task's new classes (EQA_HOME_REDETECT_VIEWS; "
                   "default from the environment)")
    p.add_argument("--restore-objects", choices=("evidence", "all"), default=None,
                   help="tasks: which Gaussians of the home's object layer a task starts with "
                   "(EQA_HOME_RESTORE_OBJECTS)")
    p.add_argument("--warm-area", choices=("explored", "observed"), default=None,
                   help="the floor a warm budget subtracts (EQA_HOME_WARM_AREA, eqa/budget.py; default from the "
                   "environment)")
    p.add_argument("--size", default="160x120", help="camera image size WxH (default 160x120)")
    p.add_argument("--scorer", choices=("oracle", "hf", "remote"), default=None,
                   help="scorer backend (default EQA_SCORER_BACKEND, normally oracle)")
    p.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    p.add_argument("--out", default="var/bench-home", help="directory for home.json and the per-episode runs")
    p.set_defaults(func=cmd_home, runner="cores", limit=None, robots=1, scorers=1)
