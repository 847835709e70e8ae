"""``eqa calibrate``: calibrate the conformal stopping rule (Explore-EQA section V) and store the table.

Two ways to get the calibration traces (per-step answer distributions and relevance of full-length
episodes, rule ``max_steps``):

* run the episodes of a benchmark split through the services (``eqa_app.benchmark_runner.collect_traces``), or
* ``--from-traces FILE.jsonl``: one :class:`services.stopper.calibration.Trace` JSON per line, nothing run.

Either way each trace is stored in the trace set (``--set-name``) as soon as it exists, and questions whose
trace is already stored are skipped: an interrupted run, run again, resumes and gives the same ``q_hat``.
The table (kappas, ``q_hat`` per eps, N, provenance) goes to the store under ``eqa:calibration:<name>``
and, with ``--out``, to a JSON file (``services/stopper/data/<name>.json`` is the packaged fallback).

Beyond the paper:

* ``--by-category``: Mondrian calibration, a ``q_hat`` per question category besides the marginal one (the
  stopper uses the question's category's own threshold), so coverage holds within each category;
* ``--from-store``: calibrate from real episodes that users labelled (``POST /v1/episodes/{id}/label``) and
  that ran full length (stop rule ``max_steps``), with the per-step scores the stopper kept for them;
* ``--check``: do new labelled episodes (``--from-store`` or ``--from-traces``) still look exchangeable with
  the table? (:mod:`services.stopper.exchangeability`: rank test and coverage test.) Prints ``STALE`` and exits
  with status 3 when they do not - the case of a scorer pointed at another model.

Standalone: ``python -m eqa_app.calibrate calibrate --help``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

from eqa.messages import Question
from eqa.settings import Settings
from eqa.store import Store, StoreError, open_store
from services.stopper.answer_memory import AnswerRule
from services.stopper.calibration import (
    DEFAULT_EPS_GRID,
    CalibrationTable,
    TraceStore,
    calibrate,
    check_name,
    read_jsonl,
    save_table,
)
from services.stopper.conformal import CalibrationError, check_eps

log = logging.getLogger(__name__)
STRATEGIES = ("fbe", "semantic", "no_lsv", "no_gsv", "nearest")


class UsageError(ValueError):
    """Bad command-line input (exit code 2)."""


def parse_eps_grid(text: str) -> list[float]:
    """``"0.05,0.1"`` -> ``[0.05, 0.1]``; every value must be in (0, 1)."""
    out = []
    for part in text.split(","):
        if not part.strip():
            continue
        try:
            out.append(check_eps(float(part)))
        except (ValueError, CalibrationError) as exc:
            raise UsageError(f"--eps: {part.strip()!r}: {exc}") from exc
    if not out:
        raise UsageError("--eps: give at least one value in (0, 1)")
    return sorted(set(out))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate the conformal stopping rule (q_hat per eps) from full-length episodes",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--split",
        choices=("calibration", "test"),
        default="calibration",
        help="benchmark split whose questions are run (default: calibration)",
    )
    p.add_argument("--benchmark-seed", type=int, default=0, help="seed of the generated benchmark (default 0)")
    p.add_argument("--strategy", choices=STRATEGIES, default="semantic", help="exploration strategy")
    p.add_argument(
        "--eps",
        default=",".join(f"{e:g}" for e in DEFAULT_EPS_GRID),
        help="comma-separated eps grid, each in (0, 1) (default 0.05..0.95 step 0.05)",
    )
    p.add_argument("--limit", type=int, default=None, help="use only the first N questions / traces")
    p.add_argument("--name", default=None, help="calibration table name (default: EQA_CALIBRATION_NAME)")
    p.add_argument(
        "--set-name",
        default=None,
        help="trace set name (default: bench-<strategy>-<scorer backend>-<WxH>, as eqa bench; or the file's stem)",
    )
    p.add_argument(
        "--from-traces",
        type=Path,
        default=None,
        metavar="FILE.jsonl",
        help="calibrate from recorded traces (one Trace JSON per line; FILE.jsonl.gz is read through gzip) "
        "without running episodes",
    )
    p.add_argument("--from-store", action="store_true",
                   help="use labelled real episodes from the store (POST /v1/episodes/{id}/label; full-length "
                        "runs only, stop rule max_steps) instead of running the benchmark")
    p.add_argument("--tenant", default=None, help="with --from-store: only this tenant's labelled episodes")
    p.add_argument("--by-category", action="store_true",
                   help="also calibrate per question category (Mondrian CP: coverage within each category)")
    p.add_argument("--check", action="store_true",
                   help="do not calibrate: test whether the labelled episodes of --from-store / --from-traces are "
                        "still exchangeable with table --name (rank and coverage tests); exit status 3 if STALE")
    p.add_argument("--alpha", type=float, default=0.05, help="significance level of --check (default 0.05)")
    p.add_argument("--answer-memory", type=int, default=None, metavar="K",
                   help="calibrate the scores of the answer-memory rule that pools the K most relevant views "
                        "(default EQA_ANSWER_MEMORY_K, 0 = the single-view rule); the stopper must use "
                        "the same K and fusion for the coverage guarantee")
    p.add_argument("--answer-fusion", choices=("loglinear", "linear"), default=None,
                   help="pooling of the answer memory (default EQA_ANSWER_MEMORY_FUSION)")
    p.add_argument("--out", type=Path, default=None, metavar="FILE.json", help="also write the table here")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_calibrate)


def _bar(total: int | None, desc: str, disable: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="episode", disable=disable, file=sys.stderr)


def _import_traces(ts: TraceStore, set_name: str, path: Path, limit: int | None, quiet: bool) -> list[str]:
    """Store each trace of ``path`` not yet in the set, one write per trace; return the question ids."""
    ids: list[str] = []
    seen: set[str] = set()
    stored = skipped = 0
    with _bar(None, f"importing traces into {set_name}", quiet) as bar:
        for _lineno, trace in read_jsonl(path):
            if limit is not None and len(ids) >= limit:
                break
            if trace.question_id in seen:
                continue
            seen.add(trace.question_id)
            ids.append(trace.question_id)
            if ts.has(set_name, trace.question_id):
                skipped += 1
            else:
                ts.save(set_name, trace)
                stored += 1
            bar.update(1)
    log.info("%d traces stored, %d already present (resumed)", stored, skipped)
    return ids


def _load_questions(args: argparse.Namespace, settings: Settings) -> list[Question]:
    from services.sim.questions import benchmark

    bench = benchmark(seed=args.benchmark_seed, scenes_dir=settings.scenes_path)
    questions = list(bench.calibration if args.split == "calibration" else bench.test)
    return questions[: args.limit] if args.limit is not None else questions


def _run_missing(
    args: argparse.Namespace, settings: Settings, ts: TraceStore, set_name: str, questions: list[Question]
) -> None:
    """Run the episodes of the questions without a stored trace (``eqa_app.benchmark_runner.collect_traces``)."""
    missing = [q for q in questions if not ts.has(set_name, q.id)]
    log.info(
        "%d of %d questions already have a trace in %s",
        len(questions) - len(missing),
        len(questions),
        set_name,
    )
    if not missing:
        return
    from eqa_app.benchmark_runner import collect_traces  # checked in run_calibrate

    with _bar(len(questions), f"calibration episodes ({set_name})", args.no_progress) as bar:
        bar.update(len(questions) - len(missing))
        # The benchmark runner stores each trace through TraceStore as it finishes; the bar is advanced here,
        # once per yielded trace; the runner may write status text to it (bar.set_postfix_str).
        for trace in collect_traces(missing, settings, strategy=args.strategy, set_name=set_name, progress=bar):
            if not ts.has(set_name, trace.question_id):
                ts.save(set_name, trace)
            bar.update(1)


def scorer_mode(settings: Settings) -> str:
    """The mode the scorer reads distributions in (recorded in the table): ``logprobs`` for the
    oracle and hf backends, the remote endpoint's resolved mode (EQA_REMOTE_MODE; auto is probed)."""
    if settings.scorer_backend != "remote":
        return "logprobs"
    if settings.remote_mode != "auto":
        return settings.remote_mode
    from services.vlm_scorer.backends.remote import probe_endpoint

    report = probe_endpoint(settings.remote_base_url or "", settings.remote_model, settings.remote_api_key,
                            settings.remote_timeout_s, "auto", settings.remote_samples, score_step=False)
    return report.mode or "auto"


def run_calibrate(args: argparse.Namespace, settings: Settings, store: Store) -> CalibrationTable:
    grid = parse_eps_grid(args.eps)
    if args.limit is not None and args.limit < 1:
        raise UsageError("--limit must be >= 1")
    name = args.name or settings.calibration_name
    try:
        check_name(name, "--name")
        if args.set_name is not None:
            check_name(args.set_name, "--set-name")
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    ts = TraceStore(store)
    provenance: dict[str, Any] = {"created_by": "eqa calibrate", "eps_grid": grid}
    rule = _answer_rule(args, settings)
    if args.from_store:
        traces = _labelled(ts, args)
        if args.limit is not None:
            traces = traces[: args.limit]
        provenance.update(source="labelled episodes", tenant=args.tenant, set_name="labelled episodes",
                          scorer_backend=settings.scorer_backend, scorer_mode=scorer_mode(settings))
        table = calibrate(traces, grid, name=name, provenance=provenance, by_category=args.by_category,
                          answer_rule=rule)
        return _save(store, table, args)
    if args.from_traces is not None:
        path: Path = args.from_traces
        if not path.exists():
            raise UsageError(f"--from-traces: {path} does not exist")
        set_name = args.set_name or f"traces-{path.stem}"
        try:
            check_name(set_name, "trace set name (use --set-name)")
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
        ids = _import_traces(ts, set_name, path, args.limit, args.no_progress)
        provenance.update(source="traces file", file=str(path))
    else:
        from eqa_app.bench_cli import set_name as bench_set_name

        # The same trace set as `eqa bench` (strategy, scorer, image size): calibration reuses benchmark runs.
        set_name = args.set_name or bench_set_name(args.strategy, settings)
        questions = _load_questions(args, settings)
        _run_missing(args, settings, ts, set_name, questions)
        ids = [q.id for q in questions]
        provenance.update(
            source="episodes",
            split=args.split,
            benchmark_seed=args.benchmark_seed,
            strategy=args.strategy,
            scorer_backend=settings.scorer_backend,
            scorer_mode=scorer_mode(settings),
        )
    provenance["set_name"] = set_name
    wanted = set(ids)
    traces = [t for t in ts.load(set_name) if t.question_id in wanted]
    absent = wanted - {t.question_id for t in traces}
    if absent:
        raise CalibrationError(
            f"{len(absent)} questions have no stored trace in {set_name}: "
            f"{sorted(absent)[:5]}; run the command again to resume"
        )
    table = calibrate(traces, grid, name=name, provenance=provenance, by_category=args.by_category,
                          answer_rule=rule)
    return _save(store, table, args)


def _answer_rule(args: argparse.Namespace, settings: Settings) -> AnswerRule:
    """The answer rule to calibrate: --answer-memory / --answer-fusion, else the settings'."""
    k = getattr(args, "answer_memory", None)
    fusion = getattr(args, "answer_fusion", None)
    try:
        return AnswerRule(settings.answer_memory_k if k is None else k,
                          fusion or settings.answer_memory_fusion)
    except ValueError as exc:
        raise UsageError(f"--answer-memory: {exc}") from exc


def _save(store: Store, table: CalibrationTable, args: argparse.Namespace) -> CalibrationTable:
    save_table(store, table)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(table.model_dump_json(indent=1) + "\n", encoding="utf-8")
    return table


def _labelled(ts: TraceStore, args: argparse.Namespace) -> list[Any]:
    traces, skipped = ts.labelled(args.tenant)
    if skipped["not_full_length"] or skipped["no_trace"] or skipped["invalid"]:
        log.warning("labelled episodes skipped: %d cut short by their stop rule (calibration data must run to the "
                    "step limit: ask with stop_rule max_steps), %d without stored scores, %d invalid",
                    skipped["not_full_length"], skipped["no_trace"], skipped["invalid"])
    if not traces:
        raise CalibrationError(
            "no labelled full-length episodes in the store: run questions with stop_rule max_steps, then post "
            "their true answers to POST /v1/episodes/{id}/label" + (f" (tenant {args.tenant})" if args.tenant else ""))
    return traces


def run_check(args: argparse.Namespace, settings: Settings, store: Store) -> Any:
    """``--check``: the staleness report of table ``--name`` against new labelled episodes."""
    from services.stopper.calibration import load_table
    from services.stopper.exchangeability import check_exchangeable

    name = args.name or settings.calibration_name
    try:
        check_name(name, "--name")
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    table, where = load_table(store, name)
    if table is None:
        raise UsageError(f"--check: {where}: calibrate first")
    ts = TraceStore(store)
    if args.from_store:
        traces = _labelled(ts, args)
    elif args.from_traces is not None:
        if not args.from_traces.exists():
            raise UsageError(f"--from-traces: {args.from_traces} does not exist")
        # a trace file is calibration data by construction; a trace that says it was cut short by a stop rule is not
        traces = [t for _, t in read_jsonl(args.from_traces)
                  if t.answer is not None and t.steps and (t.stop_rule is None or t.full_length)]
    else:
        raise UsageError("--check needs the new labelled episodes: --from-store or --from-traces FILE.jsonl")
    if args.limit is not None:
        traces = traces[: args.limit]
    try:
        rule = AnswerRule.from_name(table.provenance.get("answer_rule"))  # the table's own answer rule
        report = check_exchangeable(table, [t.kappa(rule) for t in traces], alpha=args.alpha)
    except ValueError as exc:
        raise UsageError(str(exc)) from exc
    return table, where, report


def cmd_calibrate(args: argparse.Namespace) -> int:
    try:
        settings = Settings()
    except Exception as exc:
        print(f"error: invalid EQA_* settings: {exc}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    try:
        store = open_store(settings)
    except StoreError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    try:
        if args.check:
            table, where, report = run_check(args, settings, store)
            print(f"calibration table {table.name!r} ({where}, N={table.n}) against {report.n_new} new labelled "
                  f"episodes:")
            print(report.message)
            return 3 if report.stale else 0
        table = run_calibrate(args, settings, store)
    except (UsageError, CalibrationError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:
        print(f"error: cannot run calibration episodes ({exc}); use --from-traces FILE.jsonl", file=sys.stderr)
        return 1
    finally:
        store.close()
    print(
        f"calibration table {table.name!r}: N={table.n} episodes from {table.provenance.get('set_name')} "
        f"({time.monotonic() - t0:.1f} s)"
    )
    print("   eps  success>=  q_hat   threshold 1-q_hat")
    for e in table.entries:
        print(f"  {e.eps:4.2f}  {1 - e.eps:8.2f}  {e.q_hat:.4f}  {1 - e.q_hat:+.4f}")
    if table.groups:
        print("per category (Mondrian): N and q_hat per eps ('-': too few episodes for that eps: keeps every answer)")
        for cat, g in table.groups.items():
            got = {e.eps: e.q_hat for e in g.entries}
            print(f"  {cat:<15} N={g.n:<4} " + " ".join(
                f"{e.eps:g}:{got[e.eps]:.3f}" if e.eps in got else f"{e.eps:g}:-" for e in table.entries))
    return 0


def main(argv: list[str] | None = None) -> int:
    from eqa.service import setup_logging

    parser = argparse.ArgumentParser(prog="python -m eqa_app.calibrate")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(argv)
    setup_logging("WARNING", "stopper-cli")
    return int(args.func(args))


if __name__ == "__main__":
    raise SystemExit(main())
