"""The compiled TSDF integrate kernel equals the numpy reference bit for bit.

Two volumes, one with the numba kernel (the default) and one with ``tsdf_kernel.integrate_reference`` (the
vectorised numpy code integrate ran before), fuse the same random frames (planes, noise, holes, ``inf`` and
out-of-range readings, random poses that make the grid grow); after every frame tsdf, weight, explored, the
column stamps and the returned counts must be identical.
"""

from __future__ import annotations

import numpy as np

from services.mapper import tsdf_kernel
from services.mapper.tsdf import TSDFVolume


def _pose(rng: np.random.Generator) -> np.ndarray:
    yaw = rng.uniform(-np.pi, np.pi)
    pitch = rng.uniform(-0.5, 0.3)
    # OpenCV camera (x right, y down, z forward) looking horizontally along world +x, then yaw / pitch
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cp, sp = np.cos(pitch), np.sin(pitch)
    pitch_m = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    cy, sy = np.cos(yaw), np.sin(yaw)
    yaw_m = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = yaw_m @ base @ pitch_m
    T[:3, 3] = [rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(0.8, 1.6)]
    return T


def _depth(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    v, u = np.mgrid[0:h, 0:w]
    d = rng.uniform(1.0, 6.0) + rng.uniform(-2, 2) * u / w + rng.uniform(-1, 1) * v / h
    d = d + rng.normal(0, 0.02, (h, w))
    d = np.clip(d, 0.2, None).astype(np.float32)
    d[rng.random((h, w)) < 0.05] = 0.0
    d[rng.random((h, w)) < 0.02] = np.inf
    d[rng.random((h, w)) < 0.02] = 12.0  # beyond max_depth
    return d


def test_kernel_equals_numpy_reference_on_random_frames() -> None:
    rng = np.random.default_rng(20)
    h, w = 60, 80
    K = np.array([[w / 2 / np.tan(np.radians(45)), 0, (w - 1) / 2], [0, w / 2 / np.tan(np.radians(45)), (h - 1) / 2],
                  [0, 0, 1.0]])
    fast, ref = TSDFVolume(), TSDFVolume()
    ref.kernel = tsdf_kernel.integrate_reference  # type: ignore[method-assign]
    total = 0
    for _ in range(25):
        depth, T = _depth(rng, h, w), _pose(rng)
        n_fast = fast.integrate(depth, K, T)
        n_ref = ref.integrate(depth, K, T)
        assert n_fast == n_ref
        total += n_fast
        assert fast.stamp == ref.stamp
        assert (fast.origin_x, fast.origin_y) == (ref.origin_x, ref.origin_y)
        for name in ("tsdf", "weight", "explored", "col_stamp"):
            a, b = getattr(fast, name), getattr(ref, name)
            assert a.shape == b.shape, name
            assert a.tobytes() == b.tobytes(), f"{name} differs"
    assert total > 1000 and fast.explored.any()


def test_repeated_frame_reaches_the_weight_cap() -> None:
    """The weight saturates at MAX_WEIGHT in both (cap path exercised with a pre-filled weight)."""
    rng = np.random.default_rng(3)
    h, w = 30, 40
    K = np.array([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1.0]])
    depth, T = _depth(rng, h, w), _pose(rng)
    fast, ref = TSDFVolume(), TSDFVolume()
    ref.kernel = tsdf_kernel.integrate_reference  # type: ignore[method-assign]
    fast.integrate(depth, K, T)
    ref.integrate(depth, K, T)
    for vol in (fast, ref):
        vol.weight[vol.weight > 0] = 65534.0
    for _ in range(2):
        assert fast.integrate(depth, K, T) == ref.integrate(depth, K, T)
    assert fast.weight.max() == 65535.0
    assert fast.tsdf.tobytes() == ref.tsdf.tobytes() and fast.weight.tobytes() == ref.weight.tobytes()


def test_kernel_equals_reference_on_lattice_frames() -> None:
    """Axis-aligned cameras on voxel centres and depths in 5 cm steps put many voxels exactly on the
    boundaries (``D - z_c == -mu``, pixel centres, the explored view's edges) where float32 vs float64 or
    ``>`` vs ``>=`` decide."""
    rng = np.random.default_rng(11)
    h, w = 48, 64
    K = np.array([[32.0, 0, (w - 1) / 2], [0, 32.0, (h - 1) / 2], [0, 0, 1.0]])
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    fast, ref = TSDFVolume(), TSDFVolume()
    ref.kernel = tsdf_kernel.integrate_reference  # type: ignore[method-assign]
    for i in range(16):
        yaw = (i % 4) * np.pi / 2
        c, s = round(np.cos(yaw)), round(np.sin(yaw))
        T = np.eye(4)
        T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ base
        T[:3, 3] = [0.05 + 0.1 * rng.integers(-5, 5), 0.05 + 0.1 * rng.integers(-5, 5), 1.25]
        depth = (0.05 * rng.integers(10, 80, (h, w))).astype(np.float32)
        depth[:, : w // 2] = np.float32(0.05 * rng.integers(10, 80))
        assert fast.integrate(depth, K, T) == ref.integrate(depth, K, T)
        for name in ("tsdf", "weight", "explored", "col_stamp"):
            assert getattr(fast, name).tobytes() == getattr(ref, name).tobytes(), f"{name} differs"


def test_frame_bounds_equals_numpy() -> None:
    """The one-pass image scan gives integrate's former numpy values: the usable depth image, its maximum and
    the extent of the hit points along world x and y (float32, as before)."""
    rng = np.random.default_rng(5)
    h, w = 60, 80
    K = np.array([[40.0, 0, (w - 1) / 2], [0, 40.0, (h - 1) / 2], [0, 0, 1.0]])
    for i in range(10):
        depth, T = _depth(rng, h, w), _pose(rng)
        if i == 9:
            depth[:] = np.inf  # nothing usable
        R = T[:3, :3]
        u = (np.arange(w, dtype=np.float32) - np.float32(K[0, 2])) / np.float32(K[0, 0])
        v = (np.arange(h, dtype=np.float32) - np.float32(K[1, 2])) / np.float32(K[1, 1])
        dimg = np.empty_like(depth)
        n, dmax, lo, hi = tsdf_kernel.frame_bounds(depth, np.float32(0.05), np.float32(10.0), u, v,
                                                   np.ascontiguousarray(R, dtype=np.float32), dimg)
        usable = np.isfinite(depth) & (depth >= 0.05) & (depth <= 10.0)
        ref = np.where(usable, depth, np.float32(0.0))
        assert n == usable.sum() and dimg.tobytes() == ref.tobytes() and dmax == ref.max()
        Rf = R.astype(np.float32)
        for axis in range(2):
            coord = (Rf[axis, 0] * u[None, :] + Rf[axis, 1] * v[:, None] + Rf[axis, 2]) * ref
            assert lo[axis] == coord.min(where=ref > 0, initial=np.float32(np.inf))
            assert hi[axis] == coord.max(where=ref > 0, initial=np.float32(-np.inf))


def test_read_only_frame() -> None:
    """A depth image decoded off the bus is a read-only view of the message: integrate takes it as it is."""
    rng = np.random.default_rng(7)
    h, w = 30, 40
    K = np.array([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1.0]])
    depth, T = _depth(rng, h, w), _pose(rng)
    frozen = np.frombuffer(depth.tobytes(), dtype=np.float32).reshape(h, w)
    assert not frozen.flags.writeable
    fast, ref = TSDFVolume(), TSDFVolume()
    ref.kernel = tsdf_kernel.integrate_reference  # type: ignore[method-assign]
    assert fast.integrate(frozen, K, T) == ref.integrate(depth, K, T) > 0
    assert fast.tsdf.tobytes() == ref.tsdf.tobytes()
