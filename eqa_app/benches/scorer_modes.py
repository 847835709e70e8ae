"""Scorer modes on real and double servers: per-step latency of each mode side by side, and a
conformal calibration made in sampling mode on the tiny Qwen2-VL served by ``transformers serve``, with its
coverage on held-out episodes.

    .venv/bin/python -m eqa_app.benches.scorer_modes [--steps 10] [--cal 8] [--test 8] [--samples 4]

Latency (round-robin, one step of each mode in turn, so load changes hit every mode alike; the machine is shared
and noisy, read the ratios): ``hf`` (the tiny model in-process, probabilities read from the logits),
``remote`` logprobs mode against the OpenAI-compatible double (tests/support/scorer.py, returns top_logprobs:
protocol cost only, no model), ``remote`` sampling mode against ``transformers serve`` (no logprobs) with k
samples. Calibration: ``--cal`` calibration-split and ``--test`` test-split questions of benchmark seed 0 run full
length through a real fleet whose scorer is ``remote`` in sampling mode on ``transformers serve``; q_hat from the
calibration traces, coverage (share of test episodes whose sequence-level prediction set holds the truth) per
eps. The model's weights are random: the numbers say nothing about accuracy, only that the plumbing works.
Writes bench/results/scorer_modes.json.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

from eqa_app.benches import harness

REPO = harness.REPO
harness.use_test_support()

from support.scorer import (  # noqa: E402
    OpenAIDouble,
    frame_request,
    install_serve,
    serve_double,
    serve_installed,
    start_serve,
    stop_process,
)
from tqdm import tqdm  # noqa: E402


def latency(serve_url: str, serve_model: str, model_dir: Path, steps: int, samples: list[int]) -> dict:
    from services.vlm_scorer.backends.hf import HFBackend
    from services.vlm_scorer.backends.remote import RemoteBackend

    double = OpenAIDouble(logprobs=True)
    durl, dsrv = serve_double(double)
    modes = {
        "hf (in-process, logits)": HFBackend(model_dir),
        "remote logprobs (double, no model)": RemoteBackend(durl, "tiny-vlm", mode="logprobs"),
    }
    for k in samples:
        modes[f"remote sampling k={k} (transformers serve)"] = RemoteBackend(
            serve_url, serve_model, timeout_s=120, mode="sampling", samples=k)
    times: dict[str, list[float]] = {m: [] for m in modes}
    calls: dict[str, int] = {}
    req = frame_request(h=240, w=320)
    for b in modes.values():  # warm-up (model load, first connection)
        b.score(req)
    for b in modes.values():
        if isinstance(b, RemoteBackend):
            b.calls = 0
    for _ in tqdm(range(steps), desc="latency rounds"):
        for name, b in modes.items():
            t0 = time.perf_counter()
            b.score(req)
            times[name].append(time.perf_counter() - t0)
    out = {}
    for name, b in modes.items():
        if isinstance(b, RemoteBackend):
            calls[name] = b.calls // steps
        ts = times[name]
        out[name] = {"median_ms": round(statistics.median(ts) * 1000, 1),
                     "p90_ms": round(sorted(ts)[int(0.9 * (len(ts) - 1))] * 1000, 1),
                     "http_calls_per_step": calls.get(name, 0), "n": len(ts)}
        if isinstance(b, RemoteBackend) and b.mode == "sampling":
            out[name]["n_per_request_honoured"] = b.n_supported
        b.close()
    dsrv.shutdown()  # type: ignore[attr-defined]
    dsrv.server_close()  # type: ignore[attr-defined]
    return out


def calibration(serve_url: str, serve_model: str, n_cal: int, n_test: int, samples: int, data: Path) -> dict:
    from eqa.settings import Settings
    from eqa_app.benchmark_runner import Runner
    from eqa_app.evaluation import cp_curve
    from services.sim.questions import benchmark
    from services.stopper.calibration import calibrate

    settings = Settings(data_dir=data, zenoh_listen=[], zenoh_connect=[], sim_width=160, sim_height=120,
                        scorer_backend="remote", remote_base_url=serve_url, remote_model=serve_model,
                        remote_mode="sampling", remote_samples=samples, remote_timeout_s=120.0,
                        scorer_timeout_s=300.0)
    bench = benchmark(seed=0, scenes_dir=settings.scenes_path)
    cal_q, test_q = list(bench.calibration)[:n_cal], list(bench.test)[:n_test]
    traces = {"cal": [], "test": []}
    t0 = time.perf_counter()
    steps = 0
    with Runner(settings, robots=2, scorers=2, step_timeout_s=300) as runner:
        for split, qs in (("cal", cal_q), ("test", test_q)):
            for res in tqdm(runner.run(qs), total=len(qs), desc=f"{split} episodes (sampling mode)"):
                if res.steps:
                    traces[split].append(res.trace("semantic"))
                    steps += len(res.steps)
    wall = time.perf_counter() - t0
    n = len(traces["cal"])
    eps = [e for e in (0.1, 0.2, 0.3, 0.5) if math.ceil((n + 1) * (1 - e)) <= n]  # q_hat defined at N
    table = calibrate(traces["cal"], eps, name="tiny-sampling",
                      provenance={"scorer_backend": "remote", "scorer_mode": "sampling", "samples": samples})
    curve = cp_curve(table, traces["test"])
    return {
        "n_cal": len(traces["cal"]), "n_test": len(traces["test"]), "samples": samples, "steps": steps,
        "wall_s": round(wall, 1),
        "per_eps": [{"eps": p.parameter, "q_hat": round(e.q_hat, 4), "coverage": p.coverage,
                     "target": round(1 - p.parameter, 2), "success": p.success,
                     "mean_normalized_steps": round(p.mean_normalized_steps, 3)}
                    for p, e in zip(curve, table.entries, strict=True)],
        "label": "tiny random Qwen2-VL: meaningless for accuracy, plumbing only",
    }


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--steps", type=int, default=10, help="latency rounds (one step of each mode per round)")
    ap.add_argument("--samples", type=int, nargs="+", default=[2, 4, 8], help="k for the sampling-mode latency")
    ap.add_argument("--cal", type=int, default=8, help="calibration-split questions")
    ap.add_argument("--test", type=int, default=8, help="test-split questions")
    ap.add_argument("--cal-samples", type=int, default=4, help="k for the calibration episodes")
    ap.add_argument("--skip-calibration", action="store_true")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "scorer_modes.json")
    args = ap.parse_args(argv)
    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    if not serve_installed():
        ok, out = install_serve()
        if not ok:
            print(f"transformers serve could not be installed: {out}", file=sys.stderr)
            return 1
    with tempfile.TemporaryDirectory() as tmp:
        model_dir = build_tiny_qwen2vl(Path(tmp) / "tiny")
        proc, url, model = start_serve(model_dir, Path(tmp) / "serve.log")
        try:
            from services.vlm_scorer.backends.remote import probe_endpoint

            check = probe_endpoint(url, model, samples=args.cal_samples)
            given = sys.argv[1:] if argv is None else argv
            result: dict = {"command": " ".join(["python -m eqa_app.benches.scorer_modes", *given]),
                            "check": check.lines(),
                            "latency": latency(url, model, model_dir, args.steps, args.samples)}
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(result, indent=2) + "\n")  # kept if the calibration fails
            if not args.skip_calibration:
                result["calibration"] = calibration(url, model, args.cal, args.test, args.cal_samples,
                                                    Path(tmp) / "data")
        finally:
            stop_process(proc)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
