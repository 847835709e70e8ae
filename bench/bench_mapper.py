"""Mapper step cost on a 30-step trajectory through a generated house, and our TSDF vs open3d's.

Per frame it times integrate (our vectorised TSDF), 2D projection, prompt points, frontiers (with Eq. A6
weights), the semantic-value write, the store snapshot, MapUpdate encoding and the Rerun logging; and, on
the same frames in the same run, open3d's ``t.geometry.VoxelBlockGrid`` integration (voxel 0.1 m, the same
truncation), printing p50/p95 and the ratio. Memory of the volume is printed against the explored area and
the step number.

    python bench/bench_mapper.py [--steps 30] [--width 640 --height 480] [--scene gen-00007]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from eqa.messages import EpisodeStart, Frame, Pose2D, Question, encode
from eqa.settings import Settings
from eqa.store import EmbeddedStore
from services.mapper.episode_map import EpisodeMap, Timer
from services.sim.camera import camera_pose, intrinsics
from services.sim.library import load_or_generate
from services.sim.render import Renderer


def trajectory(scene, steps: int, seed: int = 0) -> list[Pose2D]:
    """Farthest-point spread of free cells, visited in nearest-neighbour order, heading to the next one."""
    gt, ox, oy = scene.navigable_grid(0.1)
    rr, cc = np.nonzero(gt)
    pts = np.stack([ox + (cc + 0.5) * 0.1, oy + (rr + 0.5) * 0.1], axis=1)
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(len(pts)))]
    d = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while len(chosen) < steps:
        k = int(np.argmax(d))
        chosen.append(k)
        d = np.minimum(d, np.linalg.norm(pts - pts[k], axis=1))
    order = [chosen.pop(0)]
    while chosen:
        last = pts[order[-1]]
        j = int(np.argmin([np.linalg.norm(pts[c] - last) for c in chosen]))
        order.append(chosen.pop(j))
    poses = []
    for i, k in enumerate(order):
        nxt = pts[order[min(i + 1, len(order) - 1)]]
        yaw = math.atan2(nxt[1] - pts[k][1], nxt[0] - pts[k][0]) if i + 1 < len(order) else 0.0
        poses.append(Pose2D(x=float(pts[k][0]), y=float(pts[k][1]), yaw=yaw))
    return poses


class Open3DTSDF:
    """open3d's VoxelBlockGrid with the same voxel size and truncation (the other implementation)."""

    def __init__(self, voxel: float = 0.1, trunc_voxels: float = 5.0, max_depth: float = 10.0) -> None:
        import open3d as o3d

        self.o3d = o3d
        self.device = o3d.core.Device("CPU:0")
        self.voxel = voxel
        self.trunc = trunc_voxels * voxel
        self.max_depth = max_depth
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(o3d.core.float32, o3d.core.float32),
            attr_channels=((1), (1)),
            voxel_size=voxel,
            block_resolution=8,
            block_count=50000,
            device=self.device,
        )

    def integrate(self, depth: np.ndarray, K: np.ndarray, cam_pose: np.ndarray) -> None:
        o3d = self.o3d
        d = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth, np.float32)))
        intr = o3d.core.Tensor(K, o3d.core.float64)
        extr = o3d.core.Tensor(np.linalg.inv(cam_pose), o3d.core.float64)
        blocks = self.vbg.compute_unique_block_coordinates(d, intr, extr, 1.0, self.max_depth, self.trunc)
        self.vbg.integrate(blocks, d, intr, extr, 1.0, self.max_depth, self.trunc)

    def nbytes(self) -> int:
        n = self.vbg.hashmap().size()
        return int(n * 8**3 * 8)


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--scene", default="gen-00007")
    ap.add_argument("--no-open3d", action="store_true", help="skip the open3d comparison")
    ap.add_argument("--no-record", action="store_true", help="skip the Rerun logging cost")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.width < 16 or args.height < 12:
        print("error: steps >= 1, width >= 16, height >= 12", file=sys.stderr)
        return 2

    tmp = Path(tempfile.mkdtemp(prefix="bench-mapper-"))
    scene = load_or_generate(args.scene, tmp / "scenes")
    renderer = Renderer(scene)
    W, H = args.width, args.height
    K = intrinsics(W, H)
    poses = trajectory(scene, args.steps)
    frames = []
    for i, p in enumerate(poses):
        T = camera_pose(p)
        r = renderer.render(T, K, W, H)
        frames.append(
            Frame(episode_id="bench", step=i, pose=p, camera_pose=T, intrinsics=K, rgb=r.rgb, depth=r.depth)
        )
    q = Question(text="Where is the sofa?", choices=["a", "b", "c", "d"], scene=args.scene)
    start = EpisodeStart(episode_id="bench", robot="r0", question=q, max_steps=args.steps)
    em = EpisodeMap(start)
    store = EmbeddedStore(tmp / "store.sqlite")
    recorder = None
    if not args.no_record:
        from eqa.recording import EpisodeRecorder

        recorder = EpisodeRecorder(Settings(data_dir=tmp), "bench", "mapper")

    core, rows = [], []
    extra: dict[str, list[float]] = {k: [] for k in ("semantic_values", "snapshot", "encode", "record")}
    for f in frames:
        timer = Timer()
        t0 = time.perf_counter()
        em.integrate(f, timer)
        em.compute_frontiers(timer=timer)
        core.append((time.perf_counter() - t0) * 1000)
        t0 = time.perf_counter()
        em.apply_scores([0.5, 0.3, 0.2][: len(em.prompts)], 0.6)
        extra["semantic_values"].append((time.perf_counter() - t0) * 1000)
        t0 = time.perf_counter()
        store.set("mapper/episode/bench", em.snapshot())
        extra["snapshot"].append((time.perf_counter() - t0) * 1000)
        t0 = time.perf_counter()
        payload = encode(em.map_update(timer.ms))
        extra["encode"].append((time.perf_counter() - t0) * 1000)
        if recorder is not None:
            from services.mapper.service import MapperService

            t0 = time.perf_counter()
            svc = MapperService.__new__(MapperService)
            svc.recorders = {"bench": recorder}
            MapperService._record(svc, em, f)
            extra["record"].append((time.perf_counter() - t0) * 1000)
        rows.append(
            (
                f.step,
                timer.ms,
                em.explored_area_m2(),
                float(em.maps.observed.sum()) * 0.01,
                em.volume.nbytes(),
                len(payload),
            )
        )

    print(f"mapper bench: scene {args.scene}, {W}x{H}, {len(frames)} steps, {os.cpu_count()} CPUs")
    print("step  integrate  project  prompts  frontiers   explored m2  observed m2  volume MB  msg kB")
    for step, ms, area, obs, nbytes, size in rows:
        print(
            f"{step:4d} {ms['integrate']:9.1f} {ms['project']:8.1f} {ms['prompt_points']:8.1f} "
            f"{ms['frontiers']:10.1f} {area:13.1f} {obs:12.1f} {nbytes / 1e6:10.2f} {size / 1e3:7.1f}"
        )
    phase = {k: [r[1][k] for r in rows] for k in ("integrate", "project", "prompt_points", "frontiers")}
    print("\nper-frame ms            p50      p95")
    for k, v in phase.items():
        print(f"  {k:20s} {pct(v, 50):6.1f}   {pct(v, 95):6.1f}")
    print(
        f"  {'mapper step (core)':20s} {pct(core, 50):6.1f}   {pct(core, 95):6.1f}"
        "   <- integrate + projection + prompt points + frontiers; target p50 < 60 ms"
    )
    for k, v in extra.items():
        if v:
            print(f"  {k:20s} {pct(v, 50):6.1f}   {pct(v, 95):6.1f}")
    total = [c + sum(extra[k][i] for k in extra if extra[k]) for i, c in enumerate(core)]
    print(f"  {'whole step (all)':20s} {pct(total, 50):6.1f}   {pct(total, 95):6.1f}")

    if not args.no_open3d:
        o3 = Open3DTSDF()
        o3.integrate(frames[0].depth, K, frames[0].camera_pose)  # warm-up (allocation)
        o3 = Open3DTSDF()
        t_o3 = []
        for f in frames:
            t0 = time.perf_counter()
            o3.integrate(f.depth, K, f.camera_pose)
            t_o3.append((time.perf_counter() - t0) * 1000)
        ours = phase["integrate"]
        print(
            "\nTSDF integrate, same frames, same run:"
            f" ours p50 {pct(ours, 50):.1f} ms / p95 {pct(ours, 95):.1f} ms;"
            f" open3d VoxelBlockGrid p50 {pct(t_o3, 50):.1f} ms / p95 {pct(t_o3, 95):.1f} ms;"
            f" ratio ours/open3d (p50) {pct(ours, 50) / pct(t_o3, 50):.2f}"
        )
        print(
            "  (open3d keeps only blocks near surfaces: no free/unknown distinction, no explored marks;"
            f" {o3.nbytes() / 1e6:.1f} MB of voxel blocks)"
        )
    first, last = rows[0], rows[-1]
    print(
        f"\nmemory: volume {first[4] / 1e6:.2f} MB at step 0 (observed {first[3]:.0f} m2) -> "
        f"{last[4] / 1e6:.2f} MB at step {last[0]} (observed {last[3]:.0f} m2); "
        f"{last[4] / max(last[3], 1e-9) / 1e3:.1f} kB per observed m2"
    )
    # same pose again and again: the volume must not grow with the number of steps
    before = em.volume.nbytes()
    for i in range(10):
        f = frames[-1].model_copy(update={"step": len(frames) + i})
        em.integrate(f)
    print(
        f"memory after 10 more steps at the last pose: {em.volume.nbytes() / 1e6:.2f} MB "
        f"(was {before / 1e6:.2f} MB): grows with area, not steps"
    )
    if recorder is not None:
        recorder.close()
    store.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
