"""The demo task of ``eqa task`` (no instruction): a task typical of the tuning seed 11, chosen by a rule written
before any run and re-runnable after every change of the agent.

The rule (:func:`pick_demo`): run ``eqa task``'s own configuration (agent helios, the default pick limit
``EQA_HELIOS_PICK_ATTEMPTS``, the benchmark's step budget and draws) on the first :data:`DEMO_POOL`
pick-and-place tasks of seed 11 (``eqa bench ovmm --seeds 11 --tasks 24``); the majority outcome (succeeded or
failed; a tie counts as failed) and, among runs with that outcome, the most common first-failure cause
(:func:`eqa.task_traces.failure_cause`; ties: the cause met first in benchmark order) make the typical outcome. The
demo is the first task, in benchmark order, with the typical outcome whose step budget is at most the pool's
median (the lower one): a typical outcome with a typical run time (the seed's first task is in its largest house,
145 steps).

Re-pick after the agent changed::

    nice -n 10 python -m eqa_app.task_demo          # ~10 min on 2 cores, writes bench/results/task-demo-seed11.jsonl

It prints the chosen task, its outcome and the lines to set in :mod:`eqa_app.task` (``DEMO_TASK_ID``,
``DEMO_OUTCOME``, ``DEMO_SUCCESSES``);
``tests/tasks/test_task_cli.py`` checks that the constant is the rule's pick on the committed results. The demo
runs with the benchmark's seed and draws of that task (:func:`demo_draws`), so ``eqa task`` prints the outcome the
rule saw (simulated detector, not a real detector).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEMO_POOL = 24  # the tuning seed's pick-and-place tasks the demo is chosen among (its tuning table's)
RESULTS = Path(__file__).resolve().parent.parent / "bench" / "results" / "task-demo-seed11.jsonl"


@dataclass(frozen=True)
class DemoRun:
    """One run of the rule: the task, its step budget, whether it succeeded and its first failure's cause."""

    task_id: str
    max_steps: int
    success: bool
    cause: str
    text: str = ""


def typical_outcome(runs: list[DemoRun]) -> tuple[bool, str]:
    """The majority outcome (a tie counts as failed) and the most common cause among the runs with it (ties:
    the cause met first)."""
    if not runs:
        raise ValueError("no runs to choose a demo from")
    wins = sum(r.success for r in runs)
    success = wins > len(runs) - wins
    causes = Counter(r.cause for r in runs if r.success == success)
    top = max(causes.values())
    cause = next(r.cause for r in runs if r.success == success and causes[r.cause] == top)
    return success, cause


def pick_demo(runs: list[DemoRun]) -> DemoRun:
    """The demo among ``runs`` (benchmark order) by the module's rule."""
    success, cause = typical_outcome(runs)
    budgets = sorted(r.max_steps for r in runs)
    median = budgets[(len(budgets) - 1) // 2]
    typical = [r for r in runs if r.success == success and r.cause == cause]
    return next((r for r in typical if r.max_steps <= median), typical[0])


def demo_draws(task_id: str, max_steps: int) -> tuple[int, str]:
    """The seed and draw key of the benchmark's in-process run of a task (:func:`eqa_app.task_cores.
    cores_episode_id`, :func:`eqa_app.task_results.task_seed`): the demo meets the simulated detector's draws the
    rule's run met."""
    from eqa_app.task_cores import cores_episode_id
    from eqa_app.task_results import task_seed

    return task_seed(task_id), cores_episode_id(task_id, max_steps)


def load_runs(path: Path = RESULTS) -> list[DemoRun]:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [DemoRun(r["task_id"], int(r["max_steps"]), bool(r["success"]), r["cause"], r.get("text", "")) for r in rows]


def run_pool(settings: Any, pool: int = DEMO_POOL, progress: bool = True) -> list[DemoRun]:
    """Run ``eqa task``'s configuration on the seed's first ``pool`` pick-and-place tasks in process."""
    from eqa.seeds import TUNING_SEED
    from eqa.task_traces import task_outcome
    from eqa_app.task_cores import run_tasks_cores
    from services.sim.tasks import task_benchmark

    tasks = task_benchmark(TUNING_SEED, pick_place=pool, find=0, scenes_dir=settings.scenes_path).tasks
    limit = settings.helios_pick_attempts or None
    jobs = [(t, "helios", t.max_steps or 0, limit) for t in tasks]
    out = []
    for r in run_tasks_cores(settings, jobs, progress=progress):
        o = task_outcome(r.kind, r.metrics, r.state, r.reason, r.max_steps, r.max_steps, r.trace)
        out.append(DemoRun(r.task_id, r.max_steps, bool(o["success"]), o["cause"], o["text"]))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m eqa_app.task_demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=RESULTS, help=f"results file (default {RESULTS})")
    p.add_argument("--pool", type=int, default=DEMO_POOL, help=f"tasks (default {DEMO_POOL})")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    from eqa.settings import Settings

    runs = run_pool(Settings(), args.pool, not args.no_progress)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("".join(json.dumps(vars(r)) + "\n" for r in runs))
    success, cause = typical_outcome(runs)
    demo = pick_demo(runs)
    wins = sum(r.success for r in runs)
    print(f"{wins} of {len(runs)} succeeded; typical outcome: {'succeeded' if success else 'failed'} ({cause}, "
          f"{sum(r.cause == cause for r in runs)} runs)")
    print(f"demo: {demo.task_id} ({demo.max_steps} steps): {demo.text}")
    print(f"set in eqa_app/task.py:\nDEMO_TASK_ID = {demo.task_id!r}\nDEMO_OUTCOME = {demo.text!r}\n"
          f"DEMO_SUCCESSES = ({wins}, {len(runs)})")
    print(f"results: {args.out}")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
