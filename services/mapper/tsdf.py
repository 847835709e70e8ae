"""Volumetric TSDF fusion (Curless & Levoy; Explore-EQA section IV-B) on a dense voxel grid that grows.

The volume covers ``z in [z_min, z_max]`` (-0.2 m .. 3.5 m: the floor plus one storey, ``H`` of section IV-B)
and, horizontally, the bounding box of everything seen so far: when a frame's view frustum leaves the
current box the grid grows by whole chunks, so memory follows the explored area, never the number
of steps. The arrays are views of larger zeroed buffers with room on every side (a quarter of the grid's
extent, at least a chunk): most growth only widens the views, and a buffer is copied into a larger one
(room again on every side) only when the grid outgrows it, so the cost of growth is amortised, not paid by
every frame that sees new territory. The grid itself (origin, shape) and every value are what padding the
arrays by the same chunks gives. Arrays are indexed ``[row (y), col (x), layer (z)]`` with the same rows/cols
as the 2D maps (:class:`eqa.messages.GridSpec`), so the 2D projection is a reduction over the last axis.

Each voxel keeps

* ``tsdf``: running weighted mean of the truncated signed distance ``min(1, (D(u, v) - z_c) / mu)`` along
  the optical axis (the projective TSDF of Zeng's tsdf-fusion that the reference code uses), ``mu`` = the
  truncation (5 voxels). Updates happen where ``D - z_c >= -mu``, i.e. free space up to the surface and a
  band of ``mu`` behind it. Positive = free space, negative = behind a surface.
* ``weight``: number of observations (0 = never observed: unknown, which open3d's VoxelBlockGrid cannot
  represent because it only allocates blocks near surfaces).
* ``explored``: seen through the narrow field of view of appendix B (middle 50 % of the HFOV, lower 50 % of
  the VFOV, measured in angles from the optical axis).

A frame touches only the voxel columns whose (x, y) lies inside the 2D shadow of its view frustum (a
necessary condition for a voxel to be inside the frustum). The per-pixel scan and the per-voxel fusion loop are
compiled (numba, :mod:`services.mapper.tsdf_kernel`, bit-identical to the vectorised numpy code they replaced,
which stays there as the tested specification); the grid bookkeeping around them is numpy.

What follows the volume incrementally (the 2D projection's per-column cache, the snapshot's dirty columns)
reads ``col_stamp``: per column, the number of the last :meth:`TSDFVolume.integrate` that changed one of its
voxels (``stamp`` counts them). The arrays are changed only by ``integrate`` (in place) and ``ensure`` (new
arrays when the grid grows); whoever replaces them (a restore) replaces ``col_stamp`` with them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eqa import grid
from services.mapper import tsdf_kernel

MAX_WEIGHT = np.float32(65535.0)  # observation count cap (snapshots store weights as uint16)


class FrameError(ValueError):
    """A frame that cannot be integrated (the reason is the message)."""


@dataclass(frozen=True)
class VolumeConfig:
    voxel_size: float = 0.1
    trunc_voxels: float = 5.0  # truncation mu = 5 voxels
    z_min: float = -0.2
    z_max: float = 3.5
    max_depth: float = 10.0  # readings beyond are ignored
    min_depth: float = 0.05
    chunk: int = 32  # growth step in cells
    explored_hfov_frac: float = 0.5  # middle 50 % of the HFOV (appendix B)
    explored_vfov_frac: float = 0.5  # lower 50 % of the VFOV (appendix B)

    @property
    def trunc(self) -> float:
        return self.trunc_voxels * self.voxel_size

    @property
    def nz(self) -> int:
        return round((self.z_max - self.z_min) / self.voxel_size)


def check_frame(depth: np.ndarray, intrinsics: np.ndarray, cam_pose: np.ndarray) -> None:
    """Raise :class:`FrameError` with the reason if a depth frame cannot be fused.

    Checked: depth is a 2D float image whose size matches the principal point of the intrinsics, no NaN,
    no negative / ``-inf`` values (``0`` and ``+inf`` mean "no hit", the bus convention), at least one
    usable reading; intrinsics a finite 3x3 pinhole matrix; the pose a finite rigid 4x4 transform
    (orthonormal rotation with determinant +1, last row 0 0 0 1).
    """
    if not isinstance(depth, np.ndarray) or depth.ndim != 2 or depth.dtype.kind != "f":
        raise FrameError(
            f"depth must be an HxW float image, got {getattr(depth, 'shape', None)} "
            f"{getattr(depth, 'dtype', type(depth).__name__)}"
        )
    K = np.asarray(intrinsics, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise FrameError(f"intrinsics must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or K[2, 0] != 0 or K[2, 1] != 0:
        raise FrameError("intrinsics are not a pinhole matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    h, w = depth.shape
    cx, cy = K[0, 2], K[1, 2]
    # The simulator and every pinhole camera put the principal point near the image centre; a depth image
    # of another size than the one the intrinsics describe puts it far off.
    if abs(cx - (w - 1) / 2) > 0.1 * w + 1 or abs(cy - (h - 1) / 2) > 0.1 * h + 1:
        raise FrameError(
            f"depth image is {w}x{h} but the intrinsics' principal point ({cx:.1f}, {cy:.1f}) belongs to "
            f"an image of about {2 * cx + 1:.0f}x{2 * cy + 1:.0f}"
        )
    if np.isnan(depth).any():
        raise FrameError(f"depth has {int(np.isnan(depth).sum())} NaN pixels")
    if (depth < 0).any():
        raise FrameError(f"depth has {int((depth < 0).sum())} negative or -inf pixels")
    if not (np.isfinite(depth) & (depth > 0)).any():
        raise FrameError("depth has no finite positive reading (all pixels are 0 or inf)")
    T = np.asarray(cam_pose, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise FrameError(f"camera pose must be a finite 4x4 matrix, got shape {T.shape}")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise FrameError(f"camera pose last row must be [0 0 0 1], got {T[3].tolist()}")
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > 1e-4 or np.linalg.det(R) < 0:
        raise FrameError(
            f"camera pose is not rigid: |R^T R - I| = {err:.2e}, det(R) = {np.linalg.det(R):.3f}"
        )


def _convex_hull(pts: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of a few 2D points (monotone chain)."""
    p = sorted({(float(x), float(y)) for x, y in pts})
    if len(p) <= 2:
        return np.array(p)

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    for q in p:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    upper: list[tuple[float, float]] = []
    for q in reversed(p):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    return np.array(lower[:-1] + upper[:-1])


def _inside_hull(x: np.ndarray, y: np.ndarray, hull: np.ndarray, margin: float) -> np.ndarray:
    """Points within ``margin`` of a CCW convex polygon (each edge's half plane, pushed out by margin)."""
    inside = np.ones(np.broadcast(x, y).shape, dtype=bool)
    n = len(hull)
    for i in range(n):
        ax, ay = hull[i]
        bx, by = hull[(i + 1) % n]
        ex, ey = bx - ax, by - ay
        norm = math.hypot(ex, ey) or 1.0
        inside &= (ex * (y - ay) - ey * (x - ax)) / norm >= -margin
    return inside


class TSDFVolume:
    """Dense, horizontally growing TSDF + weight + explored volume, plus named 2D planes on the same grid."""

    # the per-voxel fusion loop: compiled; tests swap in tsdf_kernel.integrate_reference (the numpy spec)
    kernel = staticmethod(tsdf_kernel.integrate_columns)

    def __init__(self, config: VolumeConfig | None = None) -> None:
        self.config = config or VolumeConfig()
        c = self.config
        self.origin_x = 0.0
        self.origin_y = 0.0
        self.nz = c.nz
        self.z_centers = c.z_min + (np.arange(self.nz) + 0.5) * c.voxel_size
        self.tsdf = np.zeros((0, 0, self.nz), dtype=np.float32)
        self.weight = np.zeros((0, 0, self.nz), dtype=np.float32)
        self.explored = np.zeros((0, 0, self.nz), dtype=bool)
        # 2D arrays on the same grid that must grow with it (semantic value layers, traversed cells, ...)
        self.planes: dict[str, np.ndarray] = {}
        self.stamp = 0  # integrations that changed a voxel
        self.col_stamp = np.zeros((0, 0), dtype=np.int64)  # per column: the stamp of its last change
        # derived state kept by readers (projection.py), dropped whenever the arrays are replaced
        self.caches: dict[object, object] = {}
        # the buffers the arrays above are views of, and where the views start in them (see the module doc)
        self._bufs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._at = (0, 0)
        self._views: tuple[np.ndarray, ...] | None = None

    # ---- grid ------------------------------------------------------------------------------------------
    @property
    def shape2d(self) -> tuple[int, int]:
        return int(self.tsdf.shape[0]), int(self.tsdf.shape[1])

    @property
    def empty(self) -> bool:
        return self.tsdf.shape[0] == 0

    def cell_of(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of world points (floor division; may be outside the grid)."""
        return grid.cell_of(x, y, (self.origin_x, self.origin_y), self.config.voxel_size)

    def cell_center(self, row: np.ndarray | int, col: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        return grid.cell_center(np.asarray(row), np.asarray(col), (self.origin_x, self.origin_y),
                                self.config.voxel_size)

    def add_plane(self, name: str, fill: float | bool = 0.0, dtype: type = np.float32) -> np.ndarray:
        if name not in self.planes:
            self.planes[name] = np.full(self.shape2d, fill, dtype=dtype)
        return self.planes[name]

    def _sync_stamps(self) -> None:
        """A ``col_stamp`` that does not fit the arrays (they were replaced, e.g. by a restore) starts over."""
        if self.col_stamp.shape != self.shape2d:
            self.col_stamp = np.zeros(self.shape2d, dtype=np.int64)
            self.caches.clear()

    def ensure(self, xmin: float, xmax: float, ymin: float, ymax: float) -> None:
        """Grow the grid (by whole chunks) so it covers the box ``[xmin, xmax] x [ymin, ymax]``."""
        self._sync_stamps()
        c = self.config
        res, chunk = c.voxel_size, c.chunk
        if self.empty:
            cx0 = math.floor(xmin / (res * chunk)) * chunk
            cy0 = math.floor(ymin / (res * chunk)) * chunk
            cx1 = math.ceil(xmax / (res * chunk)) * chunk
            cy1 = math.ceil(ymax / (res * chunk)) * chunk
            self.origin_x, self.origin_y = cx0 * res, cy0 * res
            ny, nx = max(cy1 - cy0, chunk), max(cx1 - cx0, chunk)
            self._bufs = None
            self._place((ny, nx), (0, 0), copy=False)
            self.caches.clear()
            for name, arr in self.planes.items():
                self.planes[name] = np.zeros((ny, nx), dtype=arr.dtype)
            return
        ny, nx = self.shape2d
        r0, c0 = self.cell_of(xmin, ymin)
        r1, c1 = self.cell_of(xmax, ymax)
        top = int(math.ceil(max(0, -int(r0)) / chunk) * chunk)
        left = int(math.ceil(max(0, -int(c0)) / chunk) * chunk)
        bottom = int(math.ceil(max(0, int(r1) - ny + 1) / chunk) * chunk)
        right = int(math.ceil(max(0, int(c1) - nx + 1) / chunk) * chunk)
        if not (top or left or bottom or right):
            return
        pad3 = ((top, bottom), (left, right), (0, 0))
        self._place((ny + top + bottom, nx + left + right), (top, left), copy=True)
        # readers' caches that can grow with the grid (a ``grow(pad, volume)`` method) do; others are dropped
        for key, cache in list(self.caches.items()):
            grow = getattr(cache, "grow", None)
            if grow is None:
                del self.caches[key]
        for name, arr in self.planes.items():
            self.planes[name] = np.pad(arr, pad3[:2])
        self.origin_x -= left * res
        self.origin_y -= top * res
        for cache in self.caches.values():
            cache.grow(pad3[:2], self)  # type: ignore[attr-defined]

    def _owned(self) -> bool:
        """Whether the arrays are still the views of this volume's buffers (a restore replaces them)."""
        return self._views is not None and all(
            a is v for a, v in zip((self.tsdf, self.weight, self.explored, self.col_stamp), self._views, strict=True))

    def _place(self, shape: tuple[int, int], shift: tuple[int, int], copy: bool) -> None:
        """Make the arrays views of ``shape`` (rows, cols) whose cell ``(i, j)`` is the current cell
        ``(i - shift[0], j - shift[1])``, zero where there was none: within the buffers when they have room on
        the sides the grid grows to, else in new buffers with room on every side, the values copied over."""
        ny, nx = shape
        top, left = shift
        old = (self.tsdf, self.weight, self.explored, self.col_stamp) if copy else None
        owned = self._owned()
        r0, c0 = self._at[0] - top, self._at[1] - left
        if not (owned and self._bufs is not None and r0 >= 0 and c0 >= 0
                and r0 + ny <= self._bufs[0].shape[0] and c0 + nx <= self._bufs[0].shape[1]):
            chunk = self.config.chunk
            mr = max(chunk, -(-ny // 4 // chunk) * chunk)  # room on each side, whole chunks
            mc = max(chunk, -(-nx // 4 // chunk) * chunk)
            bufs = (np.zeros((ny + 2 * mr, nx + 2 * mc, self.nz), dtype=np.float32),
                    np.zeros((ny + 2 * mr, nx + 2 * mc, self.nz), dtype=np.float32),
                    np.zeros((ny + 2 * mr, nx + 2 * mc, self.nz), dtype=bool),
                    np.zeros((ny + 2 * mr, nx + 2 * mc), dtype=np.int64))
            if old is not None:  # the current cells, at their place in the grown grid
                oy, ox = old[0].shape[:2]
                for buf, a in zip(bufs, old, strict=True):
                    buf[mr + top: mr + top + oy, mc + left: mc + left + ox] = a
            self._bufs, r0, c0 = bufs, mr, mc
        self._at = (r0, c0)
        self.tsdf, self.weight, self.explored, self.col_stamp = self._views = tuple(  # type: ignore[assignment]
            b[r0: r0 + ny, c0: c0 + nx] for b in self._bufs)

    # ---- fusion ----------------------------------------------------------------------------------------
    def integrate(self, depth: np.ndarray, intrinsics: np.ndarray, cam_pose: np.ndarray) -> int:
        """Fuse one depth image (metres along the optical axis) taken from ``cam_pose`` (camera-to-world,
        OpenCV axes). Returns the number of voxels updated. Call :func:`check_frame` first on untrusted
        input; this function assumes a valid frame."""
        c = self.config
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        K = np.asarray(intrinsics, dtype=np.float64)
        T = np.asarray(cam_pose, dtype=np.float64)
        h, w = depth.shape
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        R, t = T[:3, :3], T[:3, 3]
        # usable readings (finite, within [min_depth, max_depth]; 0 elsewhere) and, per world axis x / y, the
        # extent of the hit points: every updated voxel lies on a ray segment from the camera to a hit point
        # (+ mu behind it), so the box of the camera and the hit points, grown by mu, bounds the update: the
        # volume grows with what is seen, not with the frustum.
        u_dir = (np.arange(w, dtype=np.float32) - np.float32(cx)) / np.float32(fx)
        v_dir = (np.arange(h, dtype=np.float32) - np.float32(cy)) / np.float32(fy)
        dimg = np.empty_like(depth)
        n_usable, dmax, hit_lo, hit_hi = tsdf_kernel.frame_bounds(
            depth, np.float32(c.min_depth), np.float32(c.max_depth), u_dir, v_dir,
            np.ascontiguousarray(R, dtype=np.float32), dimg,
        )
        if not n_usable:
            return 0
        far = min(float(dmax) + c.trunc, c.max_depth + c.trunc)
        lo, hi = t[:2].copy(), t[:2].copy()
        for axis in range(2):
            lo[axis] = min(lo[axis], float(hit_lo[axis]) + t[axis])
            hi[axis] = max(hi[axis], float(hit_hi[axis]) + t[axis])
        margin = c.trunc + c.voxel_size
        self.ensure(lo[0] - margin, hi[0] + margin, lo[1] - margin, hi[1] + margin)
        # 2D shadow of the frustum (camera centre + the four far corners) culls columns inside that box.
        corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
        rays = np.stack([(corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy, np.ones(4)], axis=1) * far
        pts = np.vstack([t, (R @ rays.T).T + t])
        r0, c0 = self.cell_of(lo[0] - margin, lo[1] - margin)
        r1, c1 = self.cell_of(hi[0] + margin, hi[1] + margin)
        ny, nx = self.shape2d
        r0, c0 = max(int(r0), 0), max(int(c0), 0)
        r1, c1 = min(int(r1), ny - 1), min(int(c1), nx - 1)
        rows, cols = np.mgrid[r0 : r1 + 1, c0 : c1 + 1]
        xs, ys = self.cell_center(rows, cols)
        hull = _convex_hull(pts[:, :2])
        keep = (
            _inside_hull(xs, ys, hull, margin=c.voxel_size * 0.75)
            if len(hull) >= 3
            else np.ones_like(xs, bool)
        )
        rows, cols, xs, ys = rows[keep], cols[keep], xs[keep], ys[keep]
        if rows.size == 0:
            return 0

        # camera coordinates: p_c = R^T (p_w - t) = a(col) + z * b
        Rt = R.T
        a = (np.stack([xs - t[0], ys - t[1], np.full_like(xs, -t[2])], axis=1) @ Rt.T).astype(np.float32)
        b = np.ascontiguousarray(Rt[:, 2], dtype=np.float32)
        zc = self.z_centers.astype(np.float32)
        # explored: the narrow view of appendix B, as angles from the optical axis
        half_h = math.atan((w / 2) / fx) * c.explored_hfov_frac
        vfov_lo = -math.atan((cy + 0.5) / fy)  # top edge (negative = up in OpenCV y-down)
        vfov_hi = math.atan((h - cy - 0.5) / fy)
        v_lim = vfov_hi - (vfov_hi - vfov_lo) * c.explored_vfov_frac
        self._sync_stamps()
        self._contiguous()
        n = self.kernel(
            np.ascontiguousarray(a), b, zc,
            np.ascontiguousarray(rows, dtype=np.int64), np.ascontiguousarray(cols, dtype=np.int64),
            np.ascontiguousarray(dimg),
            np.float32(fx), np.float32(fy), np.float32(cx), np.float32(cy),
            float(cx), float(cy), float(fx), float(fy),
            np.float32(c.min_depth), np.float32(c.trunc), MAX_WEIGHT,
            math.tan(half_h), math.tan(v_lim),
            self.tsdf, self.weight, self.explored, self.col_stamp, self.stamp + 1,
        )
        if n:
            self.stamp += 1
        return int(n)

    def _contiguous(self) -> None:
        """The kernel's arrays: views of this volume's buffers (float32 / bool / int64, each voxel column
        contiguous); arrays put in their place (a restore) are copied into new buffers."""
        if not self._owned():
            self._place(self.shape2d, (0, 0), copy=True)

    # ---- memory ----------------------------------------------------------------------------------------
    def nbytes(self) -> int:
        """Bytes held: the buffers (room for growth included) or the arrays, and the planes."""
        arrays = self._bufs if self._owned() else (self.tsdf, self.weight, self.explored, self.col_stamp)
        return int(sum(a.nbytes for a in arrays) + sum(a.nbytes for a in self.planes.values()))
