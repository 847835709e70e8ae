"""Scaling out on one machine: episodes/min with 1 and with 2 instances of every service, exactly-once checked,
and the CPU each service spends per step (the per-host throughput model of docs/deployment.md, "Sizing a fleet").

For each configuration (``--instances 1,2``: processes of sim, mapper, planner, stopper; scorer replicas = the
same number) the real fleet runs as separate processes over Zenoh with a private Redis, and ``--robots``
simulated robots run ``--episodes`` full-length episodes of ``--steps`` steps (stop rule ``max_steps``, generated
houses, 320x240, recording off). Configurations alternate ``--rounds`` times (A B A B ...) so that the
machine's load drifts over both alike. Per run:

* episodes/min = episodes ended / wall minutes from the first start to the last end;
* exactly once (tests/support/exactly_once.py): each step integrated, decided and planned once, none skipped;
* CPU seconds per step of each service = the sum over its processes of user+system time (``/proc``) during
  the run / steps run. 1 / that = steps per second one core of that service sustains; the service with the
  highest CPU per step saturates first.

    python -m eqa_app.benches.fleet_scale [--instances 1,2] [--robots 4] [--episodes 12] [--steps 8] [--rounds 2]

``--trees OLD,NEW`` compares source trees instead (e.g. git worktrees at two commits): each round runs this
script of each tree in turn (OLD NEW OLD NEW ...; ``--instances`` 1 unless given, the tree's own code in its
processes, a private Redis each), and prints episodes/min per tree and round, the NEW/OLD ratio of each round
(both measured back to back under the same load) and its median, and the load average before each run.

    python -m eqa_app.benches.fleet_scale --trees /work/wt-old,/work/wt-new --robots 4 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from eqa import keys
from eqa.launcher import PIPELINE, Fleet, free_port
from eqa.messages import EpisodeEnd, EpisodeStart, Question, StopConfig
from eqa.settings import Settings
from eqa_app.benches import harness

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")
harness.use_test_support()
from support.exactly_once import Ends, StepLedger  # noqa: E402

RESULTS = harness.RESULTS / "fleet_scale.json"
TICK = os.sysconf("SC_CLK_TCK")
QUESTIONS = [("gen-00001", "Is there a bed in the bedroom?", ["Yes", "No"]),
             ("gen-00002", "Where is the sofa? A) bedroom B) living room", ["bedroom", "living room"]),
             ("gen-00003", "Is there a toilet in the bathroom?", ["Yes", "No"])]


def cpu_seconds(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / TICK


def run_config(n: int, args: argparse.Namespace, redis_url: str, root: Path) -> dict[str, Any]:
    data = root / f"var-{n}"
    settings = Settings(data_dir=data, redis_url=redis_url, zenoh_listen=[], zenoh_connect=[], record=False,
                        sim_width=320, sim_height=240, step_resend_s=20.0, log_level="WARNING")
    (data / "scenes").mkdir(parents=True, exist_ok=True)
    shutil.copytree(root / "scenes", data / "scenes", dirs_exist_ok=True)
    instances = {s: n for s in ("sim", "mapper", "planner", "stopper")}
    watch = Ends()
    ledger = StepLedger()
    robots = [f"scale{i}" for i in range(args.robots)]
    with Fleet(settings, services=PIPELINE, scorers=n, instances=instances, restart=False) as fleet:
        bus = fleet.hub
        ledger.subscribe(bus)
        bus.subscribe(keys.any_robot(keys.EPISODE_END), EpisodeEnd, watch)
        time.sleep(1.0)
        cpu0 = {c.instance: cpu_seconds(c.proc.pid) for c in fleet.children if c.proc}
        starts = []
        for i in range(args.episodes):
            scene, text, choices = QUESTIONS[i % len(QUESTIONS)]
            q = Question(text=text, choices=choices, scene=scene)
            starts.append(EpisodeStart(episode_id=f"scale-{n}-{i}-{int(time.time())}", robot=robots[i % len(robots)],
                                       question=q, max_steps=args.steps, stop=StopConfig(rule="max_steps"),
                                       seed=1000 + i, record=False))
        free = list(robots)
        pending = list(starts)
        running: dict[str, EpisodeStart] = {}
        t0 = time.monotonic()
        bar = tqdm(total=len(starts), desc=f"{n} instance(s) of every service", leave=False)
        last_end = time.monotonic()
        while pending or running:
            while free and pending:
                st = pending.pop(0).model_copy(update={"robot": free.pop(0)})
                running[st.episode_id] = st
                bus.publish(keys.stream(st.robot, keys.EPISODE_START), st)
            time.sleep(0.05)
            with watch.lock:
                done = [e for e in running if e in watch.ends]
            for eid in done:
                free.append(running.pop(eid).robot)
                bar.update(1)
                last_end = time.monotonic()
            if time.monotonic() - last_end > args.timeout:
                raise RuntimeError(f"no episode ended for {args.timeout} s with {n} instance(s)")
        wall = time.monotonic() - t0
        bar.close()
        cpu = defaultdict(float)
        for c in fleet.children:
            if c.proc:
                cpu[c.service] += cpu_seconds(c.proc.pid) - cpu0.get(c.instance, 0.0)
    ids = {s.episode_id for s in starts}
    steps_run = sum(watch.ends[e].steps for e in ids)
    problems = ledger.problems({e: watch.ends[e].steps for e in ids})
    return {
        "instances": n, "episodes": len(ids), "steps": steps_run, "wall_s": round(wall, 2),
        "episodes_per_min": round(len(ids) / wall * 60, 2), "steps_per_s": round(steps_run / wall, 2),
        "failed": sorted(e for e in ids if watch.ends[e].state != "stopped"),
        "exactly_once_problems": problems[:20], "n_problems": len(problems),
        "cpu_s_per_step": {s: round(v / max(steps_run, 1), 4) for s, v in sorted(cpu.items())},
    }


def _tree_command(tree: Path) -> list[str] | None:
    """How this benchmark of source tree ``tree`` starts: a module of its application package, or the script of a
    tree that kept its benchmarks under ``bench/``; None when it has neither."""
    if (tree / "eqa_app" / "benches" / "fleet_scale.py").is_file():
        return harness.command("fleet_scale")
    if (tree / "bench" / "eqa_app/benches/fleet_scale.py").is_file():
        return [sys.executable, str(tree / "bench" / "eqa_app/benches/fleet_scale.py")]
    return None


def compare_trees(trees: list[Path], args: argparse.Namespace) -> int:
    """Run this benchmark of each tree in turn, ``--rounds`` times; one robot fleet per run (see the docstring)."""
    for t in trees:
        if _tree_command(t) is None:
            print(f"error: {t} has no eqa_app/benches/fleet_scale.py or eqa_app/benches/fleet_scale.py (give source "
                  f"trees, e.g. git worktrees)", file=sys.stderr)
            return 2
    instances = args.instances if args.instances != "1,2" else "1"
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="eqa-trees-") as tmp:
        for r in range(args.rounds):
            for t in trees:
                out = Path(tmp) / f"run-{r}-{t.name}.json"
                load = os.getloadavg()[0]
                cmd = [*(_tree_command(t) or []), "--instances", instances,
                       "--robots", str(args.robots), "--episodes", str(args.episodes), "--steps", str(args.steps),
                       "--rounds", "1", "--timeout", str(args.timeout), "--out", str(out)]
                env = {**os.environ, "PYTHONPATH": str(t)}
                print(f"round {r}: {t} (load average {load:.1f}) ...", flush=True)
                subprocess.run(cmd, cwd=t, env=env, check=True, stdout=subprocess.DEVNULL)
                res = json.loads(out.read_text())["runs"][0]
                res.update(tree=str(t), round=r, loadavg_before=round(load, 2))
                runs.append(res)
                print(f"  {res['episodes_per_min']:.1f} episodes/min, {res['steps_per_s']:.1f} steps/s, "
                      f"not once {res['n_problems']}, failed {len(res['failed'])}, CPU ms per step: "
                      + ", ".join(f"{k} {v * 1000:.0f}" for k, v in res["cpu_s_per_step"].items()), flush=True)
    base = str(trees[0])
    print(f"\nepisodes/min, {args.robots} robots, {args.episodes} episodes x {args.steps} steps, 320x240, "
          f"{instances} instance(s) per service")
    for t in trees:
        vals = [x["episodes_per_min"] for x in runs if x["tree"] == str(t)]
        print(f"  {t!s:40s} " + "  ".join(f"{v:6.1f}" for v in vals) + f"   median {np.median(vals):.1f}")
    for t in trees[1:]:
        ratios = [n["episodes_per_min"] / o["episodes_per_min"] for o, n in zip(
            [x for x in runs if x["tree"] == base], [x for x in runs if x["tree"] == str(t)], strict=True)]
        print(f"  ratio {t.name}/{trees[0].name} per round (back to back): "
              + ", ".join(f"{q:.2f}" for q in ratios) + f"; median {np.median(ratios):.2f}")
    summary = {"command": "python -m eqa_app.benches.fleet_scale " + " ".join(sys.argv[1:]), "cores": os.cpu_count(),
               "loadavg_at_end": [round(x, 2) for x in os.getloadavg()], "runs": runs}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2))
    print(f"written: {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = harness.parser(__doc__)
    p.add_argument("--instances", default="1,2", help="comma-separated instance counts to compare (default 1,2)")
    p.add_argument("--robots", type=int, default=4)
    p.add_argument("--episodes", type=int, default=12, help="episodes per run")
    p.add_argument("--steps", type=int, default=8, help="steps per episode")
    p.add_argument("--rounds", type=int, default=2, help="alternations of the configurations")
    p.add_argument("--timeout", type=float, default=120.0, help="fail when no episode ends for this long")
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--trees", default="", help="comma-separated source trees to compare (see above)")
    args = p.parse_args(argv)
    if not (1 <= args.robots <= 64 and 1 <= args.episodes <= 10_000 and 1 <= args.steps <= 1000
            and 1 <= args.rounds <= 100):
        p.error("1 <= robots <= 64, 1 <= episodes <= 10000, 1 <= steps <= 1000, 1 <= rounds <= 100")
    if args.trees:
        if args.out == RESULTS:
            args.out = RESULTS.with_name("fleet_trees.json")
        return compare_trees([Path(t) for t in args.trees.split(",") if t], args)
    counts = [int(x) for x in args.instances.split(",")]
    redis = shutil.which("redis-server")
    if redis is None:
        print("error: redis-server is not installed (apt-get install redis-server)", file=sys.stderr)
        return 2
    from services.sim.library import load_or_generate

    with tempfile.TemporaryDirectory(prefix="eqa-scale-") as tmp:
        root = Path(tmp)
        for scene, _, _ in QUESTIONS:
            load_or_generate(scene, root / "scenes")
        port = free_port()
        proc = subprocess.Popen([redis, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly",
                                 "no", "--dir", tmp], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        runs = []
        try:
            time.sleep(0.5)
            for r in range(args.rounds):
                for n in counts:
                    res = run_config(n, args, f"redis://127.0.0.1:{port}/{len(runs) % 16}", root)
                    res["round"] = r
                    runs.append(res)
                    print(json.dumps(res), flush=True)
        finally:
            proc.terminate()
            proc.wait(timeout=10)
    load = os.getloadavg()
    summary = {"command": "python -m eqa_app.benches.fleet_scale " + " ".join(argv or sys.argv[1:]),
               "cores": os.cpu_count(), "loadavg_at_end": [round(x, 2) for x in load], "runs": runs}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2))
    print(f"\n{'instances':>9} {'episodes/min':>12} {'steps/s':>8} {'not once':>8}  CPU per step per service")
    for r in runs:
        per = ", ".join(f"{s} {v * 1000:.0f} ms" for s, v in r["cpu_s_per_step"].items())
        print(f"{r['instances']:>9} {r['episodes_per_min']:>12.1f} {r['steps_per_s']:>8.1f} "
              f"{r['n_problems']:>8}  {per}")
    print(f"(2 cores shared with other work; load average at the end {load[0]:.1f}: timings are noisy)")
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
