"""Planner timing per step: path search alone and the whole step (p50 / p95, milliseconds).

Maps:

* ``house``: the fully known map of a large generated house (about 800 m2, 0.1 m cells: the simulator's
  ground-truth navigable grid, ``services.sim``), the worst case of a real episode's map: every cell known.
* ``maze``: a synthetic 2000 x 2000 cell maze (200 x 200 m at 0.1 m), long winding paths over the whole
  grid: the stress case of "a 2000 x 2000 grid".

Each step: a robot pose sampled on free space with clearance, 12 frontiers sampled on free cells with
random Eq. A6-like weights, strategy ``semantic``. "search" = traversable blocks (clearance) + Dijkstra;
"step" = everything :func:`services.planner.step.plan_step` does (validation, search, approach points,
sampling, path read-out and shortening, truncation to 3 m).

    python -m eqa_app.benches.planner [--steps 40] [--maps house,maze] [--seed 0]
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np
from scipy import ndimage

from eqa.messages import Frontier, GridSpec, Pose2D
from eqa_app.benches import harness
from services.planner.sampling import step_rng
from services.planner.step import Memory, PlannerParams, plan_step
from services.planner.synthetic import maze_map


def house_map(seed: int) -> tuple[GridSpec, np.ndarray, np.ndarray, str]:
    from services.sim.catalog import HouseLimits
    from services.sim.housegen import generate_house

    scene = generate_house(seed, HouseLimits(min_area_m2=760.0, max_area_m2=800.0, min_rooms=10))
    nav, ox, oy = scene.navigable_grid(0.1)
    free = np.pad(nav, 5)
    occ = ~free
    grid = GridSpec(
        origin_x=ox - 0.5, origin_y=oy - 0.5, resolution=0.1, rows=free.shape[0], cols=free.shape[1]
    )
    return grid, free, occ, f"generated house gen-{seed}: {scene.floor_area_m2:.0f} m2 floor"


def run(name: str, grid: GridSpec, free: np.ndarray, occ: np.ndarray, steps: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    clear = ndimage.distance_transform_edt(free) * grid.resolution
    cells = np.argwhere(clear >= 0.45)
    params = PlannerParams()
    search: list[float] = []
    whole: list[float] = []
    kinds: dict[str, int] = {}
    plan_step(
        grid,
        free,
        occ,
        Pose2D(x=grid.origin_x + 1, y=grid.origin_y + 1),
        [],
        "fbe",
        Memory(),
        step_rng(0, 0),
        params,
    )  # warm-up (imports, first allocation)
    for t in range(steps):
        i, j = cells[int(rng.integers(len(cells)))]
        pose = Pose2D(
            x=grid.origin_x + (j + 0.5) * grid.resolution,
            y=grid.origin_y + (i + 0.5) * grid.resolution,
            yaw=float(rng.uniform(-math.pi, math.pi)),
        )
        frs = []
        for _ in range(12):
            fi, fj = cells[int(rng.integers(len(cells)))]
            a = float(rng.uniform(-math.pi, math.pi))
            frs.append(
                Frontier(
                    x=grid.origin_x + (fj + 0.5) * grid.resolution,
                    y=grid.origin_y + (fi + 0.5) * grid.resolution,
                    nx=math.cos(a),
                    ny=math.sin(a),
                    size=10,
                    weight=float(math.exp(rng.uniform(1, 4))),
                )
            )
        plan = plan_step(grid, free, occ, pose, frs, "semantic", Memory(), step_rng(seed, t), params)
        kinds[plan.kind] = kinds.get(plan.kind, 0) + 1
        search.append(plan.timing_ms.get("search", float("nan")))
        whole.append(plan.timing_ms["step"])
    s = np.array(search)
    w = np.array(whole)
    print(
        f"{name}: grid {grid.rows} x {grid.cols} cells at {grid.resolution} m, {int(free.sum())} free; "
        f"{steps} steps ({', '.join(f'{v} {k}' for k, v in sorted(kinds.items()))})"
    )
    for label, v in (("path search (clearance + Dijkstra)", s), ("whole step", w)):
        print(f"  {label:35s} p50 {np.percentile(v, 50):7.1f} ms  p95 {np.percentile(v, 95):7.1f} ms")


def main(argv: list[str] | None = None) -> int:
    ap = harness.parser(__doc__)
    ap.add_argument("--steps", type=int, default=40, help="planning steps per map (default 40)")
    ap.add_argument("--maps", default="house,maze", help="comma-separated: house, maze (default both)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    maps = [m.strip() for m in args.maps.split(",") if m.strip()]
    bad = [m for m in maps if m not in ("house", "maze")]
    if bad or args.steps < 1:
        print(f"error: unknown map(s) {bad} (use house, maze) or --steps < 1", file=sys.stderr)
        return 2
    print(f"planner bench, {time.strftime('%Y-%m-%d %H:%M')}, seed {args.seed}")
    for m in maps:
        if m == "house":
            grid, free, occ, what = house_map(args.seed)
            run(f"house ({what})", grid, free, occ, args.steps, args.seed)
        else:
            grid, free, occ = maze_map(np.random.default_rng(args.seed), cells=2000)
            run("maze (synthetic 2000 x 2000, 1.6 m corridors)", grid, free, occ, args.steps, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
