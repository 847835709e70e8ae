"""Scorer benchmark: replicas of the tiny hf model over Zenoh, bus overhead, batching speed-up.

Prints
* requests per second with 1, 2 and 4 replica processes (``python -m services.vlm_scorer``, tiny random
  Qwen2-VL built offline, one torch thread each) serving a client that keeps 2 requests per replica in flight;
* the bus overhead per request: mean latency of sequential requests through one replica against the same
  call in-process (ratio in the same run);
* the speed-up of batching a step's four prompts into one forward pass against four separate calls.

The numbers depend on the machine and on what else runs on it.
"""

from __future__ import annotations

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

from eqa_app.benches import harness

REPO = harness.REPO
harness.use_test_support()

from eqa.bus import Bus  # noqa: E402
from eqa.launcher import free_port  # noqa: E402
from eqa.scorer_client import ScorerClient  # noqa: E402
from eqa.settings import Settings  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--requests", type=int, default=60, help="requests per replica-count measurement")
    ap.add_argument("--replicas", default="1,2,4", help="comma-separated replica counts")
    ap.add_argument("--size", default="120x160", help="image HxW")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per replica")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))

    import torch
    from support.scorer import frame_request

    from services.vlm_scorer import prompts
    from services.vlm_scorer.backends.hf import HFBackend
    from services.vlm_scorer.tiny import build_tiny_qwen2vl
    from services.vlm_scorer.visual_prompt import annotate

    torch.set_num_threads(args.threads)
    tmp = Path(tempfile.mkdtemp(prefix="bench-scorer-"))
    model_dir = build_tiny_qwen2vl(tmp / "tiny-qwen2vl")
    backend = HFBackend(model_dir)
    reqs = [frame_request(step=i, h=h, w=w) for i in range(args.requests)]

    # --- batching ----------------------------------------------------------------------------------------
    req = reqs[0]
    queries = prompts.step_queries(req.question, req.question.choices, len(req.prompt_points))
    ann = annotate(req.rgb, req.prompt_points)
    for _ in range(3):
        backend.candidate_probs(req.rgb, ann, queries)
    n = 20
    t0 = time.perf_counter()
    for _ in range(n):
        backend.candidate_probs(req.rgb, ann, queries)
    batched = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    for _ in range(n):
        for q in queries:
            backend.candidate_probs(req.rgb, ann, [q])
    separate = (time.perf_counter() - t0) / n
    print(
        f"batching: {len(queries)} prompts in one batch {batched * 1e3:.1f} ms, "
        f"as separate calls {separate * 1e3:.1f} ms -> speed-up x{separate / batched:.2f}"
    )

    # --- in-process reference ----------------------------------------------------------------------------
    lat_local = []
    for r in reqs[:30]:
        t0 = time.perf_counter()
        backend.score(r)
        lat_local.append(time.perf_counter() - t0)
    local_ms = statistics.mean(lat_local) * 1e3
    print(f"in-process score(): {local_ms:.1f} ms/request ({1e3 / local_ms:.1f} req/s on one thread)")

    port = free_port()
    base = Settings(
        data_dir=tmp / "var",
        zenoh_listen=["tcp/127.0.0.1:0"],
        zenoh_connect=[f"tcp/127.0.0.1:{port}"],
        record=False,
        scorer_timeout_s=60,
        scorer_backend="hf",
        hf_model_path=model_dir,
    )
    hub = base.model_copy(update={"zenoh_listen": [f"tcp/127.0.0.1:{port}"], "zenoh_connect": []})
    env = {
        **os.environ,
        **base.env(),
        "EQA_LOG_LEVEL": "WARNING",
        "OMP_NUM_THREADS": str(args.threads),
        "MKL_NUM_THREADS": str(args.threads),
    }
    with Bus(hub, "gateway", "bench") as bus:
        client = ScorerClient(bus, base)
        procs: list[subprocess.Popen[bytes]] = []
        try:
            for count in (int(c) for c in args.replicas.split(",")):
                while len(procs) < count:
                    rid = f"bench{len(procs)}"
                    procs.append(
                        subprocess.Popen(
                            [sys.executable, "-m", "services.vlm_scorer"],
                            cwd=REPO,
                            env={**env, "EQA_SCORER_REPLICA": rid, "EQA_INSTANCE": rid},
                        )
                    )
                if not client.wait_for_replicas(count, timeout=120):
                    print(f"error: {count} replicas did not come up", file=sys.stderr)
                    return 1
                with ThreadPoolExecutor(2 * count) as pool:  # warm-up: every replica serves a few
                    list(pool.map(client.score, reqs[: 4 * count]))
                if count == 1:
                    lat_bus = []
                    for r in reqs[:30]:
                        t0 = time.perf_counter()
                        client.score(r)
                        lat_bus.append(time.perf_counter() - t0)
                    bus_ms = statistics.mean(lat_bus) * 1e3
                    print(
                        f"bus: {bus_ms:.1f} ms/request vs in-process {local_ms:.1f} ms -> overhead "
                        f"{bus_ms - local_ms:.1f} ms/request (ratio x{bus_ms / local_ms:.2f})"
                    )
                t0 = time.perf_counter()
                with ThreadPoolExecutor(2 * count) as pool:
                    results = list(pool.map(client.score, reqs))
                dt = time.perf_counter() - t0
                spread = {
                    r: sum(x.replica == r for x in results) for r in sorted({x.replica for x in results})
                }
                print(f"{count} replica(s): {len(reqs) / dt:.1f} req/s  (per replica: {spread})")
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                p.wait(timeout=30)
    print(
        f"machine: {os.cpu_count()} CPUs; tiny random Qwen2-VL, images {w}x{h}, "
        f"{args.threads} torch thread(s)"
        " per replica"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
