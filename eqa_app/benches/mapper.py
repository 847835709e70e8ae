"""Mapper step cost on a trajectory through a generated house: ours against the starting implementation and
against open3d's ``VoxelBlockGrid``, on the same frames, interleaved, in one run.

Per frame, in rotating order so that load drifts hit all alike:

* ``baseline``: the TSDF of git revision ``--baseline`` (default: the first TSDF of the project, git 5f008c0), its
  source read with ``git show`` into a private module (nothing of it is kept in the tree);
* ``ours``: :class:`services.mapper.tsdf.TSDFVolume` of this tree;
* ``open3d``: ``o3d.t.geometry.VoxelBlockGrid`` with the same voxel size and truncation (surface band only:
  no free-space carving, no unknown, no explored marks).

After each frame the baseline and our volumes (tsdf, weight, explored) and their 2D projections are compared
bit for bit; the bench fails (exit 1) on the first difference. Then the whole mapper step of this tree
(integrate, projection, prompt points, frontiers), the store snapshot (full, as before, and the step's
incremental one when the tree has it) with its bytes, MapUpdate encoding and the Rerun logging are timed. The
incremental snapshot's bytes are written both as the mapper writes them (one ``Store.set_many`` call: one Redis
round trip) and key by key (a round trip per key), alternating which goes first.

    python -m eqa_app.benches.mapper [--steps 30] [--width 640 --height 480] [--scene gen-00007] [--baseline REV]
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

from eqa.messages import EpisodeStart, Frame, Pose2D, Question, encode
from eqa.settings import Settings
from eqa.store import EmbeddedStore
from eqa_app.benches import harness
from eqa_app.stats import percentile as pct
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


BASELINE_REV = "5f008c0"  # the project's first TSDF, projection and snapshot
ROOT = harness.REPO


def load_baseline(rev: str) -> tuple[types.ModuleType, types.ModuleType]:
    """``services/mapper/tsdf.py`` and ``projection.py`` of git revision ``rev`` as private modules."""
    mods = []
    for name in ("tsdf", "projection"):
        try:
            src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:services/mapper/{name}.py"],
                                 check=True, capture_output=True, text=True).stdout
        except (OSError, subprocess.CalledProcessError) as exc:
            raise LookupError(f"cannot read services/mapper/{name}.py at git {rev} ({exc})") from exc
        mod = types.ModuleType(f"_baseline_{name}")
        mod.__file__ = f"{rev}:services/mapper/{name}.py"
        sys.modules[mod.__name__] = mod  # dataclasses look their module up
        exec(compile(src, mod.__file__, "exec"), mod.__dict__)  # our own history, read from git
        mods.append(mod)
    return mods[0], mods[1]


def same_volume(a, b) -> str | None:
    """None when two volumes hold the same bits, else what differs."""
    if (a.origin_x, a.origin_y) != (b.origin_x, b.origin_y):
        return f"origin {(a.origin_x, a.origin_y)} != {(b.origin_x, b.origin_y)}"
    for name in ("tsdf", "weight", "explored"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        if x.shape != y.shape or x.tobytes() != y.tobytes():
            return f"{name} differs (shapes {x.shape} / {y.shape})"
    return None


def same_maps(a, b) -> str | None:
    for name in ("occupied", "free", "free_all", "explored", "observed"):
        x, y = getattr(a, name), getattr(b, name)
        if x.shape != y.shape or not np.array_equal(x, y):
            return f"2D {name} differs"
    return None if a.robot_cell == b.robot_cell else "robot cell differs"


def line(name: str, v: list[float], note: str = "") -> str:
    return f"  {name:28s} {pct(v, 50):7.2f} {pct(v, 95):7.2f} {max(v) if v else float('nan'):7.2f}  {note}"


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--scene", default="gen-00007")
    ap.add_argument("--baseline", default=BASELINE_REV,
                    help=f"git revision whose TSDF runs side by side (default {BASELINE_REV}); 'none' skips it")
    ap.add_argument("--no-open3d", action="store_true", help="skip the open3d comparison")
    ap.add_argument("--no-record", action="store_true", help="skip the Rerun logging cost")
    ap.add_argument("--store", choices=("redis", "embedded"), default="redis",
                    help="where snapshots are written: a private redis-server (what the fleet uses; default) or "
                         "the embedded SQLite store")
    args = ap.parse_args(argv)
    if not (1 <= args.steps <= 1000) or not (16 <= args.width <= 4096) or not (12 <= args.height <= 4096):
        print("error: 1 <= steps <= 1000, 16 <= width <= 4096, 12 <= height <= 4096", file=sys.stderr)
        return 2

    from tqdm import tqdm

    from services.mapper.tsdf import TSDFVolume

    try:
        from services.mapper.snapshots import snapshot_step
    except ImportError:  # a tree with whole-map snapshots only
        snapshot_step = None

    base_tsdf = base_proj = None
    if args.baseline != "none":
        try:
            base_tsdf, base_proj = load_baseline(args.baseline)
        except LookupError as exc:  # no git history here (e.g. a container): the rest still runs
            print(f"note: {exc}; the baseline comparison is skipped (pass --baseline REV of this repository, "
                  "or --baseline none)", file=sys.stderr)
    tmp = Path(tempfile.mkdtemp(prefix="bench-mapper-"))
    scene = load_or_generate(args.scene, tmp / "scenes")
    renderer = Renderer(scene)
    W, H = args.width, args.height
    K = intrinsics(W, H)
    poses = trajectory(scene, args.steps)
    frames = []
    for i, p in enumerate(tqdm(poses, desc="rendering", leave=False)):
        T = camera_pose(p)
        r = renderer.render(T, K, W, H)
        frames.append(
            Frame(episode_id="bench", step=i, pose=p, camera_pose=T, intrinsics=K, rgb=r.rgb, depth=r.depth)
        )
    q = Question(text="Where is the sofa?", choices=["a", "b", "c", "d"], scene=args.scene)
    start = EpisodeStart(episode_id="bench", robot="r0", question=q, max_steps=args.steps)
    episode_map = EpisodeMap(start)
    redis_proc = None
    if args.store == "redis":
        import shutil

        from eqa.launcher import free_port
        from eqa.store import RedisStore

        exe = shutil.which("redis-server")
        if exe is None:
            print("error: redis-server not found (apt-get install redis-server), or pass --store embedded",
                  file=sys.stderr)
            return 2
        port = free_port()
        redis_proc = subprocess.Popen([exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "",
                                       "--appendonly", "no", "--dir", str(tmp)], stdout=subprocess.DEVNULL)
        time.sleep(0.5)
        store = RedisStore(f"redis://127.0.0.1:{port}/0")
    else:
        store = EmbeddedStore(tmp / "store.sqlite")
    recorder = None
    if not args.no_record:
        from eqa.recording import EpisodeRecorder

        recorder = EpisodeRecorder(Settings(data_dir=tmp), "bench", "mapper")

    # the three TSDFs, interleaved (rotating order)
    ours_vol = TSDFVolume()
    base_vol = base_tsdf.TSDFVolume() if base_tsdf is not None else None
    o3 = None
    if not args.no_open3d:
        Open3DTSDF().integrate(frames[0].depth, K, frames[0].camera_pose)  # warm-up (allocation, threads)
        o3 = Open3DTSDF()
    tsdf_ms: dict[str, list[float]] = {"baseline": [], "ours": [], "open3d": []}
    runners = {
        "ours": lambda f: ours_vol.integrate(f.depth, f.intrinsics, f.camera_pose),
        "baseline": (lambda f: base_vol.integrate(f.depth, f.intrinsics, f.camera_pose)) if base_vol else None,
        "open3d": (lambda f: o3.integrate(f.depth, K, f.camera_pose)) if o3 else None,
    }
    order = [k for k, fn in runners.items() if fn is not None]

    core, rows = [], []
    extra: dict[str, list[float]] = {k: [] for k in ("semantic_values", "snapshot full", "snapshot step",
                                                     "snapshot step, key by key", "encode", "record")}
    nbytes: dict[str, list[int]] = {"snapshot full": [], "snapshot step": []}
    differ = None
    build_ms: list[float] = []  # the incremental snapshot's own work, without the store write
    for i, f in enumerate(tqdm(frames, desc="steps", leave=False)):
        for name in order[i % len(order):] + order[: i % len(order)]:
            t0 = time.perf_counter()
            runners[name](f)
            tsdf_ms[name].append((time.perf_counter() - t0) * 1000)
        if base_vol is not None and differ is None:
            why = same_volume(base_vol, ours_vol)
            differ = f"step {f.step}: TSDF {why}" if why else None
        timer = Timer()
        t0 = time.perf_counter()
        episode_map.integrate(f, timer)
        episode_map.compute_frontiers(timer=timer)
        core.append((time.perf_counter() - t0) * 1000)
        if base_proj is not None and differ is None:
            base_vol.planes["traversed"] = episode_map.volume.planes["traversed"]
            old = base_proj.project(base_vol, (f.pose.x, f.pose.y), episode_map.config.projection)
            why = same_volume(base_vol, episode_map.volume) or same_maps(old, episode_map.maps)
            differ = f"step {f.step}: mapper {why}" if why else None
        t0 = time.perf_counter()
        episode_map.apply_scores([0.5, 0.3, 0.2][: len(episode_map.prompts)], 0.6)
        extra["semantic_values"].append((time.perf_counter() - t0) * 1000)
        t0 = time.perf_counter()
        full = episode_map.snapshot()
        store.set("mapper/episode/bench", full)
        extra["snapshot full"].append((time.perf_counter() - t0) * 1000)
        nbytes["snapshot full"].append(len(full))
        if snapshot_step is not None:  # incremental snapshot: the step's parts + header
            t0 = time.perf_counter()
            header, parts, obsolete = snapshot_step(episode_map)
            built = (time.perf_counter() - t0) * 1000
            build_ms.append(built)
            # the same bytes written the two ways, in alternating order: one call (EpisodeService.save: one
            # Redis round trip) and key by key (a round trip per part, the header, the deletes)
            ways = [("", True), (", key by key", False)]
            for suffix, together in ways if i % 2 else ways[::-1]:
                prefix = f"mapper/episode/bench{suffix.replace(', ', '/').replace(' ', '-')}"
                t0 = time.perf_counter()
                if together and hasattr(store, "set_many"):
                    store.set_many([*((f"{prefix}:{part}", data) for part, data in parts.items()),
                                    (f"{prefix}/step", header)],
                                   then_delete=[f"{prefix}:{part}" for part in obsolete])
                else:
                    for part, data in parts.items():
                        store.set(f"{prefix}:{part}", data)
                    store.set(f"{prefix}/step", header)
                    for part in obsolete:
                        store.delete(f"{prefix}:{part}")
                extra["snapshot step" + suffix].append(built + (time.perf_counter() - t0) * 1000)
            nbytes["snapshot step"].append(len(header) + sum(len(d) for d in parts.values()))
        t0 = time.perf_counter()
        payload = encode(episode_map.map_update(timer.ms))
        extra["encode"].append((time.perf_counter() - t0) * 1000)
        if recorder is not None:
            from services.mapper.service import MapperService

            t0 = time.perf_counter()
            svc = MapperService.__new__(MapperService)
            svc.recorders = {"bench": recorder}
            MapperService._record(svc, episode_map, f)
            extra["record"].append((time.perf_counter() - t0) * 1000)
        rows.append((f.step, timer.ms, episode_map.explored_area_m2(), float(episode_map.maps.observed.sum()) * 0.01,
                     episode_map.volume.nbytes(), len(payload)))

    load = os.getloadavg()
    print(f"mapper bench: scene {args.scene}, {W}x{H}, {len(frames)} steps, {args.store} store, "
          f"{os.cpu_count()} CPUs, "
          f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")
    print("step  integrate  project  prompts  frontiers   explored m2  observed m2  volume MB  msg kB")
    for step, ms, area, obs, nb, size in rows:
        print(
            f"{step:4d} {ms['integrate']:9.1f} {ms['project']:8.1f} {ms['prompt_points']:8.1f} "
            f"{ms['frontiers']:10.1f} {area:13.1f} {obs:12.1f} {nb / 1e6:10.2f} {size / 1e3:7.1f}"
        )
    print(f"\nTSDF integrate, the same {len(frames)} frames interleaved in one run (ms)    p50     p95     max")
    notes = {"baseline": f"git {args.baseline}", "ours": "this tree",
             "open3d": "VoxelBlockGrid: surface band only, no carving/unknown/explored"}
    for name in order:
        print(line(f"{name}", tsdf_ms[name], notes[name]))
    ours = tsdf_ms["ours"]
    for other in ("baseline", "open3d"):
        if tsdf_ms[other]:
            print(f"  ratio ours/{other}: p50 {pct(ours, 50) / pct(tsdf_ms[other], 50):.2f}, "
                  f"p95 {pct(ours, 95) / pct(tsdf_ms[other], 95):.2f}")
    print(f"  ours p95/p50 {pct(ours, 95) / pct(ours, 50):.2f}")
    if base_vol is not None:
        print(f"  bit-identical to {args.baseline} (3D volume and 2D maps, every step): "
              f"{'NO: ' + differ if differ else 'yes'}")
    if o3 is not None:
        print(f"  (open3d voxel blocks {o3.nbytes() / 1e6:.1f} MB; our volume {ours_vol.nbytes() / 1e6:.1f} MB)")

    phase = {k: [r[1][k] for r in rows] for k in ("integrate", "project", "prompt_points", "frontiers")}
    print("\nmapper step of this tree (ms)          p50     p95     max")
    for k, v in phase.items():
        print(line(k, v))
    print(line("mapper step (core)", core, "integrate + projection + prompt points + frontiers"))
    for k, v in extra.items():
        if v:
            note = ""
            if nbytes.get(k):
                note = f"bytes p50 {pct(nbytes[k], 50) / 1e3:.0f} kB, max {max(nbytes[k]) / 1e3:.0f} kB"
            print(line(k, v, note))
    if build_ms:
        print(line("  of which building parts", build_ms, f"(the rest: the {args.store} store's write of the bytes)"))
    snap = "snapshot step" if extra["snapshot step"] else "snapshot full"
    total = [c + sum(extra[k][i] for k in extra
                     if (extra[k] and k not in ("snapshot full", "snapshot step, key by key")) or k == snap)
             for i, c in enumerate(core)]
    print(line("whole step (all)", total, f"core + values + {snap} + encode + record"))
    first, last = rows[0], rows[-1]
    print(
        f"\nmemory: volume {first[4] / 1e6:.2f} MB at step 0 (observed {first[3]:.0f} m2) -> "
        f"{last[4] / 1e6:.2f} MB at step {last[0]} (observed {last[3]:.0f} m2); "
        f"{last[4] / max(last[3], 1e-9) / 1e3:.1f} kB per observed m2"
    )
    before = episode_map.volume.nbytes()
    for i in range(10):  # same pose again and again: the volume must not grow with the number of steps
        episode_map.integrate(frames[-1].model_copy(update={"step": len(frames) + i}))
    print(f"memory after 10 more steps at the last pose: {episode_map.volume.nbytes() / 1e6:.2f} MB "
          f"(was {before / 1e6:.2f} MB): grows with area, not steps")
    if recorder is not None:
        recorder.close()
    store.close()
    if redis_proc is not None:
        redis_proc.terminate()
        redis_proc.wait(timeout=10)
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
