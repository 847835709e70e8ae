"""Simulator benchmark: render time per 640x480 RGB + depth + instance frame (p50/p95), the raw ray cast
alone, scene generation time, and the time to build the whole question benchmark.

    python bench/bench_sim.py [--frames 100] [--houses 10] [--width 640 --height 480] [--full-benchmark]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.camera import camera_pose, intrinsics
from services.sim.housegen import generate_house
from services.sim.motion import sample_start_pose
from services.sim.questions import benchmark
from services.sim.render import Renderer


def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs) * 1000.0, q))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100, help="frames to render per measurement")
    ap.add_argument("--houses", type=int, default=10, help="houses to generate for the generation time")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--full-benchmark", action="store_true", help="also time the 500-question benchmark")
    args = ap.parse_args(argv)

    gen = []
    for s in range(args.houses):
        t = time.perf_counter()
        generate_house(1000 + s)
        gen.append(time.perf_counter() - t)
    print(f"scene generation: mean {np.mean(gen) * 1000:.0f} ms, p95 {pct(gen, 95):.0f} ms per house "
          f"({args.houses} houses)")

    scene = generate_house(1)
    t = time.perf_counter()
    rend = Renderer(scene)
    print(f"renderer build: {(time.perf_counter() - t) * 1000:.1f} ms ({len(scene.triangles)} triangles)")
    K = intrinsics(args.width, args.height)
    rng = np.random.default_rng(0)
    poses = [camera_pose(sample_start_pose(scene, rng, 0.3)) for _ in range(args.frames)]
    rend.render(poses[0], K, args.width, args.height)  # warm caches
    full, raw, labels = [], [], []
    for T in poses:
        t = time.perf_counter()
        rend.cast(T, K, args.width, args.height)
        raw.append(time.perf_counter() - t)
        t = time.perf_counter()
        out = rend.render(T, K, args.width, args.height)
        full.append(time.perf_counter() - t)
        t = time.perf_counter()
        rend.labels(out.instances)
        labels.append(time.perf_counter() - t)
    print(f"raw ray cast {args.width}x{args.height}: p50 {pct(raw, 50):.1f} ms, p95 {pct(raw, 95):.1f} ms")
    print(f"RGB-D+instance frame {args.width}x{args.height}: p50 {pct(full, 50):.1f} ms, "
          f"p95 {pct(full, 95):.1f} ms (target p50 < 30 ms)")
    print(f"labels: p50 {pct(labels, 50):.2f} ms")
    if args.full_benchmark:
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            b = benchmark(0, Path(tmp))
            first = time.perf_counter() - t
            t = time.perf_counter()
            benchmark(0, Path(tmp))
            cached = time.perf_counter() - t
        print(f"benchmark: {len(b.calibration)}+{len(b.test)} questions over {len(b.scenes)} houses in "
              f"{first:.1f} s (houses generated), {cached:.1f} s (houses cached)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
