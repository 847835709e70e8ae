"""TSDF integrate's tail: the cost of the frames that make the grid grow, this tree against a git revision.

Both volumes fuse the same rendered frames (a trajectory through each house, as in ``eqa_app/benches/mapper.py``) into
fresh volumes, ``--repeats`` times, interleaved frame by frame (ours, baseline, ours, ...), so a load drift
hits both alike. Per frame the minimum over the repeats is kept: the frame's own cost without the machine's
noise, which is what a tail made by the algorithm (copying the whole volume when the grid grows) shows up in.
Printed per tree: p50 / p95 / max over frames, p95/p50, the frames that grew the grid against the others, and
of a growing frame's time the part spent growing the grid (``ensure``: the copy into larger arrays), which says
whether the tail is the growth or the frames themselves (a frame that sees new territory also fuses more
voxels), and how many of the frames at or above p95 grew the grid with p95/p50 over the frames that did not; then
whether the two trees' volumes are bit-identical after every frame.

    python -m eqa_app.benches.tsdf_growth [--scenes gen-00007 gen-00042] [--steps 40] [--repeats 5] [--baseline REV]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from eqa_app.benches import harness
from eqa_app.benches.mapper import load_baseline, same_volume, trajectory
from eqa_app.stats import percentile as pct
from services.mapper.tsdf import TSDFVolume
from services.sim.camera import camera_pose, intrinsics
from services.sim.library import load_or_generate
from services.sim.render import Renderer


def _frames(scene_id: str, steps: int, width: int, height: int, root: Path) -> list[tuple]:
    scene = load_or_generate(scene_id, root)
    renderer = Renderer(scene)
    K = intrinsics(width, height)
    out = []
    for p in trajectory(scene, steps):
        T = camera_pose(p)
        out.append((renderer.render(T, K, width, height).depth, K, T))
    return out


def _timed_ensure(vol: object) -> list[float]:
    """Wrap the volume's ``ensure`` (grid growth) so the time spent in it per frame is known (ms, in [0])."""
    spent = [0.0]
    inner = vol.ensure  # type: ignore[attr-defined]

    def ensure(*a: float) -> None:
        t0 = time.perf_counter()
        inner(*a)
        spent[0] += (time.perf_counter() - t0) * 1e3

    vol.ensure = ensure  # type: ignore[attr-defined]
    return spent


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--scenes", nargs="+", default=["gen-00007", "gen-00042", "gen-00151"],
                    help="generated houses to walk through (default: three)")
    ap.add_argument("--steps", type=int, default=40, help="frames per house (default 40)")
    ap.add_argument("--repeats", type=int, default=5, help="passes over the frames; per frame the minimum is kept")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--baseline", default="HEAD", help="git revision whose TSDF runs side by side (default HEAD)")
    args = ap.parse_args(argv)
    if not (1 <= args.steps <= 500 and 1 <= args.repeats <= 50 and len(args.scenes) <= 20):
        print("error: 1 <= steps <= 500, 1 <= repeats <= 50, at most 20 scenes", file=sys.stderr)
        return 2
    from tqdm import tqdm

    try:
        base_tsdf, _ = load_baseline(args.baseline)
    except LookupError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    scenes = harness.REPO / "var" / "scenes"  # generated once, then loaded
    houses = [_frames(s, args.steps, args.width, args.height, scenes)
              for s in tqdm(args.scenes, desc="rendering", leave=False)]
    trees = {"ours": TSDFVolume, "baseline": base_tsdf.TSDFVolume}
    cost = {name: [np.full(len(h), np.inf) for h in houses] for name in trees}
    growth = {name: [np.full(len(h), np.inf) for h in houses] for name in trees}  # of which in ensure()
    grew = [np.zeros(len(h), bool) for h in houses]
    voxels = [np.zeros(len(h), np.int64) for h in houses]  # voxels each frame updates (the same every repeat)
    identical = True
    for _ in tqdm(range(args.repeats), desc="repeats", leave=False):
        for hi, frames in enumerate(houses):
            vols = {name: cls() for name, cls in trees.items()}
            spent = {name: _timed_ensure(vol) for name, vol in vols.items()}
            for fi, (depth, K, T) in enumerate(frames):
                # alternating which tree goes first: the second would find the frame in the caches
                for name, vol in list(vols.items())[:: 1 if fi % 2 else -1]:
                    shape = vol.tsdf.shape
                    spent[name][0] = 0.0
                    t0 = time.perf_counter()
                    n = vol.integrate(depth, K, T)
                    dt = (time.perf_counter() - t0) * 1e3
                    cost[name][hi][fi] = min(cost[name][hi][fi], dt)
                    growth[name][hi][fi] = min(growth[name][hi][fi], spent[name][0])
                    if name == "ours":
                        grew[hi][fi] = vol.tsdf.shape != shape and fi > 0
                        voxels[hi][fi] = n
                if same_volume(vols["ours"], vols["baseline"]) is not None:
                    identical = False
    import os

    print(f"TSDF integrate per frame, min over {args.repeats} interleaved repeats, {args.width}x{args.height}, "
          f"{len(houses)} houses x {args.steps} frames; load {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(f"{'tree':<10}{'p50':>8}{'p95':>8}{'max':>8}{'p95/p50':>9}{'grow p50':>10}{'other p50':>10}"
          f"{'in ensure':>11}  (ms)")
    g = np.concatenate(grew)
    for name in trees:
        c = np.concatenate(cost[name])
        label = "this tree" if name == "ours" else f"git {args.baseline}"
        print(f"{name:<10}{pct(list(c), 50):8.2f}{pct(list(c), 95):8.2f}{c.max():8.2f}"
              f"{pct(list(c), 95) / pct(list(c), 50):9.2f}"
              f"{pct(list(c[g]), 50):10.2f}{pct(list(c[~g]), 50):10.2f}"
              f"{pct(list(np.concatenate(growth[name])[g]), 50):11.2f}  {label}")
    print(f"frames that grew the grid: {int(g.sum())} of {g.size}")
    for name in trees:  # what sets the tail: the growth, or frames that fuse more voxels
        c = np.concatenate(cost[name])
        tail = c >= np.percentile(c, 95)
        rest = c[~g]
        print(f"{name}: of the {int(tail.sum())} frames at or above p95, {int((tail & g).sum())} grew the grid; "
              f"without the growing frames p50 {pct(list(rest), 50):.2f}, p95 {pct(list(rest), 95):.2f}, "
              f"p95/p50 {pct(list(rest), 95) / pct(list(rest), 50):.2f}")
    # How much the frames' own work varies: every voxel a frame updates is read and written (the kernel also
    # visits the candidate columns' voxels it does not update, a cost that varies less).
    v = np.concatenate(voxels).astype(np.float64)
    c = np.concatenate(cost["ours"])
    per = c[v > 0] * 1e6 / v[v > 0]
    print(f"voxels updated per frame: p50 {np.percentile(v, 50):.0f}, p95 {np.percentile(v, 95):.0f}, "
          f"p95/p50 {np.percentile(v, 95) / np.percentile(v, 50):.2f}; ours per updated voxel p50 "
          f"{np.percentile(per, 50):.1f} ns, p95 {np.percentile(per, 95):.1f} ns")
    print(f"bit-identical volumes after every frame: {'yes' if identical else 'NO'}")
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
