"""Simulator benchmark: render time per 640x480 RGB + depth + instance frame (p50/p95), the raw ray cast
alone, scene generation time, and the time to build the whole question benchmark.

    python -m eqa_app.benches.sim [--frames 100] [--houses 10] [--width 640 --height 480] [--full-benchmark]

``--identical-to REV`` instead checks the renderer against ``services/sim/render.py`` of git revision ``REV``
(loaded from ``git show`` into a private module, nothing of it kept in the tree): ``--frames`` poses in each of
``--houses`` generated houses, each rendered by both as a question episode sees it (nothing hidden) and as a task
episode holding an object (the largest instance in view hidden); rgb, depth and instance bytes (and dtypes,
shapes) must be equal (exit 1 otherwise). It also times both, CPU seconds (``time.process_time``) per frame,
interleaved in alternating order, and prints p50 of each and the NEW/OLD ratio of the medians.

    python -m eqa_app.benches.sim --identical-to 5f008c0 --houses 3 --frames 100 --width 320 --height 240
"""

from __future__ import annotations

import hashlib
import importlib.util
import subprocess
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np

from eqa_app.benches import harness
from eqa_app.stats import percentile as pct
from services.sim.camera import camera_pose, intrinsics
from services.sim.housegen import generate_house
from services.sim.motion import sample_start_pose
from services.sim.questions import benchmark
from services.sim.render import Renderer


def ms(seconds: list[float]) -> np.ndarray:
    return np.asarray(seconds) * 1000.0


def old_render_module(rev: str) -> ModuleType:
    """``services/sim/render.py`` of git revision ``rev`` as a private module (from ``git show``)."""
    root = harness.REPO
    src = subprocess.run(["git", "show", f"{rev}:services/sim/render.py"], cwd=root, check=True,
                         capture_output=True, text=True).stdout
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "render_old.py"
        path.write_text(src)
        spec = importlib.util.spec_from_file_location("render_old", path)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    return mod


def frame_digest(out: object) -> str:
    """sha256 over the rgb, depth and instance arrays of a ``Rendered`` (bytes, dtypes and shapes)."""
    h = hashlib.sha256()
    for name in ("rgb", "depth", "instances"):
        a = getattr(out, name)
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def identical_to(rev: str, houses: int, frames: int, width: int, height: int) -> int:
    """Render the same poses with ``rev``'s renderer and ours; compare bytes and time both (see module doc)."""
    old_mod = old_render_module(rev)
    K = intrinsics(width, height)
    t_old: list[float] = []
    t_new: list[float] = []
    n_frames = n_hidden = mismatches = 0
    for s in range(houses):
        scene = generate_house(1 + s)
        old, new = old_mod.Renderer(scene), Renderer(scene)
        rng = np.random.default_rng(100 + s)
        poses = [camera_pose(sample_start_pose(scene, rng, 0.3)) for _ in range(frames)]
        for k, T in enumerate(poses):
            base = new.render(T, K, width, height)
            ids, counts = np.unique(base.instances[base.instances >= 0], return_counts=True)
            cases = [frozenset()]
            if ids.size and hasattr(old, "_without"):  # older revisions cannot hide
                cases.append(frozenset({int(ids[counts.argmax()])}))
            for hidden in cases:
                pair = [(old, t_old), (new, t_new)]
                if k % 2:
                    pair.reverse()
                digests = {}
                for rend, times in pair:
                    t = time.process_time()
                    out = rend.render(T, K, width, height, hidden) if hidden else rend.render(T, K, width, height)
                    times.append(time.process_time() - t)
                    digests[id(rend)] = frame_digest(out)
                n_frames += 1
                n_hidden += bool(hidden)
                if digests[id(old)] != digests[id(new)]:
                    mismatches += 1
                    print(f"MISMATCH house gen-{1 + s:05d} pose {k} hidden {sorted(hidden)}", flush=True)
        print(f"house gen-{1 + s:05d}: {frames} poses rendered, {mismatches} mismatches so far", flush=True)
    po, pn = pct(ms(t_old), 50), pct(ms(t_new), 50)
    print(f"{n_frames} frames {width}x{height} ({n_hidden} with an object hidden) over {houses} houses: "
          f"{'byte-identical' if mismatches == 0 else f'{mismatches} DIFFER'} to {rev}")
    print(f"CPU per frame p50: {rev} {po:.2f} ms, ours {pn:.2f} ms, ours/{rev} {pn / po:.3f} "
          f"(interleaved, same poses)")
    return 0 if mismatches == 0 else 1


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--frames", type=int, default=100, help="frames to render per measurement")
    ap.add_argument("--houses", type=int, default=10, help="houses to generate for the generation time")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--full-benchmark", action="store_true", help="also time the 500-question benchmark")
    ap.add_argument("--identical-to", metavar="REV", help="check frames are byte-identical to git revision REV's "
                    "renderer and time both (see above); --houses houses x --frames poses")
    args = ap.parse_args(argv)
    if args.identical_to:
        return identical_to(args.identical_to, args.houses, args.frames, args.width, args.height)

    gen = []
    for s in range(args.houses):
        t = time.perf_counter()
        generate_house(1000 + s)
        gen.append(time.perf_counter() - t)
    print(f"scene generation: mean {np.mean(gen) * 1000:.0f} ms, p95 {pct(ms(gen), 95):.0f} ms per house "
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
    print(f"raw ray cast {args.width}x{args.height}: p50 {pct(ms(raw), 50):.1f} ms, p95 {pct(ms(raw), 95):.1f} ms")
    print(f"RGB-D+instance frame {args.width}x{args.height}: p50 {pct(ms(full), 50):.1f} ms, "
          f"p95 {pct(ms(full), 95):.1f} ms (target p50 < 30 ms)")
    print(f"labels: p50 {pct(ms(labels), 50):.2f} ms")
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
