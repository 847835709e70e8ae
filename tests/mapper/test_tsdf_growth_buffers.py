"""TSDF grid growth within buffers with room: the same grid and values as padding the arrays at every growth."""

from __future__ import annotations

import numpy as np

from services.mapper.tsdf import TSDFVolume


def _padded(old: dict[str, np.ndarray], old_origin: tuple[float, float], vol: TSDFVolume) -> dict[str, np.ndarray]:
    """``old`` padded with zeros to ``vol``'s grid (what growing by ``np.pad`` gives)."""
    res = vol.config.voxel_size
    top = round((old_origin[1] - vol.origin_y) / res)
    left = round((old_origin[0] - vol.origin_x) / res)
    ny, nx = vol.shape2d
    out = {}
    for name, a in old.items():
        pad = [(top, ny - a.shape[0] - top), (left, nx - a.shape[1] - left)] + [(0, 0)] * (a.ndim - 2)
        out[name] = np.pad(a, pad)
    return out


def _arrays(vol: TSDFVolume) -> dict[str, np.ndarray]:
    return {"tsdf": vol.tsdf.copy(), "weight": vol.weight.copy(), "explored": vol.explored.copy(),
            "col_stamp": vol.col_stamp.copy()}


def test_growth_in_every_direction_keeps_values_and_reuses_the_buffers() -> None:
    rng = np.random.default_rng(0)
    vol = TSDFVolume()
    vol.ensure(0.0, 3.0, 0.0, 3.0)
    boxes = [(-1.0, 3.0, 0.0, 3.0), (-1.0, 6.5, 0.0, 3.0), (-1.0, 6.5, -4.0, 3.0), (-1.0, 6.5, -4.0, 9.0),
             (-9.0, 6.5, -4.0, 9.0), (-9.0, 20.0, -15.0, 25.0), (-9.0, 20.0, -15.0, 25.0)]
    reused = moved = 0
    for box in boxes:
        # values everywhere in the grid, written through the views (as the kernel writes them)
        vol.tsdf[...] = rng.standard_normal(vol.tsdf.shape).astype(np.float32)
        vol.weight[...] = rng.integers(0, 5, vol.weight.shape).astype(np.float32)
        vol.explored[...] = rng.random(vol.explored.shape) < 0.3
        vol.col_stamp[...] = rng.integers(0, 9, vol.col_stamp.shape)
        before, origin, bufs = _arrays(vol), (vol.origin_x, vol.origin_y), vol._bufs
        vol.ensure(*box)
        want = _padded(before, origin, vol)
        for name, a in _arrays(vol).items():
            assert a.shape == want[name].shape and a.dtype == want[name].dtype, name
            assert np.array_equal(a, want[name]), name
        lo_r, lo_c = vol.cell_of(box[0], box[2])
        hi_r, hi_c = vol.cell_of(box[1], box[3])
        assert min(int(lo_r), int(lo_c)) >= 0 and int(hi_r) < vol.shape2d[0] and int(hi_c) < vol.shape2d[1]
        assert vol.shape2d[0] % vol.config.chunk == 0 and vol.shape2d[1] % vol.config.chunk == 0
        if vol.shape2d != before["tsdf"].shape[:2]:
            reused += vol._bufs is bufs
            moved += vol._bufs is not bufs
    assert reused >= 1 and moved >= 1  # growth within the room and growth that outgrew it both happened
    # the room is never more than the grid plus half of it on each axis (plus a chunk a side)
    by, bx = vol._bufs[0].shape[:2]
    ny, nx = vol.shape2d
    assert by <= ny + 2 * max(vol.config.chunk, ny // 4 + vol.config.chunk)
    assert bx <= nx + 2 * max(vol.config.chunk, nx // 4 + vol.config.chunk)


def test_arrays_put_in_place_of_the_views_are_taken_into_new_buffers() -> None:
    vol = TSDFVolume()
    vol.ensure(0.0, 3.0, 0.0, 3.0)
    shape = vol.tsdf.shape
    restored = np.arange(np.prod(shape), dtype=np.float32).reshape(shape)  # as a restore assigns them
    vol.tsdf = restored.copy()
    vol.weight = np.ones(shape, np.float32)
    vol.explored = np.zeros(shape, bool)
    vol.col_stamp = np.zeros(shape[:2], np.int64)
    origin = (vol.origin_x, vol.origin_y)
    vol.ensure(-2.0, 3.0, 0.0, 3.0)
    assert vol._owned()
    want = _padded({"tsdf": restored, "weight": np.ones(shape, np.float32)}, origin, vol)
    assert np.array_equal(vol.tsdf, want["tsdf"]) and np.array_equal(vol.weight, want["weight"])
    vol.weight[0, 0, 0] = 7.0  # the views write into the buffers the kernel is given
    vol._contiguous()
    assert vol._owned() and vol._bufs[1][vol._at[0], vol._at[1], 0] == 7.0
