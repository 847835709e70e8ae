"""``eqa bench ovmm`` and ``eqa bench objectnav``: HELIOS Tables 1, 2 (and 4's protocol) through the real services.

Each task of the task benchmark of a seed (:func:`services.sim.tasks.task_benchmark`; the tuning seed 11 and
the evaluation seeds 1, 2, 3 of :mod:`eqa.seeds`) runs as a task episode on a real fleet (sim, mapper, scorer
with the detector, planner, stopper as processes over Zenoh), once per agent variant:

* ``ovmm`` (Table 1): pick-and-place tasks x ``trusting`` / ``no_global`` / ``helios`` x pick limits 1 / 5 /
  unlimited. Each limit is enforced during the run (``--pick-limits``): the episode carries it
  (``EpisodeStart.pick_limit``) to the planner, which ends the task when a failed pick used the last attempt,
  and to the simulator, which scores an episode that exceeded it 0 on every metric (the paper's rule). A limit
  not run (``--pick-limits unlimited``) is derived from the unlimited runs by zeroing the runs that used more
  attempts (rows marked "post hoc"); the difference between the two readings is measured on the traces
  (docs/results/helios-tasks.md).
* ``objectnav`` (Table 2): find-object tasks x the HELIOS stop decision (``helios``: stop only when Psi >= tau_g
  after looking again) against stopping on the first confident detection (``trusting``); SR and SPL.

Every run's per-step trace (:mod:`eqa.task_traces`: phase, decision numbers, pose, collisions, skills) is
read from the store after its end and exported to ``<out>/<bench>-seed<s>-traces.jsonl``; ``--replay DIR``
rebuilds the tables and the failure break-down (HELIOS Fig. 5 / 6, ``<bench>-failures.png``) from those files
alone, recomputing every metric from the traces, without running an episode.

Metrics come from the simulator's ground truth (``EpisodeEnd.metrics``); means with standard errors
(``sqrt(p (1 - p) / n)`` for rates, the sample SE for SPL) and paired comparisons of each variant against
``helios`` on the same tasks (wins / losses, exact two-sided sign test). Results are appended to a JSON-lines
file per benchmark and seed and reused when the same task, variant and step budget come again.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import queue
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from eqa import keys
from eqa.messages import (
    EpisodeCancel,
    EpisodeEnd,
    ErrorReply,
    Goal,
    Task,
    new_id,
)
from eqa.seeds import seed_role
from eqa.settings import Settings
from eqa.task_traces import (
    FIND_CAUSES,
    PICK_PLACE_CAUSES,
    TraceError,
    breakdown,
    collision_phases,
    format_breakdown,
    replay_metrics,
)
from eqa_app.stats import sign_test_p as sign_test
from eqa_app.task_results import TaskResult, task_seed

log = logging.getLogger(__name__)

OVMM_VARIANTS = ("trusting", "no_global", "helios")
OBJECTNAV_VARIANTS = ("trusting", "helios")
OVMM_METRICS = ("FindObj", "Pick", "FindRec", "Place", "SR")
PICK_LIMITS: tuple[int | None, ...] = (1, 5, None)
SIMULATED = ("simulated perception model (oracle detector reading ground-truth labels, with documented misses, "
             "confusions and false positives), not a detector")
GROUND_TRUTH = ("ground-truth detections (HELIOS Table 4 yardstick: the oracle detector with every visible pixel of "
                "a requested class, score 1, no miss, confusion or false positive; EQA_DETECTOR_GROUND_TRUTH), "
                "not a detector")


def limited(m: dict[str, float], limit: int | None) -> dict[str, float]:
    """The metrics of a run under a pick limit (module doc): 0 everywhere when it used more attempts."""
    if limit is not None and m.get("pick_attempts", 0.0) > limit:
        return {k: 0.0 for k in OVMM_METRICS}
    return {k: float(m.get(k, 0.0)) for k in OVMM_METRICS}


def mean_se(values: list[float], binary: bool = True) -> tuple[float, float]:
    n = len(values)
    if n == 0:
        return math.nan, math.nan
    mu = sum(values) / n
    if binary:
        return mu, math.sqrt(max(mu * (1 - mu), 0.0) / n)
    var = sum((v - mu) ** 2 for v in values) / max(n - 1, 1)
    return mu, math.sqrt(var / n)


Job = tuple[Task, str, int] | tuple[Task, str, int, int | None]


def run_tasks(settings: Settings, jobs: list[Job], robots: int = 2, scorers: int = 1,
              step_timeout_s: float = 300.0, progress: bool = True,
              on_result: Callable[[TaskResult], None] | None = None,
              episode_ids: list[str] | None = None) -> list[TaskResult]:
    """Run ``(task, variant, max_steps[, pick_limit])`` jobs through a fleet over ``robots`` simulated robots,
    each with its pick limit enforced (module doc); every result carries the run's trace from the store.
    ``on_result`` is called as each one ends (so an interrupted benchmark keeps what it ran). ``episode_ids``:
    one per job (default: fresh ids)."""
    from eqa.launcher import PIPELINE, Fleet
    from eqa.store import open_store, task_trace_key
    from eqa_app.task_cores import task_start

    if not jobs:
        return []
    jobs4 = [(j[0], j[1], j[2], j[3] if len(j) > 3 else None) for j in jobs]  # type: ignore[misc]
    inbox: queue.Queue[Any] = queue.Queue()
    out: list[TaskResult] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="task episodes", unit="ep")
    s = settings.model_copy(update={"record": False, "robots": [f"task{i}" for i in range(robots)]})
    with Fleet(s, services=PIPELINE, scorers=scorers) as fleet:
        bus = fleet.hub
        bus.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, lambda k, m: inbox.put(m))
        bus.subscribe(keys.any_robot(keys.SIM_ERROR), ErrorReply, lambda k, m: inbox.put(m))
        bus.subscribe(keys.any_robot(keys.PLANNER_GOAL), Goal, lambda k, m: inbox.put(m))  # progress
        time.sleep(0.3)
        store = open_store(s)
        pending = list(reversed(jobs4))
        free = list(s.robots)
        running: dict[str, tuple[str, Task, str, int, int | None, float, float]] = {}

        def trace_of(eid: str) -> dict[str, Any] | None:
            raw = store.get_json(task_trace_key(eid))
            return raw if isinstance(raw, dict) else None

        while pending or running:
            while free and pending:
                robot = free.pop(0)
                task, variant, steps, limit = pending.pop()
                eid = episode_ids[len(jobs4) - len(pending) - 1] if episode_ids is not None else new_id("task")
                start = task_start(task, variant, steps, limit, eid, robot, task_seed(task.id))
                bus.publish(keys.stream(robot, keys.EPISODE_START), start)
                now = time.monotonic()
                running[eid] = (robot, task, variant, steps, limit, now, now)
            try:
                msg = inbox.get(timeout=1.0)
            except queue.Empty:
                msg = None
            now = time.monotonic()
            if msg is not None and msg.episode_id in running:
                robot, task, variant, steps, limit, t0, _ = running[msg.episode_id]
                running[msg.episode_id] = (robot, task, variant, steps, limit, t0, now)
                end: EpisodeEnd | None = msg if isinstance(msg, EpisodeEnd) else None
                # a start the sim refuses ends the run; a refused goal (also of step 0) is planned again
                fatal = (isinstance(msg, ErrorReply) and msg.step in (None, 0)
                         and not msg.reason.startswith("goal refused"))
                if end is None and fatal:
                    bus.publish(keys.stream(robot, keys.EPISODE_CANCEL),
                                EpisodeCancel(episode_id=msg.episode_id, reason=msg.reason))
                if end is not None or fatal:
                    del running[msg.episode_id]
                    free.append(robot)
                    state = end.state if end is not None else "failed"
                    reason = end.reason if end is not None else f"{msg.source}: {msg.reason}"
                    out.append(TaskResult(task.id, task.kind, variant, steps, dict(end.metrics) if end else {},
                                          state, reason, now - t0, limit, trace_of(msg.episode_id)))
                    if on_result is not None:
                        on_result(out[-1])
                    if bar is not None:
                        bar.update(1)
            for eid, (robot, task, variant, steps, limit, t0, seen) in list(running.items()):
                if now - seen > step_timeout_s:
                    why = f"no progress for {step_timeout_s:.0f} s"
                    bus.publish(keys.stream(robot, keys.EPISODE_CANCEL), EpisodeCancel(episode_id=eid, reason=why))
                    del running[eid]
                    free.append(robot)
                    out.append(TaskResult(task.id, task.kind, variant, steps, {}, "failed", why, now - t0, limit,
                                          trace_of(eid)))
                    if on_result is not None:
                        on_result(out[-1])
                    if bar is not None:
                        bar.update(1)
        store.close()
    if bar is not None:
        bar.close()
    return out


def load_results(path: Path) -> dict[tuple[str, str, int], TaskResult]:
    out: dict[tuple[str, str, int], TaskResult] = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            if line.strip():
                r = TaskResult(**json.loads(line))
                out[r.key()] = r
    return out


MetricsByLimit = dict[int | None, dict[str, dict[str, dict[str, float]]]]


def _limit_metrics(results: list[TaskResult], kind: str, variants: tuple[str, ...]
                   ) -> tuple[list[str], MetricsByLimit, dict[int | None, bool]]:
    """Per pick limit, variant and task the metrics of the run under that limit: the enforced run when every
    task of every variant has one, else (a limit not run) the unlimited run zeroed post hoc (:func:`limited`).
    Returns the tasks every variant ran (unlimited, or the only limit run), the metrics and which limits are
    post hoc."""
    limits = PICK_LIMITS if kind == "pick_place" else (None,)
    by: dict[int | None, dict[str, dict[str, TaskResult]]] = {
        lim: {v: {r.task_id: r for r in results if r.variant == v and r.pick_limit == lim} for v in variants}
        for lim in limits}
    have = {lim: set.intersection(*(set(d) for d in by[lim].values())) if variants else set() for lim in limits}
    # the table's tasks: those of the limit every variant ran most often (unlimited on a tie, as it derives the
    # others), so a few stray runs under another limit cannot shrink it
    common = sorted(max((have[lim] for lim in (None, *limits)), key=len) if any(have.values()) else set())
    out: MetricsByLimit = {}
    post_hoc: dict[int | None, bool] = {}
    for lim in limits:
        enforced = bool(common) and set(common) <= have[lim]
        if not enforced and not (set(common) <= have.get(None, set())):
            continue  # neither run nor derivable
        post_hoc[lim] = not enforced
        src = by[lim] if enforced else by[None]
        out[lim] = {v: {t: (dict(src[v][t].metrics) if enforced else limited(src[v][t].metrics, lim))
                        for t in common} for v in variants}
    return common, out, post_hoc


def summarise(kind: str, results: list[TaskResult], variants: tuple[str, ...]) -> dict[str, Any]:
    """Tables (module doc) as data: per variant (and pick limit for ovmm) mean and SE of each metric, n, and
    the paired comparison of SR against ``helios``; ``post_hoc`` on a row derived from unlimited runs."""
    common, by_limit, post_hoc = _limit_metrics(results, kind, variants)
    table: dict[str, Any] = {"n": len(common), "rows": []}
    for v in variants:
        if kind == "pick_place":
            for limit in PICK_LIMITS:
                if limit not in by_limit:
                    continue
                ms = [limited(by_limit[limit][v][t], None) for t in common]
                row = {"variant": v, "picks": limit or "unlimited", "post_hoc": post_hoc[limit]}
                for k in OVMM_METRICS:
                    row[k] = mean_se([m[k] for m in ms])
                table["rows"].append(row)
        elif None in by_limit:
            ms = [by_limit[None][v][t] for t in common]
            row = {"variant": v, "SR": mean_se([m.get("SR", 0.0) for m in ms]),
                   "SPL": mean_se([m.get("SPL", 0.0) for m in ms], binary=False)}
            table["rows"].append(row)
    cmp = []
    if "helios" in variants:
        for v in variants:
            if v == "helios":
                continue
            for limit in (PICK_LIMITS if kind == "pick_place" else (None,)):
                if limit not in by_limit:
                    continue
                h, o = by_limit[limit]["helios"], by_limit[limit][v]
                for k in (OVMM_METRICS if kind == "pick_place" else ("SR",)):
                    wins = sum(1 for t in common if h[t].get(k, 0.0) > o[t].get(k, 0.0))
                    losses = sum(1 for t in common if h[t].get(k, 0.0) < o[t].get(k, 0.0))
                    row = {"helios_vs": v, "picks": limit or "unlimited", "metric": k, "helios_wins": wins,
                           "helios_losses": losses, "sign_test_p": sign_test(wins, losses)}
                    cmp.append(row)
    table["paired"] = cmp  # every phase metric (pick and place) or SR
    table["paired_SR"] = [c for c in cmp if c["metric"] == "SR"]
    return table


def format_table(kind: str, table: dict[str, Any], seed: int | str, max_steps: int | None,
                 ground_truth: bool = False) -> str:
    name = ("Table 4 (OVMM, ground-truth detections)" if ground_truth else "Table 1 (OVMM)") if kind == "pick_place" \
        else "Table 2 (object search stop decision)" + (", ground-truth detections" if ground_truth else "")
    role = seed_role(seed) if isinstance(seed, int) else "evaluation"
    lines = [f"{name}: seed {seed} ({role}), n = {table['n']} tasks, step budget {max_steps or 'task default'}; "
             f"{GROUND_TRUTH if ground_truth else SIMULATED}"]
    if kind == "pick_place":
        lines.append(f"{'picks':<10} {'variant':<10} " + " ".join(f"{k:>13}" for k in OVMM_METRICS))
        for row in table["rows"]:
            cells = " ".join(f"{100 * row[k][0]:6.1f} ± {100 * row[k][1]:4.1f}" for k in OVMM_METRICS)
            mark = " (post hoc)" if row.get("post_hoc") else ""
            lines.append(f"{row['picks']!s:<10} {row['variant']:<10} {cells}{mark}")
    else:
        lines.append(f"{'variant':<10} {'SR':>13} {'SPL':>13}")
        for row in table["rows"]:
            lines.append(f"{row['variant']:<10} {100 * row['SR'][0]:6.1f} ± {100 * row['SR'][1]:4.1f} "
                         f"{100 * row['SPL'][0]:6.1f} ± {100 * row['SPL'][1]:4.1f}")
    for c in table.get("paired", table["paired_SR"]):
        lines.append(f"paired {c.get('metric', 'SR')}, helios vs {c['helios_vs']} ({c['picks']} picks): helios "
                     f"better on {c['helios_wins']}, worse on {c['helios_losses']} tasks, "
                     f"sign test p = {c['sign_test_p']:.3f}")
    return "\n".join(lines)


def plot(kind: str, table: dict[str, Any], title: str, path: Path) -> None:
    """Bars with standard errors: OVMM metrics per variant (unlimited / 5 / 1 picks side by side), or SR and SPL
    per stop rule."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = table["rows"]
    metrics = OVMM_METRICS if kind == "pick_place" else ("SR", "SPL")
    groups = [(r["variant"], r.get("picks")) for r in rows]
    fig, ax = plt.subplots(figsize=(9 if kind == "pick_place" else 5, 3.6))
    width = 0.8 / len(groups)
    for k, (r, (v, picks)) in enumerate(zip(rows, groups, strict=True)):
        xs = [i + (k - (len(groups) - 1) / 2) * width for i in range(len(metrics))]
        ax.bar(xs, [100 * r[m][0] for m in metrics], width, yerr=[100 * r[m][1] for m in metrics], capsize=2,
               label=f"{v}" + (f" ({picks} picks)" if picks is not None else ""))
    ax.set_xticks(range(len(metrics)), metrics)
    ax.set_ylabel("% of tasks (± SE)")
    ax.set_ylim(0, 100)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, ncol=3 if kind == "pick_place" else 1)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def traces_path(out_dir: Path, tag: str, seed: int) -> Path:
    """The exported traces of one benchmark and seed; a gzipped copy (``.jsonl.gz``, the committed form) is
    read when the plain file is absent."""
    plain = out_dir / f"{tag}-seed{seed}-traces.jsonl"
    packed = plain.with_name(plain.name + ".gz")
    return packed if packed.is_file() and not plain.is_file() else plain


def load_traces(path: Path) -> list[TaskResult]:
    """The runs of an exported traces file with their metrics replayed from the traces
    (:func:`eqa_app.task_traces.replay_metrics`; runs without a trace keep the metrics they ended with).
    Raises :class:`TraceError` naming the line of a malformed entry."""
    import gzip

    out: list[TaskResult] = []
    with (gzip.open(path, "rt", encoding="utf-8") if path.suffix == ".gz" else path.open(encoding="utf-8")) as fh:
        for lineno, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                r = TaskResult(**json.loads(line))
                if r.trace is not None:
                    r.metrics = replay_metrics(r.kind, r.trace, r.pick_limit)
            except (TypeError, ValueError) as exc:
                raise TraceError(f"{path}:{lineno}: not a task run with a trace: {exc}") from exc
            out.append(r)
    return out


def failure_table(kind: str, results: list[TaskResult], variants: tuple[str, ...], limit: int | None = None
                  ) -> tuple[dict[str, dict[str, int]], dict[str, dict[str, int]]]:
    """The failure break-down (HELIOS Fig. 5 / 6) of the runs under pick limit ``limit`` (the unlimited runs
    by default): counts per variant and first-failure cause, and the phases collisions happened in."""
    rows = [(r.variant, r.failure()) for r in results if r.variant in variants and r.pick_limit == limit]
    return breakdown(rows, kind), collision_phases(rows)


def cmd(args: argparse.Namespace) -> int:
    from eqa.service import setup_logging
    from eqa_app.cli import UsageError, check_scorer, load_settings
    from services.sim.tasks import task_benchmark

    settings = load_settings()
    if args.ground_truth_detections:
        settings = settings.model_copy(update={"detector_ground_truth": True})
    replay = Path(args.replay) if args.replay else None
    if replay is None:
        check_scorer(settings)
    elif not replay.is_dir():
        raise UsageError(f"--replay {replay}: not a directory (give the --out of an earlier run)")
    setup_logging("WARNING", "eqa-bench")
    kind = "pick_place" if args.bench_command == "ovmm" else "find_object"
    variants = tuple(args.variants or (OVMM_VARIANTS if kind == "pick_place" else OBJECTNAV_VARIANTS))
    limits: tuple[int | None, ...] = tuple(args.pick_limits) if kind == "pick_place" else (None,)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    gt = bool(args.ground_truth_detections)
    tag = args.bench_command + ("-gt" if gt else "")
    report: dict[str, Any] = {"benchmark": args.bench_command, "seeds": {}, "max_steps": args.max_steps,
                              "detections": GROUND_TRUTH if gt else SIMULATED,
                              "pick_limits": [lim or "unlimited" for lim in limits],
                              "replayed_from": str(replay) if replay else None}
    pooled: list[TaskResult] = []
    for seed in args.seeds:
        if replay is not None:
            src = traces_path(replay, tag, seed)
            if not src.is_file():
                raise UsageError(f"--replay: no {src.name} in {replay} (run `eqa bench {args.bench_command} --seeds "
                                 f"{seed} --out {replay}` first)")
            try:
                results = [r for r in load_traces(src) if r.variant in variants]
            except TraceError as exc:
                raise UsageError(str(exc)) from None
            results = list({r.key(): r for r in results}.values())
        else:
            n_pp, n_fo = (args.tasks, 0) if kind == "pick_place" else (0, args.tasks)
            bench = task_benchmark(seed, pick_place=n_pp, find=n_fo, scenes_dir=settings.scenes_path,
                                   progress=not args.no_progress)
            tasks = bench.of_kind(kind)
            if args.tasks_from and args.tasks_from < len(tasks):
                tasks = tasks[args.tasks_from:]
            path = out_dir / f"{tag}-seed{seed}.jsonl"
            tpath = out_dir / f"{tag}-seed{seed}-traces.jsonl"
            done = load_results(path)
            traced = {r.key(): r for r in load_traces(tpath)} if tpath.is_file() else {}
            for k, r in done.items():
                r.trace = traced[k].trace if k in traced else None

            def budget(t: Task) -> int:
                return min(t.max_steps or 1, args.max_steps) if args.max_steps else (t.max_steps or 1)

            wanted = {(t.id, v, budget(t), lim) for t in tasks for v in variants for lim in limits}
            jobs: list[Job] = [(t, v, budget(t), lim) for t in tasks for lim in limits for v in variants
                               if (t.id, v, budget(t), lim) not in done]

            def keep(r: TaskResult, path: Path = path, tpath: Path = tpath,
                     done: dict[tuple[str, str, int, int | None], TaskResult] = done) -> None:
                with path.open("a") as f:
                    f.write(json.dumps(r.row()) + "\n")
                with tpath.open("a") as f:
                    f.write(json.dumps(r.__dict__) + "\n")
                done[r.key()] = r

            if not args.summary_only and args.runner == "cores":
                from eqa_app.task_cores import run_tasks_cores

                run_tasks_cores(settings, jobs, progress=not args.no_progress, on_result=keep)
            elif not args.summary_only:
                run_tasks(settings, jobs, robots=args.robots, scorers=args.scorers, progress=not args.no_progress,
                          on_result=keep)
            results = [r for k, r in done.items() if k in wanted]
        table = summarise(kind, results, variants)
        fails, phases = failure_table(kind, results, variants, limits[-1] if None not in limits else None)
        secs = [r.seconds for r in results]
        report["seeds"][str(seed)] = {"role": seed_role(seed), "table": table, "failures": fails,
                                      "collision_phases": phases,
                                      "failed_runs": sum(1 for r in results if r.state == "failed"),
                                      "seconds_per_episode": (sum(secs) / len(secs)) if secs else None}
        print(format_table(kind, table, seed, args.max_steps, gt), flush=True)
        print(format_breakdown(fails, kind, variants, phases), flush=True)
        pooled += [TaskResult(**{**r.__dict__, "task_id": f"{seed}:{r.task_id}"}) for r in results]
    if len(args.seeds) > 1:
        table = summarise(kind, pooled, variants)
        fails, phases = failure_table(kind, pooled, variants, limits[-1] if None not in limits else None)
        report["pooled"] = {"seeds": args.seeds, "table": table, "failures": fails, "collision_phases": phases}
        print(format_table(kind, table, "+".join(map(str, args.seeds)), args.max_steps, gt), flush=True)
        print(format_breakdown(fails, kind, variants, phases), flush=True)
    last = report.get("pooled") or report["seeds"][str(args.seeds[-1])]
    detector = "ground-truth detections" if gt else "simulated detector, not a real detector"
    title = f"{tag}, seeds {'+'.join(map(str, args.seeds))}, n = {last['table']['n']} tasks; {detector}"
    plot(kind, last["table"], title, out_dir / f"{tag}.png")
    from eqa_app.plots import plot_failures

    causes = PICK_PLACE_CAUSES if kind == "pick_place" else FIND_CAUSES
    lim = limits[-1] if None not in limits else None
    plot_failures(last["failures"], causes, list(variants),
                  f"HELIOS Fig. 5/6 reading: first failure per run, {tag}, seeds {'+'.join(map(str, args.seeds))}, "
                  f"{lim or 'unlimited'} picks; {detector}", out_dir / f"{tag}-failures.png")
    (out_dir / f"{tag}.json").write_text(json.dumps(report, indent=1) + "\n")
    print(f"results: {out_dir / (tag + '.json')} (runs: {out_dir}/{tag}-seed*.jsonl, traces: "
          f"{out_dir}/{tag}-seed*-traces.jsonl; failure break-down: {out_dir / (tag + '-failures.png')})")
    return 0


def _limits(text: str) -> int | None:
    from services.planner.decisions import pick_limit  # one parser of "1", "5", "unlimited"

    try:
        return pick_limit(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(sub: argparse._SubParsersAction) -> None:
    for name, help_text in (("ovmm", "HELIOS Table 1: pick-and-place tasks, trusting / no_global / helios x 1 / 5 / "
                                     "unlimited picks (FindObj, Pick, FindRec, Place, SR)"),
                            ("objectnav", "HELIOS Table 2: object search, the HELIOS stop decision vs stopping on the "
                                          "first confident detection (SR, SPL)")):
        p = sub.add_parser(name, help=help_text, description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3], metavar="SEED",
                       help="task benchmark seeds (evaluation 1 2 3, tuning 11: eqa.seeds); default 1 2 3")
        p.add_argument("--tasks", type=int, default=20, help="tasks per seed (default 20)")
        p.add_argument("--variants", nargs="+", default=None, choices=OVMM_VARIANTS,
                       help="agent variants (default: all of the table)")
        p.add_argument("--max-steps", type=int, default=None,
                       help="cap on each task's step budget (default: the task's own, 6*sqrt(floor area))")
        p.add_argument("--runner", choices=("fleet", "cores"), default="fleet",
                       help="fleet: every service as its own process over Zenoh (default); cores: the services' "
                            "step functions in this process, one episode after the other (eqa_app.task_cores: the "
                            "same trace for the same episode id, several times cheaper)")
        p.add_argument("--robots", type=int, default=2, help="simulated robots run in parallel (default 2)")
        p.add_argument("--scorers", type=int, default=1, help="scorer replicas (default 1)")
        p.add_argument("--out", default="var/bench/tasks", help="results directory (default var/bench/tasks)")
        p.add_argument("--ground-truth-detections", action="store_true",
                       help="HELIOS Table 4: the detector reports ground-truth semantics (every visible pixel of a "
                            "requested class, score 1; EQA_DETECTOR_GROUND_TRUTH); results go to <bench>-gt-*")
        p.add_argument("--tasks-from", type=int, default=0, metavar="K",
                       help="skip the first K tasks of each seed (a smaller, disjoint share, e.g. for Table 4)")
        p.add_argument("--summary-only", action="store_true",
                       help="run nothing: the tables of the runs already in --out (tasks not run are left out)")
        p.add_argument("--replay", metavar="DIR", default=None,
                       help="run nothing: rebuild the tables and the failure break-down from the traces exported "
                            "in DIR (<bench>-seed<s>-traces.jsonl), every metric recomputed from the traces")
        if name == "ovmm":
            p.add_argument("--pick-limits", nargs="+", type=_limits, default=list(PICK_LIMITS), metavar="LIMIT",
                           help="pick limits, each enforced in its own runs (default: 1 5 unlimited); a limit left "
                                "out is derived from the unlimited runs post hoc (paper's zeroing rule)")
        p.add_argument("--no-progress", action="store_true", help="no progress bar")
        p.set_defaults(func=cmd)
