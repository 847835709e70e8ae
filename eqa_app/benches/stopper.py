"""Benchmark of the stopper: decision cost, calibration cost, Zenoh round trip, and the stopping rules'
success vs. normalized steps on SYNTHETIC exchangeable episodes (services/stopper/synthetic.py: a simulated
VLM that is confident and biased on irrelevant views) — a small analogue of Explore-EQA Fig. 9, not a
result about any real model.

    python -m eqa_app.benches.stopper [--n-cal 300] [--n-test 2000] [--seed 0] [--no-zenoh]
"""

from __future__ import annotations

import logging
import os
import socket
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

from eqa.messages import EpisodeStart, Question, StepScores, StopConfig
from eqa_app.benches import harness
from eqa_app.stats import percentile as pct
from services.stopper import baselines, conformal, synthetic
from services.stopper.calibration import calibrate
from services.stopper.state import CalibrationChoice, EpisodeRecord, decide


def bench_decide(n: int) -> None:
    q = Question(text="q?", choices=["a", "b", "c", "d"], scene="s", answer="A")
    start = EpisodeStart(episode_id="e", robot="r", question=q, max_steps=n + 1, stop=StopConfig(rule="cp"))
    rec = EpisodeRecord.from_start(start, "r")
    rec.calibration = CalibrationChoice(q_hat=1.9, eps=0.2, asked_eps=0.2, n=300, source="bench")
    rng = np.random.default_rng(0)
    times = []
    for t in range(n):
        s = StepScores(episode_id="e", step=t, answer_probs=rng.dirichlet(np.ones(4)).tolist(), relevance=0.01)
        t0 = time.perf_counter()
        decide(rec, s)
        times.append((time.perf_counter() - t0) * 1e6)
    print(f"decide() per step (cp, 4 choices): p50 {pct(times, 50):.0f} us, p95 {pct(times, 95):.0f} us")
    t0 = time.perf_counter()
    js = rec.model_dump_json()
    EpisodeRecord.model_validate_json(js)
    print(f"state (de)serialization after {n} steps: {(time.perf_counter() - t0) * 1e3:.2f} ms, {len(js)} bytes")


def bench_calibrate(n_cal: int, seed: int) -> float:
    traces = [synthetic.to_trace(e, f"q{i}") for i, e in enumerate(synthetic.episodes(n_cal, seed))]
    t0 = time.perf_counter()
    table = calibrate(traces)
    dt = time.perf_counter() - t0
    print(f"calibrate(): N={n_cal} traces, {len(table.entries)} eps values: {dt * 1e3:.1f} ms")
    return dt


def bench_rules(n_cal: int, n_test: int, seed: int) -> None:
    cal = synthetic.episodes(n_cal, seed)
    test = synthetic.episodes(n_test, seed + 1)
    kappas = [conformal.nonconformity(e.probs, e.relevance, e.answer) for e in cal]
    print(
        f"\nstopping rules on {n_test} synthetic held-out episodes (calibrated on {n_cal}); "
        "success = answer correct, steps normalized by each episode's limit"
    )
    print(f"  {'rule':<22} {'success':>8} {'norm. steps':>12} {'early stops':>12}")

    def report(label: str, outcomes: list[tuple[bool, float, bool]]) -> None:
        ok = np.mean([o[0] for o in outcomes])
        steps = np.mean([o[1] for o in outcomes])
        early = np.mean([o[2] for o in outcomes])
        print(f"  {label:<22} {ok:8.3f} {steps:12.3f} {early:12.3f}")

    def fallback(e: synthetic.SyntheticEpisode, upto: int) -> int:
        return conformal.fallback_answer(e.probs[: upto + 1], e.relevance[: upto + 1])

    for eps in (0.5, 0.4, 0.3, 0.2, 0.1):
        q_hat = conformal.conformal_quantile(kappas, eps)
        outs = []
        for e in test:
            run = conformal.running_intersection(e.rhos(), q_hat)
            sizes = run.sum(axis=1)
            stop = np.flatnonzero(sizes <= 1)
            t = int(stop[0]) if stop.size else len(sizes) - 1
            ans = int(np.flatnonzero(run[t])[0]) if sizes[t] == 1 else fallback(e, t)
            outs.append((ans == e.answer, (t + 1) / len(sizes), t < len(sizes) - 1))
        report(f"cp eps={eps:g} (q={q_hat:.3f})", outs)
    for thr in (0.5, 0.1, 0.01):
        outs = []
        for e in test:
            hs = [baselines.entropy(p) for p in e.probs]
            hit = [i for i, h in enumerate(hs) if h < thr]
            t = hit[0] if hit else len(hs) - 1
            ans = int(np.argmax(e.probs[t])) if hit else fallback(e, t)
            outs.append((ans == e.answer, (t + 1) / len(hs), bool(hit) and t < len(hs) - 1))
        report(f"entropy < {thr:g}", outs)
    for thr in (0.4, 0.6, 0.8):
        outs = []
        for e in test:
            hit = [i for i, r in enumerate(e.relevance) if r > thr]
            t = hit[0] if hit else len(e.relevance) - 1
            ans = int(np.argmax(e.probs[t])) if hit else fallback(e, t)
            outs.append((ans == e.answer, (t + 1) / len(e.relevance), bool(hit) and t < len(e.relevance) - 1))
        report(f"relevance > {thr:g}", outs)
    report("max_steps", [(fallback(e, len(e.relevance) - 1) == e.answer, 1.0, False) for e in test])


def bench_zenoh(steps: int) -> None:
    from eqa import keys
    from eqa.bus import Bus
    from eqa.messages import Decision
    from eqa.settings import Settings
    from eqa.store import EmbeddedStore
    from services.stopper.calibration import save_table
    from services.stopper.service import StopperService

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        base = Settings(
            data_dir=Path(tmp),
            zenoh_listen=["tcp/127.0.0.1:0"],
            zenoh_connect=[f"tcp/127.0.0.1:{port}"],
            record=False,
        )
        hub = base.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{port}"], "zenoh_connect": []})
        store = EmbeddedStore(Path(tmp) / "store.sqlite")
        save_table(
            store,
            calibrate([synthetic.to_trace(e, f"q{i}") for i, e in enumerate(synthetic.episodes(100, 0))], [0.2]),
        )
        store.close()
        got = threading.Event()
        with Bus(hub, "gateway", "bench") as bus:
            bus.subscribe(keys.stream("r0", keys.STOPPER_DECISION), Decision, lambda _k, _m: got.set())
            svc = StopperService(base)
            svc.start()
            time.sleep(0.5)
            q = Question(text="q?", choices=["a", "b", "c", "d"], scene="s")
            bus.publish(
                keys.stream("r0", keys.EPISODE_START),
                EpisodeStart(episode_id="e", robot="r0", question=q, max_steps=steps + 10, record=False),
            )
            time.sleep(0.3)
            rtts = []
            for t in range(steps):
                got.clear()
                t0 = time.perf_counter()
                bus.publish(
                    keys.stream("r0", keys.MAPPER_SCORES),
                    StepScores(episode_id="e", step=t, answer_probs=[0.25] * 4, relevance=0.0),
                )
                if not got.wait(5):
                    print("  (a decision was lost)")
                    break
                rtts.append((time.perf_counter() - t0) * 1e3)
            svc.stop()
    print(
        f"\nStepScores -> Decision over Zenoh (loopback, embedded SQLite store, {len(rtts)} steps): "
        f"p50 {statistics.median(rtts):.2f} ms, p95 {pct(rtts, 95):.2f} ms"
    )


def main(argv: list[str] | None = None) -> int:
    parser = harness.parser(__doc__)
    parser.add_argument("--n-cal", type=int, default=300, help="calibration episodes (default 300, as the paper)")
    parser.add_argument("--n-test", type=int, default=2000, help="held-out synthetic episodes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=200, help="steps for the latency figures")
    parser.add_argument("--no-zenoh", action="store_true", help="skip the Zenoh round-trip figure")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    bench_decide(args.steps)
    bench_calibrate(args.n_cal, args.seed)
    bench_rules(args.n_cal, args.n_test, args.seed)
    if not args.no_zenoh:
        bench_zenoh(args.steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
