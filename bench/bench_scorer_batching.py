"""Dynamic batching in one scorer replica: steps/s and latency against the number of concurrent robots.

Two replica processes of the tiny random Qwen2-VL (built offline; ``python -m services.vlm_scorer``, one torch
thread each) run side by side: ``off`` with ``EQA_SCORER_BATCH_MAX=1``, ``on`` with batching
(``--batch-max``, ``--window-ms``). For each robot count, ``N`` robots (threads) each send their steps one after
the other (a robot waits for its step's scores before the next, as the mapper does), every robot with its own
question; the same requests go to ``off`` and to ``on`` in alternating rounds, so a load drift hits both alike,
and only one replica works at a time. Printed per robot count and mode: steps/s of the replica, p50 / p95
latency per step, the replica process's CPU time per step (``/proc``; what a saturated replica's steps/s per
core is: the robots' threads share one client process here, so the wall rate is bounded by the client's
turnaround too), and whether every request got the same values from both replicas (byte for byte).

The tiny model is not a real VLM: the figure says what merging the steps of several robots saves in the
replica's per-call work on this CPU (image processing, Python and kernel overheads), not what a GPU serving a
real model would gain.

    python bench/bench_scorer_batching.py [--robots 1 2 4 8 16] [--steps 6] [--rounds 2] [--batch-max 16]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from bench_fleet_scale import cpu_seconds  # noqa: E402

from eqa import keys  # noqa: E402
from eqa.bus import Bus  # noqa: E402
from eqa.launcher import free_port  # noqa: E402
from eqa.messages import Question, ScoreRequest, ScoreResult  # noqa: E402
from eqa.scorer_client import ScorerClient  # noqa: E402
from eqa.settings import Settings  # noqa: E402

QUESTIONS = [
    ("Is the stove in the kitchen turned off?", ["Yes", "No"]),
    ("What color is the sofa in the living room?", ["Blue", "Red", "Green", "White"]),
    ("Where did I leave the black suitcase?", ["bedroom", "hallway", "storage room", "living room"]),
    ("How many chairs are around the dining table?", ["two", "four", "six", "eight"]),
    ("Is the lamp on the nightstand switched on?", ["Yes", "No"]),
    ("Which room has the potted plant?", ["kitchen", "bathroom", "office", "bedroom"]),
    ("Is there a towel hanging in the bathroom?", ["Yes", "No"]),
    ("What is on the kitchen counter next to the sink?", ["a kettle", "a toaster", "a plant", "nothing"]),
]


def _pct(v: list[float], q: float) -> float:
    s = sorted(v)
    return s[min(len(s) - 1, round(q / 100 * (len(s) - 1)))] if s else float("nan")


def _requests(robots: int, steps: int, h: int, w: int) -> list[list[ScoreRequest]]:
    from support.scorer import frame_request

    out = []
    for r in range(robots):
        text, choices = QUESTIONS[r % len(QUESTIONS)]
        q = Question(id=f"q{r}", text=text, choices=choices, scene="s0")
        out.append([frame_request(step=s, h=h, w=w, episode=f"ep{r}", question=q,
                                  seed=r).model_copy(update={"request_id": f"r{r}-s{s}"}) for s in range(steps)])
    return out


def _run(bus: Bus, replica: str, per_robot: list[list[ScoreRequest]], timeout: float, pid: int = 0
         ) -> tuple[float, list[float], dict[str, tuple], float]:
    key = keys.scorer_replica(replica)
    latencies: list[float] = []
    values: dict[str, tuple] = {}

    def robot(reqs: list[ScoreRequest]) -> None:
        for req in reqs:
            t0 = time.perf_counter()
            replies = bus.query(key, req, timeout=timeout, expected=ScoreResult)
            latencies.append((time.perf_counter() - t0) * 1e3)
            res = replies[0][1] if replies else None
            if not isinstance(res, ScoreResult):
                raise RuntimeError(f"{replica}: no result for {req.request_id}: {res}")
            values[req.request_id] = (tuple(res.answer_probs), tuple(res.lsv), res.gsv, res.relevance)

    cpu0 = cpu_seconds(pid) if pid else 0.0
    t0 = time.perf_counter()
    with ThreadPoolExecutor(len(per_robot)) as pool:
        list(pool.map(robot, per_robot))
    wall = time.perf_counter() - t0
    steps = sum(len(r) for r in per_robot)
    cpu = (cpu_seconds(pid) - cpu0) if pid else float("nan")
    return steps / wall, latencies, values, cpu / steps


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="concurrent robot counts")
    ap.add_argument("--steps", type=int, default=6, help="steps per robot per round (default 6)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating off/on rounds per robot count (default 2)")
    ap.add_argument("--batch-max", type=int, default=16, help="EQA_SCORER_BATCH_MAX of the 'on' replica")
    ap.add_argument("--window-ms", type=float, default=0.0, help="EQA_SCORER_BATCH_WINDOW_MS of the 'on' replica")
    ap.add_argument("--size", default="120x160", help="image HxW (default 120x160)")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    if not (all(1 <= r <= 64 for r in args.robots) and 1 <= args.steps <= 100 and 1 <= args.rounds <= 20):
        print("error: robots 1..64, steps 1..100, rounds 1..20", file=sys.stderr)
        return 2

    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    tmp = Path(tempfile.mkdtemp(prefix="bench-scorer-batching-"))
    model_dir = build_tiny_qwen2vl(tmp / "tiny-qwen2vl")
    port = free_port()
    base = Settings(data_dir=tmp / "var", zenoh_listen=["tcp/127.0.0.1:0"],
                    zenoh_connect=[f"tcp/127.0.0.1:{port}"], record=False, scorer_backend="hf",
                    hf_model_path=model_dir, scorer_timeout_s=120)
    hub = base.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{port}"], "zenoh_connect": []})
    env = {**os.environ, **base.env(), "EQA_LOG_LEVEL": "WARNING", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    modes = {"off": {"EQA_SCORER_BATCH_MAX": "1"},
             "on": {"EQA_SCORER_BATCH_MAX": str(args.batch_max), "EQA_SCORER_BATCH_WINDOW_MS": str(args.window_ms)}}
    rows = []
    identical = True
    with Bus(hub, "gateway", "bench") as bus:
        procs = [subprocess.Popen([sys.executable, "-m", "services.vlm_scorer"], cwd=REPO,
                                  env={**env, **extra, "EQA_SCORER_REPLICA": f"b-{m}", "EQA_INSTANCE": f"b-{m}"})
                 for m, extra in modes.items()]
        try:
            if not ScorerClient(bus, base).wait_for_replicas(2, timeout=180):
                print("error: the two replicas did not come up", file=sys.stderr)
                return 1
            pids = {m: p.pid for m, p in zip(modes, procs, strict=True)}
            warm = _requests(2, 2, h, w)
            for m in modes:
                _run(bus, f"b-{m}", warm, 120)
            for n in args.robots:
                reqs = _requests(n, args.steps, h, w)
                rates: dict[str, list[float]] = {m: [] for m in modes}
                cpus: dict[str, list[float]] = {m: [] for m in modes}
                lats: dict[str, list[float]] = {m: [] for m in modes}
                vals: dict[str, dict[str, tuple]] = {}
                for rnd in range(args.rounds):
                    order = list(modes) if rnd % 2 == 0 else list(reversed(modes))
                    for m in order:
                        rate, lat, v, cpu = _run(bus, f"b-{m}", reqs, 120, pids[m])
                        rates[m].append(rate)
                        cpus[m].append(cpu)
                        lats[m].extend(lat)
                        vals.setdefault(m, v)
                same = vals["off"] == vals["on"]
                identical &= same
                rows.append((n, {m: statistics.median(rates[m]) for m in modes},
                             {m: (_pct(lats[m], 50), _pct(lats[m], 95)) for m in modes}, same,
                             {m: statistics.median(cpus[m]) * 1e3 for m in modes}))
                r = rows[-1]
                print(f"  {n:3d} robots: off {r[1]['off']:6.1f} steps/s {r[4]['off']:5.1f} CPU ms/step, on "
                      f"{r[1]['on']:6.1f} steps/s {r[4]['on']:5.1f} CPU ms/step", flush=True)
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                p.wait(timeout=30)
    print(f"\nscorer replica, tiny random Qwen2-VL (not a VLM), {w}x{h} frames, 1 torch thread, batch max "
          f"{args.batch_max}, window {args.window_ms:g} ms; {args.steps} steps per robot x {args.rounds} rounds; "
          f"{os.cpu_count()} CPUs, load {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(f"{'robots':>6} {'off steps/s':>12} {'on steps/s':>11} {'on/off':>7} {'off p50/p95 ms':>16} "
          f"{'on p50/p95 ms':>15} {'replica CPU ms/step off':>24} {'on':>5} {'off/on':>7}  same values")
    for n, rate, lat, same, cpu in rows:
        print(f"{n:6d} {rate['off']:12.1f} {rate['on']:11.1f} {rate['on'] / rate['off']:7.2f} "
              f"{lat['off'][0]:8.0f}/{lat['off'][1]:<7.0f} {lat['on'][0]:7.0f}/{lat['on'][1]:<7.0f} "
              f"{cpu['off']:24.2f} {cpu['on']:5.2f} {cpu['off'] / cpu['on']:7.2f}  {'yes' if same else 'NO'}")
    print("replica CPU ms/step: user+system time of the replica process per step served (median over rounds); "
          "1000 / it = steps per second one core of a saturated replica sustains")
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
