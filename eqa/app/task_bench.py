"""``eqa bench ovmm`` and ``eqa bench objectnav``: HELIOS Tables 1, 2 (and 4's protocol) through the real services.

Each task of the task benchmark of a seed (:func:`services.sim.tasks.task_benchmark`; the tuning seed 11 and
the evaluation seeds 1, 2, 3 of :mod:`eqa.seeds`) runs as a task episode on a real fleet (sim, mapper, scorer
with the detector, planner, stopper as processes over Zenoh), once per agent variant:

* ``ovmm`` (Table 1): pick-and-place tasks x ``trusting`` / ``no_global`` / ``helios``, with unlimited pick
  attempts. The 1-pick and 5-pick columns are derived from the same runs by the paper's rule ("if the agent
  exceeds the limit, we set all metrics for that episode to 0"): the planner's behaviour does not depend on the
  limit until the limit is reached, so a run that used at most L attempts is exactly the run with limit L, and a
  run that used more scores 0 with limit L.
* ``objectnav`` (Table 2): find-object tasks x the HELIOS stop decision (``helios``: stop only when Psi >= tau_g
  after looking again) against stopping on the first confident detection (``trusting``); SR and SPL.

Metrics come from the simulator's ground truth (``EpisodeEnd.metrics``); means with standard errors
(``sqrt(p (1 - p) / n)`` for rates, the sample SE for SPL) and paired comparisons of each variant against
``helios`` on the same tasks (wins / losses, exact two-sided sign test). Results are appended to a JSON-lines
file per benchmark and seed and reused when the same task, variant and step budget come again.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from eqa import keys
from eqa.app.evaluation import sign_test_p as sign_test
from eqa.messages import (
    EpisodeCancel,
    EpisodeEnd,
    EpisodeStart,
    ErrorReply,
    Goal,
    Question,
    StopConfig,
    Task,
    new_id,
)
from eqa.seeds import seed_role
from eqa.settings import Settings

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


def task_seed(task_id: str) -> int:
    return int.from_bytes(hashlib.sha256(task_id.encode()).digest()[:4], "little") & 0x7FFFFFFF


@dataclass
class TaskResult:
    task_id: str
    kind: str
    variant: str
    max_steps: int
    metrics: dict[str, float]
    state: str
    reason: str
    seconds: float

    def key(self) -> tuple[str, str, int]:
        return (self.task_id, self.variant, self.max_steps)


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


def run_tasks(settings: Settings, jobs: list[tuple[Task, str, int]], robots: int = 2, scorers: int = 1,
              step_timeout_s: float = 300.0, progress: bool = True,
              on_result: Callable[[TaskResult], None] | None = None) -> list[TaskResult]:
    """Run ``(task, variant, max_steps)`` jobs through a fleet over ``robots`` simulated robots; ``on_result`` is
    called as each one ends (so an interrupted benchmark keeps what it ran)."""
    from eqa.launcher import PIPELINE, Fleet

    if not jobs:
        return []
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
        pending = list(reversed(jobs))
        free = list(s.robots)
        running: dict[str, tuple[str, Task, str, int, float, float]] = {}
        while pending or running:
            while free and pending:
                robot = free.pop(0)
                task, variant, steps = pending.pop()
                eid = new_id("task")
                q = Question(text=task.text, scene=task.scene, start_pose=task.start_pose, max_steps=steps)
                start = EpisodeStart(episode_id=eid, robot=robot, question=q, stop=StopConfig(rule="max_steps"),
                                     max_steps=steps, seed=task_seed(task.id), record=False, task=task,
                                     ablation=variant)  # type: ignore[arg-type]
                bus.publish(keys.stream(robot, keys.EPISODE_START), start)
                now = time.monotonic()
                running[eid] = (robot, task, variant, steps, now, now)
            try:
                msg = inbox.get(timeout=1.0)
            except queue.Empty:
                msg = None
            now = time.monotonic()
            if msg is not None and msg.episode_id in running:
                robot, task, variant, steps, t0, _ = running[msg.episode_id]
                running[msg.episode_id] = (robot, task, variant, steps, t0, now)
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
                                          state, reason, now - t0))
                    if on_result is not None:
                        on_result(out[-1])
                    if bar is not None:
                        bar.update(1)
            for eid, (robot, task, variant, steps, t0, seen) in list(running.items()):
                if now - seen > step_timeout_s:
                    why = f"no progress for {step_timeout_s:.0f} s"
                    bus.publish(keys.stream(robot, keys.EPISODE_CANCEL), EpisodeCancel(episode_id=eid, reason=why))
                    del running[eid]
                    free.append(robot)
                    out.append(TaskResult(task.id, task.kind, variant, steps, {}, "failed", why, now - t0))
                    if on_result is not None:
                        on_result(out[-1])
                    if bar is not None:
                        bar.update(1)
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


def summarise(kind: str, results: list[TaskResult], variants: tuple[str, ...]) -> dict[str, Any]:
    """Tables (module doc) as data: per variant (and pick limit for ovmm) mean and SE of each metric, n, and
    the paired comparison of SR against ``helios``."""
    by = {v: {r.task_id: r for r in results if r.variant == v} for v in variants}
    common = sorted(set.intersection(*(set(d) for d in by.values()))) if by else []
    table: dict[str, Any] = {"n": len(common), "rows": []}
    for v in variants:
        runs = [by[v][t] for t in common]
        if kind == "pick_place":
            for limit in PICK_LIMITS:
                ms = [limited(r.metrics, limit) for r in runs]
                row = {"variant": v, "picks": limit or "unlimited"}
                for k in OVMM_METRICS:
                    row[k] = mean_se([m[k] for m in ms])
                table["rows"].append(row)
        else:
            row = {"variant": v, "SR": mean_se([r.metrics.get("SR", 0.0) for r in runs]),
                   "SPL": mean_se([r.metrics.get("SPL", 0.0) for r in runs], binary=False)}
            table["rows"].append(row)
    cmp = []
    if "helios" in by:
        for v in variants:
            if v == "helios":
                continue
            for limit in (PICK_LIMITS if kind == "pick_place" else (None,)):
                def sr(r: TaskResult, lim: int | None = limit) -> float:
                    return limited(r.metrics, lim)["SR"] if kind == "pick_place" else r.metrics.get("SR", 0.0)

                wins = sum(1 for t in common if sr(by["helios"][t]) > sr(by[v][t]))
                losses = sum(1 for t in common if sr(by["helios"][t]) < sr(by[v][t]))
                cmp.append({"helios_vs": v, "picks": limit or "unlimited", "helios_wins": wins, "helios_losses": losses,
                            "sign_test_p": sign_test(wins, losses)})
    table["paired_SR"] = cmp
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
            lines.append(f"{row['picks']!s:<10} {row['variant']:<10} {cells}")
    else:
        lines.append(f"{'variant':<10} {'SR':>13} {'SPL':>13}")
        for row in table["rows"]:
            lines.append(f"{row['variant']:<10} {100 * row['SR'][0]:6.1f} ± {100 * row['SR'][1]:4.1f} "
                         f"{100 * row['SPL'][0]:6.1f} ± {100 * row['SPL'][1]:4.1f}")
    for c in table["paired_SR"]:
        lines.append(f"paired SR, helios vs {c['helios_vs']} ({c['picks']} picks): helios better on "
                     f"{c['helios_wins']}, worse on {c['helios_losses']} tasks, sign test p = {c['sign_test_p']:.3f}")
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


def cmd(args: argparse.Namespace) -> int:
    from eqa.app.cli import check_scorer, load_settings
    from eqa.service import setup_logging
    from services.sim.tasks import task_benchmark

    settings = load_settings()
    if args.ground_truth_detections:
        settings = settings.model_copy(update={"detector_ground_truth": True})
    check_scorer(settings)
    setup_logging("WARNING", "eqa-bench")
    kind = "pick_place" if args.bench_command == "ovmm" else "find_object"
    variants = tuple(args.variants or (OVMM_VARIANTS if kind == "pick_place" else OBJECTNAV_VARIANTS))
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    gt = bool(args.ground_truth_detections)
    tag = args.bench_command + ("-gt" if gt else "")
    report: dict[str, Any] = {"benchmark": args.bench_command, "seeds": {}, "max_steps": args.max_steps,
                              "detections": GROUND_TRUTH if gt else SIMULATED}
    pooled: list[TaskResult] = []
    for seed in args.seeds:
        n_pp, n_fo = (args.tasks, 0) if kind == "pick_place" else (0, args.tasks)
        bench = task_benchmark(seed, pick_place=n_pp, find=n_fo, scenes_dir=settings.scenes_path,
                               progress=not args.no_progress)
        tasks = bench.of_kind(kind)
        if args.tasks_from and args.tasks_from < len(tasks):
            tasks = tasks[args.tasks_from:]
        path = out_dir / f"{tag}-seed{seed}.jsonl"
        done = load_results(path)
        jobs = []
        for t in tasks:
            steps = min(t.max_steps or 1, args.max_steps) if args.max_steps else (t.max_steps or 1)
            for v in variants:
                if (t.id, v, steps) not in done:
                    jobs.append((t, v, steps))
        def keep(r: TaskResult, path: Path = path, done: dict[tuple[str, str, int], TaskResult] = done) -> None:
            with path.open("a") as f:
                f.write(json.dumps(r.__dict__) + "\n")
            done[r.key()] = r

        if not args.summary_only:
            run_tasks(settings, jobs, robots=args.robots, scorers=args.scorers, progress=not args.no_progress,
                      on_result=keep)
        wanted = {(t.id, v, min(t.max_steps or 1, args.max_steps) if args.max_steps else (t.max_steps or 1))
                  for t in tasks for v in variants}
        results = [r for k, r in done.items() if k in wanted]
        table = summarise(kind, results, variants)
        secs = [r.seconds for r in results]
        report["seeds"][str(seed)] = {"role": seed_role(seed), "table": table,
                                      "failed_runs": sum(1 for r in results if r.state == "failed"),
                                      "seconds_per_episode": (sum(secs) / len(secs)) if secs else None}
        print(format_table(kind, table, seed, args.max_steps, gt), flush=True)
        pooled += [TaskResult(**{**r.__dict__, "task_id": f"{seed}:{r.task_id}"}) for r in results]
    if len(args.seeds) > 1:
        table = summarise(kind, pooled, variants)
        report["pooled"] = {"seeds": args.seeds, "table": table}
        print(format_table(kind, table, "+".join(map(str, args.seeds)), args.max_steps, gt), flush=True)
    last = report.get("pooled") or report["seeds"][str(args.seeds[-1])]
    title = (f"{tag}, seeds {'+'.join(map(str, args.seeds))}, n = {last['table']['n']} tasks; "
             f"{'ground-truth detections' if gt else 'simulated detector, not a detector'}")
    plot(kind, last["table"], title, out_dir / f"{tag}.png")
    (out_dir / f"{tag}.json").write_text(json.dumps(report, indent=1) + "\n")
    print(f"results: {out_dir / (tag + '.json')} (runs: {out_dir}/{tag}-seed*.jsonl)")
    return 0


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
        p.add_argument("--no-progress", action="store_true", help="no progress bar")
        p.set_defaults(func=cmd)
