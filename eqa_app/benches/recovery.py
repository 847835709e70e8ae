"""Time to recover: from a kill -9 of one service mid-episode to the episode's next step, and from an instance
joining (robots move to it) to the next step of each robot that moved.

The real fleet runs as separate processes over Zenoh with a private Redis (one process of sim, mapper,
planner and stopper, ``--scorers`` scorer replicas; the launcher restarts a killed process, as in production).
Each round of each service: an episode runs (stop rule ``max_steps``, generated house, ``--width`` x
``--height``); after ``--warmup`` steps, at a random moment within a step, the service's process gets SIGKILL;
the time until a frame of a step not seen before the kill is the recovery time. Then the episode is cancelled
and the next round begins once the restarted process is up. The join: ``--robots`` episodes run at once, a
second instance of ``--join-service`` starts, and for each robot whose owner changed the time from the
newcomer's liveliness token to the robot's next new step is taken.

Exactly once is checked over every episode (tests/support/exactly_once.py: each step integrated, decided and planned
once, none skipped). ``EQA_STEP_RESEND_S`` stays at its default (30 s): what is measured is the re-drive on
membership changes, not the resend timer.

``--standby on,off`` (the default) runs the whole measurement twice in one run, with the launcher's warm
standbys (``EQA_STANDBY``, :mod:`eqa.standby`: a killed process is replaced by a pre-started, already imported
one) and without them (a new process is started); with standbys a round starts only once every service has a
ready standby again.

    python -m eqa_app.benches.recovery [--rounds 3] [--services sim,mapper,planner,stopper,vlm_scorer] [--no-join]
                                   [--standby on,off]

Prints one line per round, then median/p90/min/max per case and mode, and writes ``bench/results/recovery.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

from eqa import keys, sharding
from eqa.launcher import PIPELINE, STEADY_S, Fleet, free_port
from eqa.messages import EpisodeCancel, EpisodeStart, Frame, Question, StopConfig
from eqa.settings import Settings
from eqa_app.benches import harness

harness.use_test_support()
from support.exactly_once import StepLedger, wait_on  # noqa: E402
from support.scorer import stop_process  # noqa: E402

RESULTS = harness.RESULTS / "recovery.json"
SCENE = "gen-00001"
SERVICES = ("sim", "mapper", "planner", "stopper", "vlm_scorer")
STATEFUL = ("sim", "mapper", "planner", "stopper")


class Frames:
    """The steps the sim publishes (robot -> episode -> step -> first time seen), from the bus."""

    def __init__(self) -> None:
        self.first: dict[str, dict[int, float]] = {}
        self.cond = threading.Condition()

    def __call__(self, _key: str, msg: Frame) -> None:
        with self.cond:
            steps = self.first.setdefault(msg.episode_id, {})
            steps.setdefault(msg.step, time.monotonic())
            self.cond.notify_all()

    def last(self, episode_id: str) -> int:
        with self.cond:
            return max(self.first.get(episode_id, {}) or [-1])

    def wait(self, pred, timeout: float) -> bool:
        return wait_on(self.cond, pred, timeout)

    def new_step_after(self, episode_id: str, step: int, t0: float) -> float | None:
        with self.cond:
            times = [t for s, t in self.first.get(episode_id, {}).items() if s > step]
        return min(times) - t0 if times else None


class Ups:
    """When instances' liveliness tokens appear (service -> times), from the bus."""

    def __init__(self) -> None:
        self.times: dict[str, list[float]] = {}
        self.lock = threading.Lock()

    def __call__(self, service: str, _instance: str, up: bool) -> None:
        if up:
            with self.lock:
                self.times.setdefault(service, []).append(time.monotonic())

    def first_after(self, service: str, t0: float) -> float | None:
        with self.lock:
            later = [t for t in self.times.get(service, []) if t > t0]
        return min(later) - t0 if later else None


def _start(robot: str, eid: str, max_steps: int, seed: int) -> EpisodeStart:
    q = Question(text="Is there a bed in the bedroom?", choices=["Yes", "No"], scene=SCENE)
    return EpisodeStart(episode_id=eid, robot=robot, question=q, max_steps=max_steps,
                        stop=StopConfig(rule="max_steps"), seed=seed, record=False)


def _summary(xs: list[float]) -> dict[str, float | int]:
    if not xs:
        return {"n": 0}
    return {"n": len(xs), "median_s": round(statistics.median(xs), 3),
            "p90_s": round(float(np.percentile(xs, 90)), 3), "min_s": round(min(xs), 3), "max_s": round(max(xs), 3)}


def kill_rounds(fleet: Fleet, frames: Frames, ups: Ups, service: str, args: argparse.Namespace,
                rng: random.Random, episodes: dict[str, int]) -> tuple[list[float], list[float]]:
    """Recovery times of each round, and the times from the kill to the restarted process's liveliness token."""
    bus = fleet.hub
    out: list[float] = []
    restarts: list[float] = []
    for r in range(args.rounds):
        fleet.wait_alive(timeout=args.timeout)
        fleet.wait_standbys(timeout=args.timeout)  # the kill finds a warm standby (no-op with standbys off)
        # a process killed within STEADY_S of coming up counts as a crash loop and backs off: kill a steady one
        for c in fleet.children:
            if c.service == service and c.up_at is not None:
                time.sleep(max(0.0, c.up_at + STEADY_S - time.monotonic()))
        eid = f"rec-{service}-{r}-{os.getpid()}-{time.time_ns()}"
        bus.publish(keys.stream("robot0", keys.EPISODE_START), _start("robot0", eid, args.steps, r))
        if not frames.wait(lambda eid=eid: frames.last(eid) >= args.warmup, args.timeout):
            raise RuntimeError(f"{service} round {r}: the episode did not reach step {args.warmup}")
        # a random moment within a step: right after a frame, while the step is computed, just before the goal
        t_frame = frames.first[eid][frames.last(eid)]
        step_s = (t_frame - frames.first[eid][0]) / max(1, frames.last(eid))
        time.sleep(rng.uniform(0.0, step_s))
        last = frames.last(eid)
        names = [c.instance for c in fleet.children if c.service == service]
        index = names.index(sharding.owner("robot0", names)) if service in STATEFUL else 0  # robot0's instance
        child = [c for c in fleet.children if c.service == service][index]
        old_pid = child.proc.pid if child.proc is not None else None
        t_kill = time.monotonic()
        fleet.kill(service, index)
        ok = frames.wait(lambda eid=eid, last=last: frames.last(eid) > last, args.timeout)
        rec = frames.new_step_after(eid, last, t_kill) if ok else None
        deadline = time.monotonic() + args.timeout  # the launcher restarts it (a new process), then it is up
        while (child.proc is None or child.proc.pid == old_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        fleet.wait_alive(timeout=max(1.0, deadline - time.monotonic()), children=[child])
        up = ups.first_after(service, t_kill)
        if up is not None:
            restarts.append(up)
        bus.publish(keys.stream("robot0", keys.EPISODE_CANCEL),
                    EpisodeCancel(episode_id=eid, reason="bench round over"))
        episodes[eid] = frames.last(eid)
        if rec is None:
            print(f"  {service} round {r + 1}/{args.rounds}: no new step within {args.timeout:.0f} s", flush=True)
            out.append(float("inf"))
        else:
            print(f"  {service} round {r + 1}/{args.rounds}: killed at step {last} (step {step_s:.2f} s), next step "
                  f"after {rec:.2f} s (restarted process up after {'-' if up is None else f'{up:.2f} s'})",
                  flush=True)
            out.append(rec)
        time.sleep(1.0)  # the cancel reaches every service before the next episode on the same robot
    return out, restarts


def join_rounds(fleet: Fleet, frames: Frames, args: argparse.Namespace, episodes: dict[str, int],
                root: Path) -> list[float]:
    out: list[float] = []
    for r in range(args.rounds):
        fleet.wait_alive(timeout=args.timeout)
        out += _join_round(fleet, frames, args, episodes, root, r)
    return out


def _join_round(fleet: Fleet, frames: Frames, args: argparse.Namespace, episodes: dict[str, int], root: Path,
                r: int) -> list[float]:
    bus = fleet.hub
    robots = [f"robot{i}" for i in range(args.robots)]
    service = args.join_service
    ids = {rb: f"join-{r}-{rb}-{os.getpid()}-{time.time_ns()}" for rb in robots}
    for i, rb in enumerate(robots):
        bus.publish(keys.stream(rb, keys.EPISODE_START), _start(rb, ids[rb], args.steps, 100 + i))
    if not frames.wait(lambda: all(frames.last(e) >= args.warmup for e in ids.values()), args.timeout):
        raise RuntimeError(f"join round {r}: the episodes did not reach step {args.warmup}")
    instance = f"{service}-joined-{r}-{os.getpid()}"
    before = {inst for _, inst in bus.alive(keys.alive_service(service), timeout=1.0)}
    moved = sharding.reassigned(robots, before, before | {instance})
    seen = threading.Event()
    t_up: list[float] = []
    last: dict[str, int] = {}

    def on_alive(svc: str, inst: str, up: bool) -> None:
        if svc == service and inst == instance and up and not seen.is_set():
            for rb in robots:
                last[rb] = frames.last(ids[rb])
            t_up.append(time.monotonic())
            seen.set()

    watch = bus.watch_alive(keys.alive_service(service), on_alive)
    log = open(root / f"{instance}.log", "wb")  # noqa: SIM115 - handed to the child
    proc = subprocess.Popen([sys.executable, "-m", f"services.{service}"], env=fleet._child_env(service, instance),
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    out: list[float] = []
    try:
        if not seen.wait(args.timeout):
            raise RuntimeError(f"the joined {service} did not come up")
        frames.wait(lambda: all(frames.last(ids[rb]) > last[rb] for rb in moved), args.timeout)
        for rb in sorted(moved):
            rec = frames.new_step_after(ids[rb], last[rb], t_up[0])
            out.append(float("inf") if rec is None else rec)
            print(f"  join round {r + 1}/{args.rounds}: {rb} moved to {instance}; next step after "
                  f"{'-' if rec is None else f'{rec:.2f} s'}", flush=True)
        if not moved:
            print(f"  join round {r + 1}/{args.rounds}: no robot moved to {instance}", flush=True)
    finally:
        watch.undeclare()
        for rb in robots:
            bus.publish(keys.stream(rb, keys.EPISODE_CANCEL),
                        EpisodeCancel(episode_id=ids[rb], reason="bench round over"))
            episodes[ids[rb]] = frames.last(ids[rb])
        stop_process(proc)
        time.sleep(1.0)
    return out


def main(argv: list[str] | None = None) -> int:
    p = harness.parser(__doc__)
    p.add_argument("--rounds", type=int, default=3, help="kills per service and joins (default 3)")
    p.add_argument("--services", default=",".join(SERVICES), help=f"services to kill (default {','.join(SERVICES)})")
    p.add_argument("--join", action=argparse.BooleanOptionalAction, default=True,
                   help="also measure a join that moves robots (default on)")
    p.add_argument("--join-service", default="planner", choices=STATEFUL, help="the service that gets an instance")
    p.add_argument("--robots", type=int, default=4, help="robots running during a join (default 4)")
    p.add_argument("--steps", type=int, default=60, help="step limit of each episode (default 60)")
    p.add_argument("--warmup", type=int, default=3, help="steps before the kill (default 3)")
    p.add_argument("--scorers", type=int, default=2, help="scorer replicas (default 2)")
    p.add_argument("--instances", type=int, default=1,
                   help="processes of each of sim, mapper, planner, stopper (default 1: a kill waits for the "
                   "restart; 2: the other instance takes the robot over)")
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--timeout", type=float, default=90.0, help="give up on a round after this long (default 90 s)")
    p.add_argument("--seed", type=int, default=11, help="random kill moments (default 11)")
    p.add_argument("--standby", default="on,off",
                   help="launcher warm standbys, one fleet per mode in this order (default on,off)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    services = [s for s in args.services.split(",") if s]
    if any(s not in SERVICES for s in services):
        p.error(f"--services: choose from {', '.join(SERVICES)}")
    modes = [m.strip() for m in args.standby.split(",") if m.strip()]
    if not modes or any(m not in ("on", "off") for m in modes) or len(set(modes)) != len(modes):
        p.error("--standby: on, off or both (on,off)")
    if not (1 <= args.rounds <= 50 and 1 <= args.robots <= 32 and args.warmup + 5 <= args.steps <= 1000
            and 1 <= args.scorers <= 8 and 1 <= args.instances <= 4):
        p.error("1 <= rounds <= 50, 1 <= robots <= 32, warmup + 5 <= steps <= 1000, 1 <= scorers <= 8, "
                "1 <= instances <= 4")
    redis = shutil.which("redis-server")
    if redis is None:
        print("error: redis-server is not installed (apt-get install redis-server)", file=sys.stderr)
        return 2
    from services.sim.library import load_or_generate

    rng = random.Random(args.seed)
    load_start = os.getloadavg()
    results: dict[str, dict[str, list[float]]] = {m: {} for m in modes}
    episodes: dict[str, int] = {}
    ledger = StepLedger()
    with tempfile.TemporaryDirectory(prefix="eqa-recovery-") as tmp:
        root = Path(tmp)
        port = free_port()
        rproc = subprocess.Popen([redis, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly",
                                  "no", "--dir", tmp], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            settings = Settings(data_dir=root / "var", redis_url=f"redis://127.0.0.1:{port}/0", zenoh_listen=[],
                                zenoh_connect=[], record=False, sim_width=args.width, sim_height=args.height,
                                episode_timeout_s=600.0)
            load_or_generate(SCENE, settings.scenes_path)
            for mode in modes:
                print(f"starting the fleet ({args.instances} instance(s) of each stateful service, scorers "
                      f"{args.scorers}, {args.width}x{args.height}, step resend {settings.step_resend_s:g} s, "
                      f"standby {mode}) ...", flush=True)
                with Fleet(settings, services=PIPELINE, scorers=args.scorers,
                           instances=dict.fromkeys(STATEFUL, args.instances),
                           max_restarts=args.rounds * len(services) + 5, standby=mode == "on") as fleet:
                    out = results[mode]
                    frames = Frames()
                    fleet.hub.subscribe(keys.any_robot(keys.SIM_FRAME), Frame, frames)
                    ledger.subscribe(fleet.hub)
                    ups = Ups()
                    fleet.hub.watch_alive(keys.ALIVE_ANY, ups)
                    time.sleep(0.5)
                    for service in services:
                        print(f"kill -9 {service} ({args.rounds} rounds, standby {mode})", flush=True)
                        out[f"kill {service}"], out[f"restart {service}"] = kill_rounds(
                            fleet, frames, ups, service, args, rng, episodes)
                    if args.join:
                        print(f"join of a {args.join_service} instance ({args.rounds} rounds, {args.robots} robots)",
                              flush=True)
                        out[f"join {args.join_service}"] = join_rounds(fleet, frames, args, episodes, root)
                    time.sleep(1.0)
        finally:
            rproc.terminate()
            rproc.wait(timeout=10)
    problems = ledger.problems(episodes)
    summary = {
        "command": "python -m eqa_app.benches.recovery " + " ".join(argv if argv is not None else sys.argv[1:]),
        "instances": args.instances, "scorers": args.scorers, "size": [args.width, args.height],
        "cores": os.cpu_count(), "loadavg_at_start": [round(x, 2) for x in load_start],
        "loadavg_at_end": [round(x, 2) for x in os.getloadavg()], "step_resend_s": 30.0,
        "standby": {m: {k: {**_summary([x for x in v if x != float("inf")]),
                            "lost_rounds": sum(x == float("inf") for x in v), "rounds_s": [round(x, 3) for x in v]}
                        for k, v in cases.items()} for m, cases in results.items()},
        "exactly_once_problems": problems[:20], "n_problems": len(problems), "episodes": len(episodes),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2))
    print(f"\n{'case':<18} {'standby':>7} {'n':>3} {'median':>8} {'p90':>8} {'min':>8} {'max':>8}  seconds (kill, "
          "join: to the episode's next step; restart: from the kill to the restarted process's liveliness token)")
    first = summary["standby"][modes[0]]
    for case in first:
        for mode in modes:
            s = summary["standby"][mode].get(case, {"n": 0, "lost_rounds": 0})
            if s["n"]:
                print(f"{case:<18} {mode:>7} {s['n']:>3} {s['median_s']:>8.2f} {s['p90_s']:>8.2f} {s['min_s']:>8.2f} "
                      f"{s['max_s']:>8.2f}" + (f"  {s['lost_rounds']} round(s) without a new step"
                                               if s["lost_rounds"] else ""))
            else:
                print(f"{case:<18} {mode:>7} {0:>3}  no round recovered")
    print(f"exactly once over {len(episodes)} episodes: {len(problems)} problem(s)" +
          (f": {problems[:5]}" if problems else ""))
    print(f"load average {summary['loadavg_at_start'][0]:.1f} at start, {summary['loadavg_at_end'][0]:.1f} at end "
          f"({os.cpu_count()} cores); written: {args.out}")
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())
