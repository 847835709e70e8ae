"""The remote scorer's HTTP: a step's four queries sent concurrently on kept-alive connections, against the same
queries one after the other and/or on a new connection each, on a real OpenAI-compatible server.

The server is llama.cpp's ``llama-server`` (built by ``scripts/setup-llama.sh``, as for
tests/scorer/test_scorer_llamacpp.py) serving the tiny random LLaVA with its vision projector, one thread, on
loopback. Four clients, all :class:`services.vlm_scorer.backends.remote.RemoteBackend` in logprobs mode on the same
steps, in alternating rounds:

* ``concurrent, keep-alive``: the backend as it is (a pool of 4 threads, one ``httpx.Client``);
* ``concurrent, new connections``: the client keeps no idle connection (``max_keepalive_connections=0``);
* ``sequential, keep-alive``: a pool of one thread;
* ``sequential, new connections``: both.

Printed per client: p50 / p95 wall time of a step and the client process's CPU time per step. Then a replica's
batch of ``--batch`` steps (robots): ``score_many`` (all their queries in flight together) against the steps one
after the other, wall and CPU per step. The model is
random and tiny: the figures are the protocol's cost and how much of the server's work the concurrency overlaps,
not a real model's speed.

    python -m eqa_app.benches.scorer_remote [--steps 12] [--rounds 3] [--size 120x160]
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from eqa_app.benches import harness

REPO = harness.REPO
harness.use_test_support()

from eqa_app.stats import percentile as pct  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--steps", type=int, default=12, help="steps per client per round (1..100, default 12)")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds (1..20, default 3)")
    ap.add_argument("--size", default="120x160", help="frame HxW (default 120x160)")
    ap.add_argument("--batch", type=int, default=8, help="steps of one replica batch (1..8, default 8)")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    if not (1 <= args.steps <= 100 and 1 <= args.rounds <= 20 and 16 <= h <= 1024 and 16 <= w <= 1024
            and 1 <= args.batch <= 8):
        print("error: steps 1..100, rounds 1..20, sides 16..1024, batch 1..8", file=sys.stderr)
        return 2

    import httpx
    from support.scorer import frame_request, setup_llama, start_llama_server, stop_process

    from services.vlm_scorer.backends.remote import RemoteBackend

    print("setting up llama-server (scripts/setup-llama.sh) ...", flush=True)
    paths, built, out = setup_llama()
    if paths is None:
        print(f"error: llama-server is not available ({'set-up failed' if built else 'not built'}): {out}",
              file=sys.stderr)
        return 1
    proc, url, model = start_llama_server(paths, Path(tempfile.mkdtemp(prefix="bench-remote-")) / "server.log")
    try:
        clients: dict[str, RemoteBackend] = {}
        for concurrent in (True, False):
            for keep in (True, False):
                b = RemoteBackend(url, model, timeout_s=120.0, max_retries=0, mode="logprobs")
                if not concurrent:
                    b.pool.shutdown()
                    b.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="remote-scorer")
                if not keep:
                    b.client.close()
                    b.client = httpx.Client(timeout=httpx.Timeout(120.0),
                                            limits=httpx.Limits(max_keepalive_connections=0))
                name = f"{'concurrent' if concurrent else 'sequential'}, {'keep-alive' if keep else 'new connections'}"
                clients[name] = b
        reqs = [frame_request(step=s, h=h, w=w) for s in range(args.steps)]
        for b in clients.values():  # warm: the server's prompt cache and each client's first connections
            b.score(reqs[0])
        times: dict[str, list[float]] = {n: [] for n in clients}
        cpus: dict[str, float] = dict.fromkeys(clients, 0.0)
        loads = [os.getloadavg()[0]]
        for rnd in range(args.rounds):
            order = list(clients) if rnd % 2 == 0 else list(reversed(clients))
            for name in order:
                c0 = time.process_time()
                for req in reqs:
                    t0 = time.perf_counter()
                    clients[name].score(req)
                    times[name].append((time.perf_counter() - t0) * 1e3)
                cpus[name] += time.process_time() - c0
            loads.append(os.getloadavg()[0])
            print(f"  round {rnd + 1}/{args.rounds} done; load {loads[-1]:.1f}", flush=True)
        shipped = clients["concurrent, keep-alive"]
        batch = [frame_request(step=s, h=h, w=w, episode=f"ep{s}") for s in range(args.batch)]
        batch_times: dict[str, list[float]] = {"batch together (score_many)": [], "batch one by one": []}
        batch_cpu = dict.fromkeys(batch_times, 0.0)
        for rnd in range(args.rounds * 2):
            for name in (list(batch_times) if rnd % 2 == 0 else list(reversed(batch_times))):
                c0, t0 = time.process_time(), time.perf_counter()
                if name.startswith("batch together"):
                    got = shipped.score_many(batch)
                    if not all(hasattr(g, "answer_probs") for g in got):
                        raise RuntimeError(f"a step of the batch failed: {got}")
                else:
                    for req in batch:
                        shipped.score(req)
                batch_times[name].append((time.perf_counter() - t0) * 1e3)
                batch_cpu[name] += time.process_time() - c0
        loads.append(os.getloadavg()[0])
        for b in clients.values():
            b.close()
    finally:
        stop_process(proc)
    print(f"\nremote scorer (logprobs mode) on llama-server (tiny random LLaVA, -t 1, loopback), {w}x{h} frames, "
          f"{args.steps} steps x {args.rounds} rounds per client; {os.cpu_count()} CPUs, 1-min load "
          f"{min(loads):.1f}-{max(loads):.1f}")
    print(f"{'client':<32} {'step p50 ms':>11} {'p95 ms':>7} {'client CPU ms/step':>19}")
    for name in clients:
        n = len(times[name])
        print(f"{name:<32} {pct(times[name], 50):11.1f} {pct(times[name], 95):7.1f} {cpus[name] / n * 1e3:19.2f}")
    print(f"\na replica's batch of {args.batch} steps, {args.rounds * 2} alternating rounds (the shipped client)")
    print(f"{'':<32} {'batch p50 ms':>12} {'ms per step':>11} {'client CPU ms/step':>19}")
    for name, v in batch_times.items():
        p50 = pct(v, 50)
        print(f"{name:<32} {p50:12.1f} {p50 / args.batch:11.1f} {batch_cpu[name] / (len(v) * args.batch) * 1e3:19.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
