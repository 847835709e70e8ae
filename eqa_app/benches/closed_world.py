"""Closed-world existence answers and counting across views, against today's answering (recorded, then offline).

SIMULATED PERCEPTION MODEL (oracle scorer) and SIMULATED DETECTOR, not a VLM / detector. The rules and their
thresholds are declared in ``docs/results/closed-world-answers.md`` before any run. Two steps:

1. ``record``: full-length episodes (``semantic`` and ``fbe``) of the existence and counting questions with the
   services' pure cores in this process (:func:`eqa_app.core_runner.run_episode_loop`: the same path and seeds as
   the benchmark traces, whose f and Rel each recorded test episode is checked against), plus per step the
   scorer's answers to the presence prompts (:meth:`OracleBackend.presence`: "is there an X in this image?",
   "is this image taken in the Y?"), the asked room's extent on the robot's own map
   (:class:`services.mapper.room_extent.RoomExtent`: area and open boundary share) and, for counting, the
   question class's instances in the HELIOS object layer (Psi, and whether the centre lies in the room's
   extent). Neither rule steers the robot, so the path is the benchmark's; the closed-world rule may end an
   episode early, which the replay models (the answer from the stopping step on is fixed).
2. ``eval``: the knobs are chosen on the tuning seed 11 only (full-budget accuracy on its existence and
   counting test questions, ``semantic``), then seeds 1-3 are evaluated once: both strategies, at 0.5 T and T,
   paired sign test against today's answering, per question kind (the other kinds are unchanged by both rules:
   their answers are today's, read from the stored traces), and CP (eps 0.1 / 0.2 / 0.3) calibrated per seed
   and strategy on the calibration split's existence and counting questions with the same rule, with coverage.

    PYTHONPATH=. .venv/bin/python -m eqa_app.benches.closed_world record --out DIR --workers 2
    PYTHONPATH=. .venv/bin/python -m eqa_app.benches.closed_world eval --out DIR
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from eqa_app.benches.harness import RESULTS

LABEL = "simulated perception model and simulated detector, not a VLM / detector"
CATEGORIES = ("existence", "counting")
TRACES = RESULTS / "explore-seeds" / "traces"


@dataclasses.dataclass
class CWStep:
    probs: list[float]
    relevance: float
    object_yes: float  # P(Yes) to PRESENCE
    in_room: float | None  # P(Yes) to IN_ROOM (None: the question names no room)
    room_area_m2: float
    open_share: float
    instances: list[tuple[float, bool]]  # counting: (Psi of the class, centre in the room's extent)


@dataclasses.dataclass
class CWEpisode:
    qid: str
    seed: int
    strategy: str
    category: str
    choices: list[str]
    truth: int
    max_steps: int
    steps: list[CWStep]
    seconds: float


def run_episode(args: tuple[Any, int, str]) -> CWEpisode:
    """One full-length episode of ``question`` with ``strategy`` (module docstring, step 1)."""
    from eqa.messages import DetectResult, EpisodeStart, letters
    from eqa.settings import Settings
    from eqa_app.benchmark_runner import question_seed
    from eqa_app.core_runner import EpisodeCores, StepHooks, run_episode_loop
    from services.mapper.episode_map import EpisodeMap
    from services.mapper.question_objects import QuestionObjects
    from services.mapper.room_extent import RoomExtent, room_vote
    from services.planner.step import PlannerParams
    from services.sim.render import Renderer
    from services.sim.service import load_scene
    from services.vlm_scorer.backends.oracle import OracleBackend
    from services.vlm_scorer.detector import make_detector

    question, bench_seed, strategy = args
    t0 = time.monotonic()
    settings = Settings()
    scene = load_scene(settings, question.scene)
    oracle = OracleBackend.from_settings(settings)
    seed = question_seed(question.id)
    start = EpisodeStart(episode_id=f"cw-{question.id}", robot="r0", question=question, strategy=strategy,
                         max_steps=question.max_steps, seed=seed)
    cls = str(question.query["category"])
    room_kind = question.query.get("room_kind") or None
    counting = question.category == "counting"
    objects = QuestionObjects(question, None) if counting else None
    detector = make_detector(settings) if counting else None
    extent = RoomExtent()
    steps: list[CWStep] = []
    pending: dict[str, Any] = {}

    class Hooks(StepHooks):
        def scored(self, step: int, frame: Any, request: Any, scores: Any) -> None:
            object_yes, in_room = oracle.presence(request, cls, room_kind)
            pending.update(probs=list(scores.answer_probs), relevance=float(scores.relevance),
                           object_yes=object_yes, in_room=in_room, frame=frame)
            if objects is not None and detector is not None:
                dreq = objects.detect_request(frame, seed)
                objects.integrate(frame, DetectResult(request_id=dreq.request_id, episode_id=start.episode_id,
                                                      step=step, detections=detector.detect(dreq),
                                                      backend=settings.detector_backend))

        def mapped(self, step: int, emap: Any, step_map: Any) -> None:
            m, frame = emap.maps, pending["frame"]
            extent.update(frame.depth, frame.intrinsics, frame.camera_pose, room_vote(pending["in_room"], room_kind),
                          m.explored, m.free, m.occupied, emap.origin, emap.resolution)
            cov = extent.coverage(0.0, 1.0)
            inst = objects.in_room(extent.room_mask(), emap.origin, emap.resolution) if objects is not None else []
            steps.append(CWStep(pending["probs"], pending["relevance"], pending["object_yes"], pending["in_room"],
                                cov.area_m2, cov.open_share, inst))

    cores = EpisodeCores(scene, Renderer(scene), oracle, EpisodeMap(start), PlannerParams(), 320, 240)
    run_episode_loop(question, strategy, cores, episode_id=start.episode_id, seed=seed, hooks=Hooks())
    return CWEpisode(question.id, bench_seed, strategy, question.category or "", list(question.choices),
                     letters(len(question.choices)).index(question.answer), question.max_steps, steps,
                     time.monotonic() - t0)


# what is recorded, in this order (seed, split, strategy, categories, at most n per seed): the tuning seed's
# existence questions (rule 2 tunes nothing), then the evaluation seeds' test questions kind by kind and strategy
# by strategy, then the calibration splits, so a recording cut short by the machine's time holds whole groups
PLAN: tuple[tuple[tuple[int, ...], str, str, tuple[str, ...], int | None], ...] = (
    ((11,), "test", "semantic", ("existence",), None),
    ((1, 2, 3), "test", "semantic", ("existence",), None),
    ((1, 2, 3), "test", "fbe", ("existence",), None),
    ((1, 2, 3), "test", "semantic", ("counting",), None),
    ((1, 2, 3), "test", "fbe", ("counting",), None),
    ((1, 2, 3), "calibration", "semantic", ("existence", "counting"), 16),
    ((1, 2, 3), "calibration", "fbe", ("existence", "counting"), 16),
)


def path_of(out: Path, seed: int, split: str, strategy: str) -> Path:
    return out / f"cw-seed{seed}-{split}-{strategy}.pkl"


class _Unpickler(pickle.Unpickler):
    """Recordings made by running this file as a script name its classes ``__main__``."""

    def find_class(self, module: str, name: str) -> Any:
        if module in ("__main__", "eqa_app.benches.closed_world") and name in ("CWEpisode", "CWStep"):
            return globals()[name]
        return super().find_class(module, name)


def load(out: Path, seed: int, split: str, strategy: str) -> list[CWEpisode]:
    """A recording of :func:`record` (a pickle of our own making: never load one from elsewhere)."""
    path = path_of(out, seed, split, strategy)
    if not path.is_file():
        return []
    with open(path, "rb") as fh:
        return _Unpickler(fh).load()


def load_all(outs: list[Path], seed: int, split: str, strategy: str) -> list[CWEpisode]:
    """The recordings of several ``--out`` directories (two recorders, disjoint groups) together."""
    seen: set[str] = set()
    eps: list[CWEpisode] = []
    for out in outs:
        for e in load(out, seed, split, strategy):
            if e.qid not in seen:
                seen.add(e.qid)
                eps.append(e)
    return eps


def questions(split: str, categories: tuple[str, ...], n: int | None, bench: Any) -> list[Any]:
    from services.sim.questions import category_round_robin

    qs = {"calibration": bench.calibration, "test": bench.test}[split]
    return category_round_robin(qs, n, categories=categories)


def record(out: Path, workers: int, groups: list[int] | None = None) -> None:
    from tqdm import tqdm

    from eqa.settings import Settings
    from services.sim.questions import benchmark

    out.mkdir(parents=True, exist_ok=True)
    benches: dict[int, Any] = {}
    for g, (seeds, split, strategy, categories, n) in enumerate(PLAN):
        if groups is not None and g not in groups:
            continue
        todo: list[tuple[Any, int, str]] = []
        done: dict[int, list[CWEpisode]] = {}
        for seed in seeds:
            if seed not in benches:
                benches[seed] = benchmark(seed=seed, scenes_dir=Settings().scenes_path)
            done[seed] = load(out, seed, split, strategy)
            have = {e.qid for e in done[seed]}
            todo += [(q, seed, strategy) for q in questions(split, categories, n, benches[seed]) if q.id not in have]
        # interleave the seeds, so that a cut-short group still holds every seed
        per = {s: [a for a in todo if a[1] == s] for s in seeds}
        todo = [a for group in zip(*[per[s] + [None] * (max(map(len, per.values())) - len(per[s]))
                                     for s in seeds], strict=True) for a in group if a is not None]
        t0 = time.monotonic()
        desc = f"{split}-{strategy}-{'+'.join(categories)}"
        with ProcessPoolExecutor(workers) as pool:
            for i, ep in enumerate(tqdm(pool.map(run_episode, todo), total=len(todo), desc=desc, unit="ep",
                                        file=sys.stderr)):
                done[ep.seed].append(ep)
                if i % 4 == 3 or i == len(todo) - 1:
                    for seed in seeds:
                        path_of(out, seed, split, strategy).write_bytes(pickle.dumps(done[seed]))
        if todo:
            print(f"{desc}: {len(todo)} episodes in {(time.monotonic() - t0) / 60:.1f} min wall", flush=True)


# ---- evaluation (offline, on the recordings) ---------------------------------------------------------------
BUDGET_FRACTIONS = (0.5, 1.0)
EPS_EVAL = (0.1, 0.2, 0.3)
TUNE_GRID = tuple((k, a, o) for k in (1, 2, 3) for a in (2.0, 4.0, 8.0) for o in (0.1, 0.2, 0.3))


def presence_steps(ep: CWEpisode) -> list[Any]:
    from services.stopper.closed_world import PresenceStep

    return [PresenceStep(object_yes=s.object_yes, in_room=s.in_room, room_area_m2=s.room_area_m2,
                         open_share=min(s.open_share, 1.0)) for s in ep.steps]


def count_params() -> Any:
    """Rule 2's psi_min and w: the object-evidence settings' defaults (chosen on seed 11), as the product uses."""
    from eqa.settings import Settings
    from services.stopper.object_evidence import EvidenceParams

    fields = Settings.model_fields
    return EvidenceParams(psi_min=fields["object_evidence_psi_min"].default,
                          weight=fields["object_evidence_weight"].default)


def step_evidence(ep: CWEpisode, t: int) -> Any:
    """The object layer's evidence at step ``t`` (rule 2, :func:`services.mapper.question_objects.count_evidence`)."""
    from services.mapper.question_objects import count_evidence

    return count_evidence(ep.steps[t].instances, ep.steps[t].open_share)


def layer_dist(ep: CWEpisode, t: int) -> Any:
    """The object layer's count distribution at step ``t`` (rule 2; the docs' declaration)."""
    from services.stopper.object_evidence import layer_distribution

    return layer_distribution(step_evidence(ep, t), ep.choices, count_params())


def arrays(ep: CWEpisode) -> tuple[Any, Any]:
    import numpy as np

    return (np.asarray([s.probs for s in ep.steps], dtype=np.float64),
            np.asarray([s.relevance for s in ep.steps], dtype=np.float64))


def rule_outcome(ep: CWEpisode, params: Any, budget: float) -> tuple[bool, float]:
    """(correct, normalised steps) of the rules at ``budget`` (fraction of T), without CP."""
    import math

    from services.stopper.closed_world import firing_step, no_index
    from services.stopper.conformal import fallback_answer
    from services.stopper.object_evidence import budget_answer

    f, rel = arrays(ep)
    n = max(1, min(math.floor(budget * ep.max_steps + 1e-9), len(ep.steps)))
    if ep.category == "existence":
        fire = firing_step(presence_steps(ep)[:n], params)
        no = no_index(ep.choices)
        if fire is not None and no is not None:
            return no == ep.truth, (fire + 1) / ep.max_steps
        return fallback_answer(f[:n], rel[:n]) == ep.truth, n / ep.max_steps
    answer = budget_answer(f[:n], rel[:n], step_evidence(ep, n - 1), ep.choices, count_params())
    return answer == ep.truth, n / ep.max_steps


def transformed(ep: CWEpisode, params: Any, on: bool) -> tuple[Any, Any, int | None]:
    """CP: the episode's (f, Rel) under the rules (``on``) or today's, and the closed-world firing step."""
    import numpy as np

    from services.stopper.closed_world import apply, firing_step
    from services.stopper.object_evidence import combine

    f, rel = arrays(ep)
    if not on:
        return f, rel, None
    if ep.category == "existence":
        fire = firing_step(presence_steps(ep), params)
        f2, r2 = apply(f, rel, fire, ep.choices, params)
        return f2, r2, fire
    w = count_params().weight
    return np.asarray([combine(f[t], layer_dist(ep, t), w) for t in range(len(ep.steps))]), rel, None


def cp_replay(ep: CWEpisode, params: Any, on: bool, q_hat: float) -> tuple[bool, float, bool]:
    """As :func:`services.stopper.state.decide` (running intersection, stop at one answer), plus the
    closed-world stop at its firing step; (correct, normalised steps, sequence-level set covers the truth)."""
    import numpy as np

    from services.stopper.closed_world import no_index
    from services.stopper.conformal import fallback_answer, in_set, relevance_weighted_confidence

    f, rel, fire = transformed(ep, params, on)
    running = np.logical_and.accumulate(in_set(relevance_weighted_confidence(f, rel), q_hat), axis=0)
    covered = bool(running[-1, ep.truth])
    t_end = min(len(rel), ep.max_steps) - 1
    sizes = running.sum(axis=1)
    hit = np.flatnonzero(sizes[: t_end + 1] <= 1)
    t_cp = int(hit[0]) if hit.size else None
    if fire is not None and (t_cp is None or fire <= t_cp):
        return no_index(ep.choices) == ep.truth, (fire + 1) / ep.max_steps, covered
    if t_cp is not None:
        ans = int(np.flatnonzero(running[t_cp])[0]) if sizes[t_cp] == 1 else fallback_answer(f[: t_cp + 1],
                                                                                            rel[: t_cp + 1])
        return ans == ep.truth, (t_cp + 1) / ep.max_steps, covered
    return fallback_answer(f[: t_end + 1], rel[: t_end + 1]) == ep.truth, (t_end + 1) / ep.max_steps, covered


def kappa(ep: CWEpisode, params: Any, on: bool) -> float:
    from services.stopper.conformal import nonconformity

    f, rel, _ = transformed(ep, params, on)
    return nonconformity(f, rel, ep.truth)


def stored_traces(seed: int, strategy: str) -> dict[str, Any]:
    from services.stopper.calibration import read_jsonl

    path = TRACES / f"bench-{strategy}-oracle-320x240-seed{seed}-x1-cores.jsonl.gz"
    return {t.question_id: t for _, t in read_jsonl(path)}


def check_against_traces(eps: list[CWEpisode], traces: dict[str, Any]) -> int:
    """How many recorded episodes differ from the stored benchmark trace of the question (f or Rel > 1e-6)."""
    import numpy as np

    bad = 0
    for e in eps:
        t = traces.get(e.qid)
        f, rel = arrays(e)
        if t is None:
            bad += 1
            continue
        tf, tr = t.arrays()
        if tf.shape != f.shape or np.abs(tf - f).max() > 1e-6 or np.abs(tr - rel).max() > 1e-6:
            bad += 1
    return bad


def tune(eps: list[CWEpisode]) -> tuple[Any, list[dict[str, Any]], float]:
    """The closed-world setting with the best full-budget accuracy on the tuning episodes (ties: the declared
    order, i.e. smaller k_yes, larger min_area_m2, smaller max_open); None when none beats today's answer."""
    import numpy as np

    from services.stopper.closed_world import ClosedWorldParams
    from services.stopper.conformal import fallback_answer

    base = float(np.mean([fallback_answer(*arrays(e)) == e.truth for e in eps]))
    rows = []
    order = sorted(TUNE_GRID, key=lambda g: (g[0], -g[1], g[2]))
    best: tuple[float, Any] = (base, None)
    for k, area, open_ in order:
        params = ClosedWorldParams(k_yes=k, min_area_m2=area, max_open=open_)
        acc = float(np.mean([rule_outcome(e, params, 1.0)[0] for e in eps]))
        fired = float(np.mean([rule_outcome(e, params, 1.0)[1] < 1.0 for e in eps]))
        rows.append({"k_yes": k, "min_area_m2": area, "max_open": open_, "accuracy": acc, "stopped_early": fired})
        if acc > best[0] + 1e-12:
            best = (acc, params)
    return best[1], rows, base


def evaluate(outs: list[Path]) -> dict[str, Any]:

    from eqa_app.benches.answer_rules import Out, paired
    from eqa_app.evaluation import correct_at_budget
    from eqa_app.stats import wilson_ci
    from services.stopper.conformal import conformal_quantile

    tuning = [e for e in load_all(outs, 11, "test", "semantic") if e.category == "existence"]
    chosen, rows, base = tune(tuning)
    print(f"scorer: oracle ({LABEL}); tuning seed 11, semantic, existence test questions: n = {len(tuning)}, "
          f"today's accuracy {base:.3f}")
    for r in rows:
        print(f"  k_yes={r['k_yes']} min_area={r['min_area_m2']:g} max_open={r['max_open']:g}: "
              f"{r['accuracy']:.3f} (stopped before T: {r['stopped_early']:.2f})")
    print(f"chosen: {chosen}")
    res: dict[str, Any] = {"scorer": LABEL, "tuning": {"n": len(tuning), "today": base, "grid": rows,
                                                       "chosen": dataclasses.asdict(chosen) if chosen else None},
                           "strategies": {}}
    if chosen is None:
        from services.stopper.closed_world import ClosedWorldParams

        chosen = ClosedWorldParams()
        res["note"] = "no closed-world setting beat today's answer on seed 11; evaluated at the declared defaults"
    for strategy in ("semantic", "fbe"):
        groups: dict[str, dict[str, list[Out]]] = {}
        n_rec: dict[str, int] = {}
        mismatched = 0
        cp_data: dict[int, tuple[list[CWEpisode], list[CWEpisode]]] = {}
        for seed in (1, 2, 3):
            traces = stored_traces(seed, strategy)
            rec = {e.qid: e for e in load_all(outs, seed, "test", strategy)}
            mismatched += check_against_traces(list(rec.values()), traces)
            cp_data[seed] = (load_all(outs, seed, "calibration", strategy), list(rec.values()))
            for qid, tr in traces.items():
                cat = tr.category or ""
                if cat in CATEGORIES and qid not in rec:
                    continue  # not recorded (the machine's time): left out of both sides
                n_rec[cat] = n_rec.get(cat, 0) + 1
                for b in BUDGET_FRACTIONS:
                    base_ok = correct_at_budget(tr, b)
                    if cat in CATEGORIES:
                        ok, steps = rule_outcome(rec[qid], chosen, b)
                    else:
                        ok, steps = base_ok, b
                    g = groups.setdefault(f"{b:g}", {})
                    for key in (cat, "all"):
                        g.setdefault(f"{key}/rule", []).append(Out(ok, steps))
                        g.setdefault(f"{key}/today", []).append(Out(base_ok, b))
        sres: dict[str, Any] = {"n": n_rec, "recorded_differing_from_traces": mismatched, "budgets": {}, "cp": {}}
        print(f"\n{strategy}: seeds 1-3 test, n per kind {n_rec} (recorded episodes differing from the stored "
              f"traces: {mismatched})")
        for b, g in groups.items():
            sres["budgets"][b] = {}
            for key in ["all", *sorted({k.split('/')[0] for k in g} - {"all"})]:
                r = paired(g[f"{key}/rule"], g[f"{key}/today"])
                sres["budgets"][b][key] = r
                print(f"  {b} T {key:<15} n={r['n']:>3} rule {r['success_a']:.3f} today {r['success_b']:.3f} "
                      f"diff {r['diff']:+.3f} [{r['ci_low']:+.3f}, {r['ci_high']:+.3f}] only rule/today "
                      f"{r['a_only']}/{r['b_only']} p={r['p']:.3g} steps {r['steps_a']:.3f}")
        for eps in EPS_EVAL:
            cp_outs: dict[str, list[Out]] = {"rule": [], "today": []}
            cats: list[str] = []
            for _seed, (cal, test) in cp_data.items():
                if not test:
                    continue
                folds = [(cal, test)] if cal else [(test[1::2], test[0::2]), (test[0::2], test[1::2])]
                for c, t in folds:
                    if not c:
                        continue
                    for key, on in (("rule", True), ("today", False)):
                        q = conformal_quantile([kappa(e, chosen, on) for e in c], eps)
                        cp_outs[key] += [Out(*cp_replay(e, chosen, on, q)) for e in t]
                    cats += [e.category for e in t]
            if not cats:
                continue
            cov = {}
            for key in ("rule", "today"):
                k = sum(bool(o.covered) for o in cp_outs[key])
                lo, hi = wilson_ci(k, len(cp_outs[key]))
                cov[key] = {"coverage": k / len(cp_outs[key]), "ci_low": lo, "ci_high": hi, "n": len(cp_outs[key])}
            per = {c: paired([o for o, x in zip(cp_outs["rule"], cats, strict=True) if x == c],
                             [o for o, x in zip(cp_outs["today"], cats, strict=True) if x == c]) for c in set(cats)}
            r = paired(cp_outs["rule"], cp_outs["today"])
            calibrated = ", ".join(f"seed {sd}: " + (f"calibration split (n={len(c)})" if c else
                                                     "2-fold cross-fit on its test questions")
                                   for sd, (c, t) in cp_data.items() if t)
            sres["cp"][f"{eps:g}"] = {"coverage": cov, "paired": r, "per_kind": per, "calibrated_on": calibrated}
            print(f"  CP eps={eps:g} ({calibrated}) n={r['n']}: success rule {r['success_a']:.3f} today "
                  f"{r['success_b']:.3f} p={r['p']:.3g} steps {r['steps_a']:.3f} vs {r['steps_b']:.3f}; coverage "
                  f"rule {cov['rule']['coverage']:.3f} [{cov['rule']['ci_low']:.3f}, {cov['rule']['ci_high']:.3f}]"
                  f" today {cov['today']['coverage']:.3f} (want {1 - eps:.2f})")
        res["strategies"][strategy] = sres
    return res


def plot(res: dict[str, Any], path: Path) -> None:
    """Success of the rules and of today's answering per question kind, at 0.5 T and T, per strategy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    strategies = list(res["strategies"])
    fig, axes = plt.subplots(1, len(strategies), figsize=(6.5 * len(strategies), 4.2), squeeze=False)
    for ax, strategy in zip(axes[0], strategies, strict=True):
        budgets = res["strategies"][strategy]["budgets"]
        kinds = [k for k in budgets["1"] if k != "all"] + ["all"]
        x = list(range(len(kinds)))
        for j, (b, key, hatch) in enumerate((("0.5", "success_b", ""), ("0.5", "success_a", ""),
                                             ("1", "success_b", "//"), ("1", "success_a", "//"))):
            vals = [budgets[b][k][key] for k in kinds]
            label = f"{'rules' if key == 'success_a' else 'today'} at {b} T"
            ax.bar([i + (j - 1.5) * 0.2 for i in x], vals, 0.2, label=label, hatch=hatch,
                   color="tab:orange" if key == "success_a" else "tab:blue", alpha=0.55 if b == "0.5" else 1.0)
        ax.set_xticks(x, [f"{k}\nn={budgets['1'][k]['n']}\np={budgets['1'][k]['p']:.2g}" for k in kinds], fontsize=8)
        ax.set_ylim(0, 1)
        ax.set_ylabel("success")
        ax.set_title(f"{strategy}, seeds 1-3 (p: paired sign test at T)", fontsize=9)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"closed-world existence and counting across views; scorer: {LABEL}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--groups", type=int, nargs="+", default=None, help="only these PLAN entries (0-based), so "
                   "two recorders can share the work in two --out directories")
    e = sub.add_parser("eval")
    e.add_argument("--out", type=Path, nargs="+", required=True)
    e.add_argument("--json", type=Path, default=Path("bench/results/closed-world/closed_world.json"))
    e.add_argument("--png", type=Path, default=Path("bench/results/closed-world/closed_world.png"))
    a = p.parse_args(argv)
    if a.cmd == "record":
        record(a.out, a.workers, a.groups)
        return 0
    res = evaluate(a.out)
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(res, indent=1))
    plot(res, a.png)
    print(f"results: {a.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
