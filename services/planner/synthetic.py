"""Synthetic 2D maps for planner tests and benchmarks (no simulator needed).

* :func:`rooms_map`: a house of rectangular rooms on a lattice, walls with doors, furniture blocks.
* :func:`maze_map`: a perfect maze of corridors (randomised depth-first search), for the worst case of
  long winding paths on a large grid (2000 x 2000 cells).

Both return ``(grid, free, occupied)`` with every non-wall cell inside the building free (fully known).
"""

from __future__ import annotations

import itertools

import numpy as np

from eqa.messages import GridSpec


def rooms_map(
    rng: np.random.Generator,
    width_m: float = 12.0,
    height_m: float = 9.0,
    resolution: float = 0.1,
    room_m: float = 4.0,
    door_m: float = 0.9,
    wall_m: float = 0.2,
    furniture: int = 6,
) -> tuple[GridSpec, np.ndarray, np.ndarray]:
    """A house: outer walls, interior walls every ``room_m`` with one door per wall segment, furniture."""
    margin = 5
    rows = round(height_m / resolution) + 2 * margin
    cols = round(width_m / resolution) + 2 * margin
    occ = np.zeros((rows, cols), dtype=bool)
    w = max(1, round(wall_m / resolution))
    door = max(1, round(door_m / resolution))
    r0, r1, c0, c1 = margin, rows - margin, margin, cols - margin
    occ[r0 : r0 + w, c0:c1] = occ[r1 - w : r1, c0:c1] = True
    occ[r0:r1, c0 : c0 + w] = occ[r0:r1, c1 - w : c1] = True
    step = max(door + 2 * w + 4, round(room_m / resolution))
    xs = list(range(c0 + step, c1 - w - 4, step))
    ys = list(range(r0 + step, r1 - w - 4, step))
    for x in xs:  # vertical walls, one door per room segment
        occ[r0:r1, x : x + w] = True
        bounds = [r0 + w, *ys, r1 - w]
        for a, b in itertools.pairwise(bounds):
            lo, hi = a + w + 2, b - door - 2
            if hi > lo:
                d = int(rng.integers(lo, hi))
                occ[d : d + door, x : x + w] = False
    for y in ys:  # horizontal walls
        occ[y : y + w, c0:c1] = True
        bounds = [c0 + w, *xs, c1 - w]
        for a, b in itertools.pairwise(bounds):
            lo, hi = a + w + 2, b - door - 2
            if hi > lo:
                d = int(rng.integers(lo, hi))
                occ[y : y + w, d : d + door] = False
    inside = np.zeros_like(occ)
    inside[r0:r1, c0:c1] = True
    for _ in range(furniture):  # boxes 0.4-1.2 m
        h = int(rng.integers(4, 13))
        ww = int(rng.integers(4, 13))
        i = int(rng.integers(r0 + w, r1 - w - h))
        j = int(rng.integers(c0 + w, c1 - w - ww))
        occ[i : i + h, j : j + ww] = True
    free = inside & ~occ
    grid = GridSpec(
        origin_x=-margin * resolution,
        origin_y=-margin * resolution,
        resolution=resolution,
        rows=rows,
        cols=cols,
    )
    return grid, free, occ


def maze_map(
    rng: np.random.Generator,
    cells: int = 2000,
    resolution: float = 0.1,
    corridor_m: float = 1.6,
    wall_m: float = 0.2,
) -> tuple[GridSpec, np.ndarray, np.ndarray]:
    """A ``cells x cells`` perfect maze: corridors ``corridor_m`` wide separated by ``wall_m`` walls."""
    cw = max(1, round(corridor_m / resolution))
    ww = max(1, round(wall_m / resolution))
    pitch = cw + ww
    n = (cells - ww) // pitch
    occ = np.ones((cells, cells), dtype=bool)
    seen = np.zeros((n, n), dtype=bool)
    stack = [(0, 0)]
    seen[0, 0] = True

    def carve(a: int, b: int) -> None:
        occ[ww + a * pitch : ww + a * pitch + cw, ww + b * pitch : ww + b * pitch + cw] = False

    carve(0, 0)
    while stack:
        a, b = stack[-1]
        nbrs = [
            (a + da, b + db)
            for da, db in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= a + da < n and 0 <= b + db < n and not seen[a + da, b + db]
        ]
        if not nbrs:
            stack.pop()
            continue
        na, nb = nbrs[int(rng.integers(len(nbrs)))]
        seen[na, nb] = True
        carve(na, nb)
        # open the wall between (a, b) and (na, nb)
        if na != a:
            r = ww + max(a, na) * pitch - ww
            occ[r : r + ww, ww + b * pitch : ww + b * pitch + cw] = False
        else:
            c = ww + max(b, nb) * pitch - ww
            occ[ww + a * pitch : ww + a * pitch + cw, c : c + ww] = False
        stack.append((na, nb))
    free = ~occ
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=resolution, rows=cells, cols=cells)
    return grid, free, occ
