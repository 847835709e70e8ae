"""Compiled per-pixel loops of :class:`services.sim.render.Renderer` (numba): the world rays of a view and the
frame from the ray cast's hits. Each does, pixel by pixel, the float32 operations of the numpy form it replaces
in the same order, so the frames are byte-identical (``python -m eqa_app.benches.sim --identical-to REV``,
tests/sim/test_sim_render.py); what it saves is numpy's strided column writes and temporaries (about 1 ms of a
320x240 frame, most of what the sim spends outside open3d's ray cast).

Eager signatures with ``cache=True`` (cache outside the source tree: :mod:`eqa.numba_cache`), so a sim's first
frame does not compile.
"""

from __future__ import annotations

import numba
import numpy as np

from eqa.numba_cache import choose_cache_dir

choose_cache_dir()  # before the njit calls below

_f4_1 = numba.types.Array(numba.float32, 1, "C", readonly=True)
_f4_2 = numba.types.Array(numba.float32, 2, "C", readonly=True)


@numba.njit(numba.void(_f4_1, _f4_1, _f4_2, _f4_1, numba.float32[:, ::1]), cache=True, nogil=True)
def world_rays(u: np.ndarray, v: np.ndarray, R: np.ndarray, origin: np.ndarray, rays: np.ndarray) -> None:
    """``rays[k] = (origin, R @ (u[col], v[row], 1))`` for pixel ``k = row * W + col``, each world component
    summed as ``(u R[j,0] + v R[j,1]) + R[j,2]`` in float32 (the renderer's order)."""
    w = u.size
    for r in range(v.size):
        vr = v[r]
        for c in range(w):
            k = r * w + c
            uc = u[c]
            rays[k, 0] = origin[0]
            rays[k, 1] = origin[1]
            rays[k, 2] = origin[2]
            for j in range(3):
                rays[k, 3 + j] = (uc * R[j, 0] + vr * R[j, 1]) + R[j, 2]


@numba.njit(numba.void(_f4_1, numba.types.Array(numba.uint32, 1, "C", readonly=True), numba.int64,
                       numba.types.Array(numba.int32, 1, "C", readonly=True),
                       numba.types.Array(numba.uint8, 2, "C", readonly=True),
                       numba.float32[::1], numba.int32[::1], numba.uint8[:, ::1]), cache=True, nogil=True)
def flat_frame(t_hit: np.ndarray, prim: np.ndarray, miss: int, tri_instance: np.ndarray, tri_rgb: np.ndarray,
               depth: np.ndarray, instances: np.ndarray, rgb: np.ndarray) -> None:
    """Depth (0 where nothing is hit), instance id and flat shaded colour of each pixel from its hit: the
    triangle ``prim[k]`` where ``t_hit[k]`` is finite, else the miss row ``miss`` of the per-triangle tables."""
    for k in range(t_hit.size):
        t = t_hit[k]
        if np.isfinite(t):
            depth[k] = t
            p = np.int64(prim[k])
        else:
            depth[k] = np.float32(0.0)
            p = miss
        instances[k] = tri_instance[p]
        rgb[k, 0] = tri_rgb[p, 0]
        rgb[k, 1] = tri_rgb[p, 1]
        rgb[k, 2] = tri_rgb[p, 2]
