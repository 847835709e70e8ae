"""Compiled inner loop of :meth:`services.mapper.tsdf.TSDFVolume.integrate` (numba).

Per candidate voxel (the columns inside the frame's 2D frustum shadow, every layer) it does what the
vectorised numpy reference :func:`integrate_reference` does, in the same float32 / float64 arithmetic and
the same order, so the result is bit-identical (tests/mapper/test_tsdf_kernel.py): project the voxel centre
``p_c = a(col) + z * b`` (camera frame), keep it if in front and inside the image, read the depth ``D`` of its
pixel, and where ``D > 0`` and ``D - z_c >= -mu`` update the projective TSDF as the running weighted mean of
``min(1, (D - z_c) / mu)`` (Curless & Levoy eq. 2-3; Explore-EQA section IV-B), stamp the column, and mark
the voxel explored if it falls inside the narrow view of appendix B.

The numpy version materialises ~10 (ncols, nz) float32 arrays per frame (~170 k candidates at 640x480) and
gathers / scatters through flat indices; the kernel visits each candidate once without temporaries.

Compilation: eager (explicit signatures) with ``cache=True``, so importing this module either loads the
machine code from numba's cache (~0.1 s, plus ~0.3 s to import numba) or compiles it once (~1 s) and writes
the cache; the first frame a mapper integrates after a start or restart never pays for compilation.
The cache never goes into the source tree (a read-only install cannot write there, a checkout would get
dirty): ``NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/eqa/numba`` (``~/.cache/eqa/numba``), else
``<temp dir>/eqa-numba-cache-<uid>`` (with none of them writable, numba's own fallbacks apply). The
container image sets ``NUMBA_CACHE_DIR`` and compiles at build time (Dockerfile), so a container's first
start does not compile.
"""

from __future__ import annotations

import numba
import numpy as np

from eqa.numba_cache import choose_cache_dir

choose_cache_dir()  # before the eager njit calls below (eqa.numba_cache)


def _ro(dtype: object, ndim: int) -> object:
    """A read-only C-contiguous array type: inputs may be read-only (a depth image decoded off the bus is a
    view of the message bytes); writable arrays are accepted too."""
    return numba.types.Array(dtype, ndim, "C", readonly=True)


_SIG = numba.int64(
    _ro(numba.float32, 2),  # a: (ncols, 3) camera-frame offset of each column's axis (float32)
    _ro(numba.float32, 1),  # b: (3,) camera-frame direction of world z (float32)
    _ro(numba.float32, 1),  # zc: (nz,) layer centres (float32)
    _ro(numba.int64, 1),  # rows
    _ro(numba.int64, 1),  # cols
    _ro(numba.float32, 2),  # dimg: (h, w) depth, 0 where unusable
    numba.float32,  # fx
    numba.float32,  # fy
    numba.float32,  # cx
    numba.float32,  # cy
    numba.float64,  # cx (float64, explored test)
    numba.float64,  # cy
    numba.float64,  # fx
    numba.float64,  # fy
    numba.float32,  # min_depth
    numba.float32,  # trunc
    numba.float32,  # max_weight
    numba.float64,  # tan of half the explored HFOV
    numba.float64,  # tan of the explored VFOV's upper limit
    # the volume's arrays are views of larger buffers (TSDFVolume: room for growth), so any layout
    numba.types.Array(numba.float32, 3, "A"),  # tsdf (ny, nx, nz), updated in place
    numba.types.Array(numba.float32, 3, "A"),  # weight
    numba.types.Array(numba.boolean, 3, "A"),  # explored
    numba.types.Array(numba.int64, 2, "A"),  # col_stamp (ny, nx)
    numba.int64,  # stamp to write into the changed columns
)


@numba.njit(_SIG, cache=True, nogil=True)
def integrate_columns(
    a, b, zc, rows, cols, dimg, fx, fy, cx, cy, cx64, cy64, fx64, fy64,
    min_depth, trunc, max_weight, tan_h, tan_v, tsdf, weight, explored, col_stamp, stamp,
):  # pragma: no cover - compiled; tested against integrate_reference
    """Fuse one frame into the candidate columns; returns the number of voxels updated.

    Every float32 operation is the numpy reference's, in its order (no fused multiply-add: numba does not
    contract without fastmath); ``np.rint`` rounds half to even like numpy's.
    """
    h, w = dimg.shape
    nz = zc.shape[0]
    neg_trunc = -trunc
    one = np.float32(1.0)
    count = 0
    for i in range(rows.shape[0]):
        r = rows[i]
        c = cols[i]
        a0 = a[i, 0]
        a1 = a[i, 1]
        a2 = a[i, 2]
        changed = False
        for k in range(nz):
            z = zc[k]
            Z = a2 + z * b[2]
            if not (min_depth < Z):
                continue
            X = a0 + z * b[0]
            Y = a1 + z * b[1]
            uf = X / Z * fx + cx
            vf = Y / Z * fy + cy
            ur = np.rint(uf)
            vr = np.rint(vf)
            # out-of-range floats: numpy's int32 cast gives INT_MIN (out of view); compare as floats instead
            if not (ur >= 0 and ur < w and vr >= 0 and vr < h):
                continue
            d = dimg[int(vr), int(ur)]
            if not (d > 0):
                continue
            sdf = d - Z
            if not (sdf >= neg_trunc):
                continue
            obs = min(one, sdf / trunc)
            w_old = weight[r, c, k]
            w_new = min(w_old + one, max_weight)
            tsdf[r, c, k] = (tsdf[r, c, k] * w_old + obs) / w_new
            weight[r, c, k] = w_new
            count += 1
            changed = True
            u_rel = (np.float64(uf) - cx64) / fx64
            v_rel = (np.float64(vf) - cy64) / fy64
            if abs(u_rel) <= tan_h and v_rel >= tan_v:
                explored[r, c, k] = True
        if changed:
            col_stamp[r, c] = stamp
    return count


_BOUNDS_SIG = numba.types.Tuple((numba.int64, numba.float32, numba.float32[:], numba.float32[:]))(
    _ro(numba.float32, 2),  # depth (h, w), float32
    numba.float32,  # min_depth
    numba.float32,  # max_depth
    _ro(numba.float32, 1),  # u: (w,) (column - cx) / fx, float32
    _ro(numba.float32, 1),  # v: (h,) (row - cy) / fy, float32
    _ro(numba.float32, 2),  # R (3, 3) float32 (rows 0 and 1 used)
    numba.float32[:, ::1],  # out: dimg (h, w), depth where usable else 0
)


@numba.njit(_BOUNDS_SIG, cache=True, nogil=True)
def frame_bounds(depth, min_depth, max_depth, u, v, R, dimg):  # pragma: no cover - compiled
    """One pass over the image: ``dimg`` (usable depth, 0 elsewhere), its maximum, and per world axis x, y
    the min / max over hit pixels of ``dir_axis(u, v) * D`` (the hit's offset from the camera), where
    ``dir_axis = R[axis, 0] * u + R[axis, 1] * v + R[axis, 2]`` in float32 as numpy computes it. No usable
    pixel: max 0 and the bounds stay +inf / -inf. Returns (usable pixels, max, lo[2], hi[2])."""
    h, w = depth.shape
    lo = np.full(2, np.inf, dtype=np.float32)
    hi = np.full(2, -np.inf, dtype=np.float32)
    dmax = np.float32(0.0)
    n = 0
    for r in range(h):
        vr = v[r]
        for c in range(w):
            d = depth[r, c]
            if not (np.isfinite(d) and d >= min_depth and d <= max_depth):
                dimg[r, c] = np.float32(0.0)
                continue
            dimg[r, c] = d
            n += 1
            if d > dmax:
                dmax = d
            if not (d > 0):
                continue
            for axis in range(2):
                x = (R[axis, 0] * u[c] + R[axis, 1] * vr + R[axis, 2]) * d
                if x < lo[axis]:
                    lo[axis] = x
                if x > hi[axis]:
                    hi[axis] = x
    return n, dmax, lo, hi


def integrate_reference(
    a: np.ndarray, b: np.ndarray, zc: np.ndarray, rows: np.ndarray, cols: np.ndarray, dimg: np.ndarray,
    fx: np.float32, fy: np.float32, cx: np.float32, cy: np.float32,
    cx64: float, cy64: float, fx64: float, fy64: float,
    min_depth: np.float32, trunc: np.float32, max_weight: np.float32,
    tan_h: float, tan_v: float, tsdf: np.ndarray, weight: np.ndarray, explored: np.ndarray,
    col_stamp: np.ndarray, stamp: int,
) -> int:
    """The vectorised numpy version (the code integrate ran before the kernel): the specification the
    kernel is tested against (tests/mapper/test_tsdf_kernel.py). Same arguments as :func:`integrate_columns`, so
    it can stand in for it (``TSDFVolume.kernel``); arrays updated in place; returns the voxels updated."""
    h, w = dimg.shape
    nz = zc.shape[0]
    X = a[:, 0, None] + zc[None, :] * b[0]
    Y = a[:, 1, None] + zc[None, :] * b[1]
    Z = a[:, 2, None] + zc[None, :] * b[2]
    front = min_depth < Z
    Zs = np.where(front, Z, np.float32(1.0))
    uf = X / Zs * fx + cx
    vf = Y / Zs * fy + cy
    u = np.rint(uf).astype(np.int32)
    v = np.rint(vf).astype(np.int32)
    inview = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    pix = np.where(inview, v * w + u, 0)
    d = dimg.reshape(-1)[pix]
    sdf = d - Z
    upd = inview & (d > 0) & (sdf >= -trunc)
    sel = np.flatnonzero(upd)
    if sel.size == 0:
        return 0
    ci, ki = np.divmod(sel, nz)
    obs = np.minimum(np.float32(1.0), sdf.reshape(-1)[sel] / trunc)
    vox = (rows[ci], cols[ci], ki)  # indexed, not flat: the arrays may be views of larger buffers
    w_old = weight[vox]
    w_new = np.minimum(w_old + 1.0, max_weight)
    tsdf[vox] = (tsdf[vox] * w_old + obs) / w_new
    weight[vox] = w_new
    col_stamp[rows[ci], cols[ci]] = stamp
    u_rel = (uf.reshape(-1)[sel] - np.float64(cx64)) / np.float64(fx64)
    v_rel = (vf.reshape(-1)[sel] - np.float64(cy64)) / np.float64(fy64)
    narrow = (np.abs(u_rel) <= tan_h) & (v_rel >= tan_v)
    explored[rows[ci][narrow], cols[ci][narrow], ki[narrow]] = True
    return int(ci.size)
