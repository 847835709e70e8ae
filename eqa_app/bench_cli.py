"""``eqa bench``: reproduce the paper's comparisons on the simulated benchmark, through the real services.

    eqa bench explore [--limit N]   success vs normalised step budget for fbe / semantic / no_lsv / no_gsv
                                    (Explore-EQA Fig. 7), per category (Fig. A6) and by house size (Fig. A7)
    eqa bench stop [--limit N]      calibrate CP on the calibration split, then success vs mean normalised steps
                                    for an eps sweep, an entropy sweep and a relevance sweep (Fig. 9), and
                                    the empirical coverage of the CP sets against 1 - eps

Each question is run once per strategy to its full step budget through a real fleet (several simulated robots
at once), its per-step scores stored as a trace (resumable: stored traces are not run again); every budget
and every stopping rule is then read from the same traces (eqa/evaluation.py). Results: JSON + PNG plots in
``--out``. Every plot and table names the scorer that produced it; with the default ``oracle`` scorer the
numbers come from a simulated perception model, not from a VLM.

Seeds are a benchmark axis (``--seeds``): each seed is its own benchmark of 500 questions over its own
generated houses (``eqa.seeds``: seed 11 is the tuning seed, 1 2 3 the evaluation seeds, 0 the legacy seed of the
first figures). Results are given pooled over the seeds and per seed, with Wilson 95 % intervals on success
rates and, for each pair of strategies, the exact sign test and a 95 % interval of the paired difference.
``--limit`` applies per seed. The yardsticks ``target_oracle``, ``perfect_sv``, ``perfect_vlfm`` and ``perfect_gain``
(upper bounds that read the ground truth) run only here, when named in ``--strategies``.

Traces are exported to ``<--out>/traces/<set>.jsonl.gz`` (one set per strategy, scorer, size and seed) and
imported from there on the next run, so ``--out bench/results`` replays the published runs in seconds.

    eqa bench explore --seeds 1 2 3 --limit 20 --out /tmp/quick   quick mode: 240 episodes (about 9 min through
                                    the fleet on an idle 2-core machine; add --runner cores under load)
    eqa bench explore --runner cores --seeds 1 2 3 --split test --strategies fbe semantic
        --out bench/results/explore-seeds      the evaluation figures (stored traces, replayed in seconds)
    eqa bench stop --out bench/results                 the seed-0 stopping figures (docs/results/)
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from eqa_app.bench_common import _quantile_defined, _settings, scorer_label

log = logging.getLogger(__name__)

STRATEGIES = ("fbe", "semantic", "no_lsv", "no_gsv")
# benchmark-only yardsticks (upper bounds reading ground truth; the perfect_* ones: eqa.messages.PERFECT_VALUE_RULE)
BOUNDS = ("target_oracle", "perfect_sv", "perfect_vlfm", "perfect_gain")
RULES = ("vlfm", "gain", "topo")  # deterministic frontier rules beyond Eq. A6 (services/planner/frontier_rules.py)
CDF_BUDGETS = tuple(round(0.05 * k, 2) for k in range(1, 21))
ENTROPY_SWEEP = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 1.1, 1.3)
RELEVANCE_SWEEP = (0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.175, 0.15, 0.125, 0.1)
PAIRED_BUDGETS = (0.5, 0.7, 1.0)
EPS_SWEEP = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6, 0.7, 0.8)




# Bumped when the exploration itself changes (planner, mapper value layers), so that traces of an earlier
# behaviour are not resumed into new figures (version 2 was a withdrawn trial of a doorway fix).
EXPLORATION_VERSION = 1
# Strategies whose own behaviour has a later version than the rest: target_oracle 2 walks to the target through
# the true house (services/sim/paths.py); its version-1 traces (straight-line distance) stay a separate set.
STRATEGY_VERSIONS = {"target_oracle": 2}


def set_name(strategy: str, settings: Any, seed: int = 0) -> str:
    """One trace set per (strategy, scorer, image size, benchmark seed, exploration version), keyed by question
    id: the explore and the stop benchmarks read the same full-length runs. Seed 0 keeps the legacy names (and
    traces) of the first figures."""
    base = f"bench-{strategy}-{settings.scorer_backend}-{settings.sim_width}x{settings.sim_height}"
    return base if seed == 0 else f"{base}-seed{seed}-x{STRATEGY_VERSIONS.get(strategy, EXPLORATION_VERSION)}"


def _runner_suffix(args: argparse.Namespace) -> str:
    return "-cores" if getattr(args, "runner", "fleet") == "cores" else ""


def tau_label(tau: float) -> str:
    """Name of semantic exploration at temperature ``tau_LSV = tau_GSV = tau`` (Explore-EQA Fig. 7c)."""
    return f"semantic_tau{tau:g}"


def view_bins_label(bins: int, agree: int) -> str:
    """Name of semantic exploration with ``bins`` viewing-direction bins per value layer."""
    return f"semantic_vbins{bins}a{agree}"


def _benchmark(seed: int, settings: Any) -> Any:
    """The benchmark of ``seed``, cached as JSON next to the generated houses under a key of the source of the
    modules that make it (house generator, catalog, questions): building it loads all of its ~170 houses
    (about a minute even when they are cached), a cached one loads in a second."""
    import hashlib

    import services.sim.catalog as catalog
    import services.sim.housegen as housegen
    import services.sim.questions as questions

    digest = hashlib.sha256()
    for mod in (catalog, housegen, questions):
        digest.update(Path(str(mod.__file__)).read_bytes())
    path = Path(settings.scenes_path) / f"benchmark-seed{seed}-{digest.hexdigest()[:12]}.json"
    if path.is_file():
        try:
            return questions.Benchmark.load(path)
        except (ValueError, KeyError) as exc:
            log.warning("cached benchmark %s unreadable (%s): building it again", path, exc)
    bench = questions.benchmark(seed=seed, scenes_dir=settings.scenes_path)
    tmp = path.with_suffix(f".tmp{id(bench)}")
    bench.save(tmp)
    tmp.replace(path)
    return bench


def _questions(split: str, limit: int | None, settings: Any, seed: int = 0) -> list[Any]:
    bench = _benchmark(seed, settings)
    from services.sim.questions import category_round_robin

    qs = {"calibration": bench.calibration, "test": bench.test, "all": bench.calibration + bench.test}[split]
    return qs if limit is None else category_round_robin(qs, limit)


def _import(path: Path, name: str, settings: Any) -> int:
    """Store the traces of ``path`` (a JSONL export of a set) that the store lacks; how many were added."""
    from eqa.store import open_store
    from services.stopper.calibration import TraceStore, read_jsonl

    if not path.is_file():
        return 0
    added = 0
    with open_store(settings) as store:
        ts = TraceStore(store)
        for _, trace in read_jsonl(path):
            if not ts.has(name, trace.question_id):
                ts.save(name, trace)
                added += 1
    return added


def _export(path: Path, traces: list[Any]) -> None:
    from services.stopper.calibration import write_jsonl

    write_jsonl(path, sorted(traces, key=lambda t: t.question_id))


def trace_file(directory: Path, name: str) -> Path:
    """Where the set ``name`` is kept under ``directory``: ``<name>.jsonl.gz``, or an uncompressed
    ``<name>.jsonl`` already there (kept as it is)."""
    plain = directory / f"{name}.jsonl"
    return plain if plain.is_file() else directory / f"{name}.jsonl.gz"


def _collect(questions: list[Any], settings: Any, strategy: str, name: str, args: argparse.Namespace) -> list[Any]:
    """The full-length traces of ``questions``: imported from ``--out/traces/<set>.jsonl.gz``, read from the store,
    or run (resumable); the set is exported back to that file so a fresh checkout can reuse the runs."""
    from tqdm import tqdm

    from eqa.store import open_store
    from eqa_app.benchmark_runner import collect_traces
    from services.stopper.calibration import TraceStore

    export = trace_file(Path(args.out) / "traces", name)
    # --out's own traces first, then those of other result directories (--traces), e.g. the stored runs of the
    # strategies a new one is compared with, so that they are not run (or copied) again
    kept = [trace_file(Path(d), name) for d in getattr(args, "traces", [])]
    elsewhere = any(k.is_file() for k in kept)
    for source in [export, *kept]:
        if (added := _import(source, name, settings)):
            log.info("%s: %d traces imported from %s", name, added, source)
    with open_store(settings) as store:
        done = sum(TraceStore(store).has(name, q.id) for q in questions)
    t0 = time.monotonic()
    steps = 0
    with tqdm(total=len(questions), initial=done, desc=f"{strategy:>8}", unit="ep", file=sys.stderr,
              disable=args.no_progress) as bar:
        if getattr(args, "runner", "fleet") == "cores":
            runs = _collect_cores(questions, settings, strategy, name, args.workers)
        else:
            runs = collect_traces(questions, settings, strategy=strategy, set_name=name, progress=bar,
                                  robots=args.robots, scorers=args.scorers)
        for trace in runs:
            bar.update(1)
            steps += len(trace.steps)
    ran = len(questions) - done
    if ran:
        minutes = (time.monotonic() - t0) / 60
        log.info("%s: %d episodes in %.1f min (%.1f episodes/min, %.1f steps/s)", strategy, ran, minutes,
                 ran / max(minutes, 1e-9), steps / max(minutes * 60, 1e-9))
    with open_store(settings) as store:
        everything = TraceStore(store).load(name)
    if ran or export.is_file() or not elsewhere:  # a set only read from --traces stays where it is kept
        _export(export, everything)
    by_id = {t.question_id: t for t in everything}
    return [by_id[q.id] for q in questions if q.id in by_id]


def _collect_cores(questions: list[Any], settings: Any, strategy: str, name: str, workers: int) -> Any:
    """Run the questions without a stored trace in ``name`` with the pure cores (:mod:`eqa_app.core_runner`),
    ``workers`` processes; store and yield each trace as it finishes."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from eqa.store import open_store
    from eqa_app.core_runner import core_episode
    from services.stopper.calibration import TraceStore

    with open_store(settings) as store:
        traces = TraceStore(store)
        missing = [q for q in questions if not traces.has(name, q.id)]
        if not missing:
            return
        dump = settings.model_dump(mode="json")
        pool = ProcessPoolExecutor(workers)
        try:
            futures = [pool.submit(core_episode, (q, strategy, dump)) for q in missing]
            for fut in as_completed(futures):
                trace = fut.result()
                traces.save(name, trace)
                yield trace
        finally:
            # on Ctrl-C / SIGTERM (KeyboardInterrupt, eqa_app.cli) drop the queued episodes: a plain `with` waited
            # for every one of them before the command could exit; the stored traces are resumed next time
            pool.shutdown(wait=True, cancel_futures=True)




def _summary(traces: list[Any], ev: Any) -> dict[str, Any]:
    """Success per budget with Wilson 95 % intervals, and when the evidence was first seen."""
    from eqa_app import stats

    n = len(traces)
    success = ev.success_at_budgets(traces)
    return {
        "n": n,
        "success": success,
        "success_ci95": [list(stats.wilson_ci(round(v * n), n)) for v in success],
        "evidence_share": ev.evidence_share(traces),
        "first_evidence_at": ev.first_evidence(traces),
        "median_first_evidence": ev.median_first_evidence(traces),
        "evidence_cdf": ev.evidence_cdf(traces, CDF_BUDGETS),
        # success among the episodes that saw the evidence within the budget and among those that did not
        "success_by_evidence": {f"{b:g}": {**vars(s), "lift": s.lift}
                                for b in (0.5, 1.0) for s in [ev.success_by_evidence(traces, b)]},
    }


def cmd_explore(args: argparse.Namespace) -> int:
    from eqa.seeds import seed_role
    from eqa.service import setup_logging
    from eqa_app import evaluation as ev

    settings = _settings(args)
    setup_logging(settings.log_level, "eqa-bench")
    logging.getLogger("eqa.launcher").setLevel(logging.WARNING)
    if len(args.traces) > 16:
        from eqa_app.cli import UsageError

        raise UsageError("--traces takes at most 16 directories")
    seeds = list(dict.fromkeys(args.seeds))
    roles = {s: seed_role(s) for s in seeds}
    for s, role in roles.items():
        if role != "evaluation":
            log.warning("seed %d is the %s seed, not an evaluation seed: label its figures so", s, role)
    questions = {s: _questions(args.split, args.limit, settings, s) for s in seeds}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {"scorer": scorer_label(settings), "budgets": list(ev.BUDGETS),
                               "size": f"{settings.sim_width}x{settings.sim_height}", "split": args.split,
                               "limit_per_seed": args.limit, "seeds": seeds, "runner": args.runner,
                               "seed_roles": {str(s): r for s, r in roles.items()},
                               "cdf_budgets": list(CDF_BUDGETS), "strategies": {}}
    areas = {k: v for s in seeds for k, v in _areas(questions[s], settings).items()}
    cuts = ev.size_cuts(areas.values())
    sizes = {q: ev.size_class(a, cuts) for q, a in areas.items()}
    results["size_cuts_m2"] = list(cuts)
    runs: dict[str, dict[int, list[Any]]] = {}
    # (label, strategy, settings): the strategies, then semantic exploration at other temperatures (Fig. 7c)
    plan = [(s, s, settings) for s in args.strategies]
    plan += [(tau_label(t), "semantic", settings.model_copy(update={"tau_lsv": t, "tau_gsv": t})) for t in args.tau]
    plan += [(view_bins_label(b, settings.view_agree), "semantic", settings.model_copy(update={"view_bins": b}))
             for b in getattr(args, "view_bins", [])]
    for label, strategy, run_settings in plan:
        runs[label] = {s: _collect(questions[s], run_settings, strategy,
                                   set_name(label, run_settings, s) + _runner_suffix(args), args) for s in seeds}
        traces = [t for s in seeds for t in runs[label][s]]
        results["strategies"][label] = {
            **_summary(traces, ev),
            "bound": label in BOUNDS,
            "per_seed": {str(s): _summary(runs[label][s], ev) for s in seeds},
            "by_category": {c: {"n": len(ts), "success": ev.success_at_budgets(ts),
                                "evidence_cdf": ev.evidence_cdf(ts, CDF_BUDGETS)}
                            for c, ts in ev.by_group(traces, "category").items()},
            "by_size": {c: {"n": len(ts), "success": ev.success_at_budgets(ts),
                            "evidence_cdf": ev.evidence_cdf(ts, CDF_BUDGETS)}
                        for c, ts in ev.by_group(traces, groups=sizes).items()},
            "by_area": {b: {"n": len(ts), "success_full_budget": ev.success_at_budgets(ts, (1.0,))[0]}
                        for b, ts in ev.by_group(traces, groups={q: ev.area_bin(a) for q, a in areas.items()}).items()},
        }

    # Paired comparisons on the same questions: semantic against every other run, every run against fbe; per
    # seed and pooled over the seeds (discordant counts add up), with the 95 % interval of the difference.
    def paired(a: str, b: str) -> tuple[list[dict[str, Any]], dict[str, list[dict[str, Any]]]]:
        per = {s: ev.paired_comparison(runs[a][s], runs[b][s], PAIRED_BUDGETS) for s in seeds}
        return ([vars(p) for p in ev.pool_paired(list(per.values()))],
                {str(s): [vars(p) for p in rows] for s, rows in per.items()})

    def sooner(a: str, b: str) -> dict[str, Any]:
        pooled = ev.paired_first_evidence([t for s in seeds for t in runs[a][s]],
                                          [t for s in seeds for t in runs[b][s]])
        return {"pooled": vars(pooled),
                "per_seed": {str(s): vars(ev.paired_first_evidence(runs[a][s], runs[b][s])) for s in seeds}}

    def paired_in(a: str, b: str, kind: str, group: str) -> list[dict[str, Any]]:
        """The pooled paired comparison of a and b on the questions of one category or house-size class."""
        def keep(ts: list[Any]) -> list[Any]:
            return [t for t in ts if (t.category if kind == "category" else sizes.get(t.question_id)) == group]

        return [vars(p) for p in ev.pool_paired([ev.paired_comparison(keep(runs[a][s]), keep(runs[b][s]),
                                                                        PAIRED_BUDGETS) for s in seeds])]

    groups = {"category": sorted({str(t.category) for r in runs.values() for ts in r.values() for t in ts}),
              "size": [c for c in ev.SIZE_CLASSES if c in set(sizes.values())]}
    # semantic against every other run, every run against fbe and against each --versus strategy
    results["paired_bases"] = [b for b in dict.fromkeys(("semantic", "fbe", *getattr(args, "versus", []))) if b in runs]
    for base in results["paired_bases"]:
        others = [k for k in runs if k != base]
        results[f"paired_vs_{base}_by_group"] = {
            kind: {g: {k: (paired_in(base, k, kind, g) if base == "semantic" else paired_in(k, base, kind, g))
                       for k in others} for g in names} for kind, names in groups.items()}
        pairs = {k: (paired(base, k) if base == "semantic" else paired(k, base)) for k in others}
        results[f"paired_vs_{base}"] = {k: v[0] for k, v in pairs.items()}
        results[f"paired_vs_{base}_per_seed"] = {k: v[1] for k, v in pairs.items()}
        results[f"first_evidence_vs_{base}"] = {k: (sooner(base, k) if base == "semantic" else sooner(k, base))
                                                for k in others}
    if args.ceiling:
        results["ceiling"] = _ceiling(questions, settings, out, sizes)
    (out / "explore.json").write_text(json.dumps(results, indent=2))
    from eqa_app.plots import plot_explore

    paths = plot_explore(results, out)
    _print_explore(results)
    print(f"results: {out / 'explore.json'}; plots: {', '.join(str(p) for p in paths)}")
    return 0


def _ceiling(questions: dict[int, list[Any]], settings: Any, out: Path, sizes: dict[str, str]) -> dict[str, Any]:
    """The evidence ceiling of the questions (:mod:`eqa_app.ceiling`): per question the earliest normalised step
    at which the evidence can be perceived, kept in ``<out>/ceiling.json`` (computed again only for questions it
    lacks); pooled, per seed, per category and per house-size class, the share within each CDF budget."""
    from eqa_app.ceiling import Ceiling, benchmark_ceilings, ceiling_cdf

    path = out / "ceiling.json"
    stored: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {}
    todo = [q for qs in questions.values() for q in qs if q.id not in stored]
    if todo:
        t0 = time.monotonic()
        for c in benchmark_ceilings(todo, settings, settings.sim_width, settings.sim_height):
            stored[c.question_id] = vars(c)
        log.info("evidence ceiling of %d questions in %.1f min", len(todo), (time.monotonic() - t0) / 60)
        path.write_text(json.dumps(dict(sorted(stored.items())), indent=0))
    every = {q.id: (q, Ceiling(**stored[q.id])) for qs in questions.values() for q in qs}

    def summary(cs: list[Ceiling]) -> dict[str, Any]:
        reasons: dict[str, int] = {}
        for c in cs:
            reasons[c.reason] = reasons.get(c.reason, 0) + 1
        return {"n": len(cs), "cdf": ceiling_cdf(cs, CDF_BUDGETS),
                "share_within": {f"{b:g}": ceiling_cdf(cs, [b])[0] for b in (0.25, 0.5, 1.0)}, "reasons": reasons}

    def group(key: Any) -> dict[str, Any]:
        names = sorted({str(key(q)) for q, _ in every.values()})
        return {g: summary([c for q, c in every.values() if str(key(q)) == g]) for g in names}

    return {**summary([c for _, c in every.values()]),
            "what": "evidence perceivable (simulated perception model, quality > 0) from a pose reachable within the "
                    "budget along the true house's shortest paths, max_step_m per step, any heading on arrival",
            "per_seed": {str(s): summary([every[q.id][1] for q in qs]) for s, qs in questions.items()},
            "by_category": group(lambda q: q.category), "by_size": group(lambda q: sizes.get(q.id))}


def _areas(questions: list[Any], settings: Any) -> dict[str, float]:
    from services.sim.library import load_or_generate

    cache: dict[str, float] = {}
    for q in questions:
        if q.scene not in cache:
            cache[q.scene] = float(load_or_generate(q.scene, settings.scenes_path).floor_area_m2)
    return {q.id: cache[q.scene] for q in questions}


def _print_explore(results: dict[str, Any]) -> None:
    budgets = results["budgets"]
    seeds = results.get("seeds", [0])
    roles = results.get("seed_roles", {})
    print(f"success rate vs normalised step budget ({results['scorer']}, {results['size']}, runner "
          f"{results.get('runner', 'fleet')}), pooled over seeds "
          + ", ".join(f"{s} ({roles.get(str(s), '?')})" for s in seeds))
    width = max([9, *(len(k) for k in results["strategies"])])
    print(f"{'strategy':<{width}} n    " + " ".join(f"{b:>5.1f}" for b in budgets) + "  evidence seen (first at, x T)")
    for name, r in results["strategies"].items():
        print(f"{name:<{width}} {r['n']:<4} " + " ".join(f"{v:5.2f}" for v in r["success"])
              + f"  {r['evidence_share']:.3f} ({r['first_evidence_at']:.2f})")
    if (c := results.get("ceiling")):
        print(f"evidence ceiling (n {c['n']}): perceivable within 0.25 / 0.5 / 1 T "
              + " / ".join(f"{c['share_within'][b]:.3f}" for b in ("0.25", "0.5", "1")))
    print("success at T among the episodes that saw the evidence within T / that did not (n):")
    for name, r in results["strategies"].items():
        s = r.get("success_by_evidence", {}).get("1")
        if s:
            print(f"  {name:<{width}} {s['success_seen']:.3f} ({s['n_seen']}) / {s['success_unseen']:.3f} "
                  f"({s['n_unseen']}); lift {s['lift']:+.3f}")
    for base in results.get("paired_bases", ("semantic", "fbe")):
        what = "semantic against each other run" if base == "semantic" else f"each run against {base}"
        paired = results.get(f"paired_vs_{base}", {})
        if not paired:
            continue
        print(f"{what}, same questions (right only in the first / only in the second, exact sign-test p):")
        for other, rows in paired.items():
            print(f"  {other:<{width}} " + "   ".join(
                f"{p['budget']:.1f} T: {p['a_only']:>3} / {p['b_only']:<3} p {p['p_value']:<7.3g}"
                + (f"[{p['ci_low']:+.3f}, {p['ci_high']:+.3f}]" if "ci_low" in p else "") for p in rows))
        sooner = results.get(f"first_evidence_vs_{base}", {})
        if sooner:
            print(f"  evidence seen sooner ({what}; first / second, sign-test p; mean gain in share of T):")
            for other, r in sooner.items():
                p = r["pooled"]
                print(f"  {other:<{width}} {p['a_only']:>4} / {p['b_only']:<4} p {p['p_value']:<7.3g} "
                      f"{p['diff']:+.3f} [{p['ci_low']:+.3f}, {p['ci_high']:+.3f}]")


def cmd_stop(args: argparse.Namespace) -> int:
    from eqa.service import setup_logging
    from eqa_app import evaluation as ev

    if args.miscalibration or args.cp_guided:  # from perceptions recorded in-process
        from eqa.settings import Settings
        from eqa_app import stop_sensitivity as sens

        settings = Settings()

        def loader(seed: int) -> Any:
            return _benchmark(seed, settings)

        if args.cp_guided:
            sens.compare_guided(Path(args.recordings), list(sens.EVALUATION_SEEDS), args.limit, args.size,
                                args.record_workers, Path(args.out), not args.no_progress, loader)
            return 0
        return sens.run(args.miscalibration, args.levels, args.limit, Path(args.out), Path(args.recordings),
                        args.strategy, args.size, args.record_workers, not args.no_progress, loader=loader)

    settings = _settings(args)
    setup_logging(settings.log_level, "eqa-bench")
    logging.getLogger("eqa.launcher").setLevel(logging.WARNING)
    # calibration and test splits of every seed, pooled (--limit per seed); each seed's runs in its own set
    cal, test = [], []
    for seed in dict.fromkeys(args.seeds):
        name = set_name(args.strategy, settings, seed) + _runner_suffix(args)
        cal += _collect(_questions("calibration", args.limit, settings, seed), settings, args.strategy, name, args)
        test_limit = None if args.limit is None else max(1, args.limit * 2 // 3)
        test += _collect(_questions("test", test_limit, settings, seed), settings, args.strategy, name, args)
    usable = [e for e in EPS_SWEEP if _quantile_defined(len(cal), e)]
    table = ev.calibrate_traces(cal, usable, name="bench")
    results: dict[str, Any] = {
        "scorer": scorer_label(settings), "strategy": args.strategy, "n_calibration": len(cal), "n_test": len(test),
        "seeds": list(dict.fromkeys(args.seeds)),
        "size": f"{settings.sim_width}x{settings.sim_height}",
        "cp": [vars(p) for p in ev.cp_curve(table, test)],
        "entropy": [vars(p) for p in ev.threshold_curve("entropy", ENTROPY_SWEEP, test)],
        "relevance": [vars(p) for p in ev.threshold_curve("relevance", RELEVANCE_SWEEP, test)],
        "full_budget_success": ev.success_at_budgets(test, (1.0,))[0],
        "q_hat": {f"{e.eps:g}": e.q_hat for e in table.entries},
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "stop.json").write_text(json.dumps(results, indent=2))
    from eqa_app.plots import plot_stop

    path = plot_stop(results, out)
    print(f"stopping rules on {len(test)} test episodes, calibrated on {len(cal)} ({results['scorer']})")
    print(f"running to the step limit: success {results['full_budget_success']:.3f}")
    print("rule       param  success  mean norm. steps  coverage (CP: >= 1-eps?)")
    for rule in ("cp", "entropy", "relevance"):
        for p in results[rule]:
            cov = "" if p["coverage"] is None else f"{p['coverage']:.3f} vs {1 - p['parameter']:.2f}"
            print(f"{rule:<10} {p['parameter']:<6.3g} {p['success']:<8.3f} {p['mean_normalized_steps']:<17.3f} {cov}")
    print(f"results: {out / 'stop.json'}; plot: {path}")
    return 0




def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--limit", type=int, default=None, help="use only N questions (quick mode, e.g. 20)")
    p.add_argument("--robots", type=int, default=4,
                   help="simulated robots run at once (default 4: the fastest measured on 2 cores, 27 episodes/min)")
    p.add_argument("--scorers", type=int, default=1, help="scorer replicas (default 1)")
    p.add_argument("--size", default="320x240",
                   help="camera image size WxH (default 320x240, as the published figures; the reference is 640x480)")
    p.add_argument("--out", default="var/bench", help="directory for JSON results and PNG plots")
    p.add_argument("--scorer", choices=("oracle", "hf", "remote"), default=None,
                   help="scorer backend (default: EQA_SCORER_BACKEND, normally oracle; hf reads EQA_HF_MODEL_PATH, "
                        "remote reads EQA_REMOTE_BASE_URL / EQA_REMOTE_MODEL / EQA_REMOTE_API_KEY)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--runner", choices=("fleet", "cores"), default="fleet",
                   help="fleet (default): every service as its own process over Zenoh; cores: the services' step "
                        "functions in-process (eqa_app/core_runner.py), several times less CPU, same seeds; its "
                        "trace sets are kept apart (name suffix -cores) and the results say which runner")
    p.add_argument("--workers", type=int, default=2, help="processes of the cores runner (default 2)")


def cmd_component(args: argparse.Namespace) -> int:
    """``eqa bench component [NAME [ARGS]]``: that benchmark's ``main(ARGS)``, or the default set."""
    import importlib

    from eqa_app.benches.harness import names

    if args.name is None:
        from eqa_app.benches.__main__ import main

        return main(args.args)
    if args.name not in names():
        from eqa_app.cli import UsageError

        raise UsageError(f"no benchmark {args.name!r}; choose from {', '.join(names())}")
    return int(importlib.import_module(f"eqa_app.benches.{args.name}").main(args.args) or 0)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("bench", help="reproduce the paper's comparisons (Fig. 7, 9, A6, A7)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="bench_command", metavar="WHAT", required=True)
    base_help = p.format_help

    def format_help() -> str:  # the catalogue reads every benchmark's source: only when help is printed
        from eqa_app.benches.harness import catalogue

        return (f"{base_help()}\ncomponent benchmarks (eqa bench component NAME [ARGS], or "
                f"python -m eqa_app.benches.NAME [ARGS]):\n{catalogue()}\n")

    p.format_help = format_help  # type: ignore[method-assign]
    c = sub.add_parser("component", help="a component benchmark (eqa bench --help lists them), or the default set",
                       description="Run one component benchmark with its own arguments (NAME --help for them), or "
                                   "with no NAME the default set in turn (make bench).")
    c.add_argument("name", nargs="?", default=None, help="the benchmark (eqa bench --help lists them)")
    c.add_argument("args", nargs=argparse.REMAINDER, help="its arguments")
    c.set_defaults(func=cmd_component)
    e = sub.add_parser("explore", help="success vs normalised step budget per exploration strategy",
                       description="Success rate against the normalised step budget (0.1..1.0 of T) for each "
                       "exploration strategy (Explore-EQA Fig. 7), per category (Fig. A6) and by house size (Fig. A7).")
    _common(e)
    e.add_argument("--split", choices=("test", "all"), default="all",
                   help="questions: the 200 test ones or all 500 (default all)")
    e.add_argument("--strategies", nargs="+", choices=STRATEGIES + RULES + BOUNDS, default=list(STRATEGIES),
                   help="strategies to run (default: the four of Fig. 7; vlfm, gain and topo are the deterministic "
                        "frontier rules of docs/results/exploration-strategies.md); target_oracle and perfect_sv / "
                        "perfect_vlfm / perfect_gain (Eq. A6 / vlfm / gain on ground-truth semantic values) are "
                        "benchmark-only yardsticks (upper bounds that read the ground-truth target positions)")
    e.add_argument("--versus", nargs="*", default=[], metavar="STRATEGY",
                   help="also pair every run with these (each run against it, as against fbe), e.g. --versus gain "
                        "to compare a yardstick with the rule it runs")
    e.add_argument("--ceiling", action="store_true",
                   help="also compute the evidence ceiling (eqa_app/ceiling.py): the share of questions whose evidence "
                        "can be perceived at all within each budget (ground truth, kept in <--out>/ceiling.json)")
    e.add_argument("--traces", nargs="*", default=[], metavar="DIR",
                   help="also import stored trace sets from these directories (e.g. bench/results/explore-seeds/"
                        "traces), so that runs stored elsewhere join the figures and paired tests without being run")
    e.add_argument("--seeds", nargs="+", type=int, default=[0], metavar="SEED",
                   help="benchmark seeds, pooled and per seed (default 0, the legacy seed; the evaluation seeds "
                        "are 1 2 3, the tuning seed 11: eqa.seeds); --limit applies per seed")
    e.add_argument("--tau", nargs="*", type=float, default=[], metavar="TAU",
                   help="also run semantic exploration with tau_LSV = tau_GSV = TAU (Fig. 7c; the default "
                        "temperatures are EQA_TAU_LSV / EQA_TAU_GSV = 1), e.g. --tau 3 5")
    e.add_argument("--view-bins", nargs="*", type=int, default=[], choices=range(1, 17), metavar="B",
                   help="also run semantic exploration keeping the best value per viewing-direction bin, B bins "
                        "(EQA_VIEW_BINS; the agreement EQA_VIEW_AGREE, default 2, from the environment)")
    e.set_defaults(func=cmd_explore)
    s = sub.add_parser("stop", help="CP vs entropy vs relevance stopping (calibrate, then replay the test split)",
                       description="Calibrate CP on the calibration split, then replay the test split with an eps "
                       "sweep, an entropy sweep and a relevance sweep (Explore-EQA Fig. 9); prints the empirical "
                       "coverage of the CP sets against 1 - eps.")
    _common(s)
    s.add_argument("--strategy", choices=STRATEGIES, default="semantic")
    s.add_argument("--seeds", nargs="+", type=int, default=[0], metavar="SEED",
                   help="benchmark seeds whose calibration and test splits are pooled (default 0, the legacy seed; "
                        "evaluation seeds 1 2 3: eqa.seeds); --limit applies per seed")
    s.add_argument("--miscalibration", nargs="+", metavar="MODE",
                   choices=("category", "view", "related", "irrelevant", "all"),
                   help="sensitivity study instead (simulated perception model, not a VLM): sweep these oracle "
                        "miscalibration modes (EQA_ORACLE_MISCAL_*; 'all' = every mode at once) over --levels; "
                        "operating points chosen on the tuning seed, evaluated on the evaluation seeds (eqa.seeds); "
                        "perceptions recorded once in-process (--recordings), re-scored per level. --limit = "
                        "calibration questions per seed (the test split gets 2/3 of it)")
    s.add_argument("--levels", nargs="+", type=float, default=[0.0, 0.25, 0.5, 0.75, 1.0],
                   help="miscalibration levels in [0, 1] (0 = the default model), with --miscalibration")
    s.add_argument("--recordings", default="var/sensitivity", help="where --miscalibration keeps its recordings")
    s.add_argument("--record-workers", type=int, default=1, help="recording processes for --miscalibration")
    s.add_argument("--cp-guided", action="store_true",
                   help="compare the cp_guided strategy with semantic instead: steps to a single-answer CP set and "
                        "success at eps 0.2 on the evaluation seeds' test splits (simulated perception model)")
    s.set_defaults(func=cmd_stop)
    from eqa_app import task_bench  # HELIOS Tables 1, 2

    task_bench.register(sub)
    from eqa_app import home_bench  # questions in a known house: cold vs warm

    home_bench.register(sub)
