"""The TSDF's values against hand-computed ones on a scene simple enough to work out on paper.

A camera 1 m above the floor looks horizontally along world +x at a fronto-parallel wall 3 m away: every
usable pixel reads depth ``D = 3.0``. A voxel whose centre is at ``x`` in front of the camera has
``z_c = x`` (depth along the optical axis), so the projective TSDF of section IV-B is

    tsdf = min(1, (D - x) / mu),   updated only where D - x >= -mu,

with the truncation ``mu = trunc_voxels * voxel_size = 0.5 m``. The signed distance ramps from +1 (free space
0.5 m or more in front of the wall) through 0 at the wall to -1 at 0.5 m behind it; voxels deeper behind the
wall are never observed (weight 0). A different truncation (e.g. half of it) moves the ramp and the band
and fails here.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.mapper import tsdf_kernel
from services.mapper.tsdf import TSDFVolume, VolumeConfig

WALL = 3.0
H, W = 48, 64


def _camera() -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[32.0, 0.0, (W - 1) / 2], [0.0, 32.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    # OpenCV axes: camera x = world -y, camera y = world -z, camera z (optical axis) = world +x
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = [0.0, 0.0, 1.0]
    return K, T


def _volume(kernel: object) -> tuple[TSDFVolume, VolumeConfig]:
    config = VolumeConfig()
    vol = TSDFVolume(config)
    vol.kernel = kernel  # type: ignore[assignment]
    K, T = _camera()
    depth = np.full((H, W), WALL, dtype=np.float32)
    assert vol.integrate(depth, K, T) > 0
    return vol, config


@pytest.mark.parametrize("kernel", [tsdf_kernel.integrate_columns, tsdf_kernel.integrate_reference],
                         ids=["compiled", "reference"])
def test_signed_distances_and_truncation_band_on_the_optical_axis(kernel: object) -> None:
    vol, config = _volume(kernel)
    assert config.trunc == pytest.approx(0.5)
    mu = 0.5
    row, _ = vol.cell_of(0.0, 0.0)
    layer = int(np.argmin(np.abs(vol.z_centers - 0.95)))  # the layer whose centre is 0.95 m (camera at 1 m)
    assert vol.z_centers[layer] == pytest.approx(0.95)
    checked = 0
    for x in np.arange(0.55, 4.5, 0.1):
        r, c = vol.cell_of(x, 0.0)
        assert int(r) == int(row)
        cx, _ = vol.cell_center(r, c)
        cx = float(cx)
        sdf = WALL - cx
        tsdf = float(vol.tsdf[int(r), int(c), layer])
        weight = float(vol.weight[int(r), int(c), layer])
        if sdf >= -mu + 1e-6:
            assert weight == 1.0, f"voxel at x={cx:.2f} (D - z = {sdf:+.2f}) must be observed once"
            assert tsdf == pytest.approx(min(1.0, sdf / mu), abs=1e-5), f"x={cx:.2f}"
        else:
            assert weight == 0.0, f"voxel at x={cx:.2f} is {-sdf:.2f} m behind the wall: outside the band"
            assert tsdf == 0.0
        checked += 1
    assert checked >= 35


def test_values_at_hand_picked_distances() -> None:
    """The ramp at four distances from the wall: 0.45 m in front -> 0.9, 0.05 m in front -> 0.1, 0.05 m
    behind -> -0.1, 0.45 m behind -> -0.9; 0.55 m behind is not observed."""
    vol, _ = _volume(tsdf_kernel.integrate_columns)
    layer = int(np.argmin(np.abs(vol.z_centers - 0.95)))
    expected = {2.55: (0.9, 1.0), 2.95: (0.1, 1.0), 3.05: (-0.1, 1.0), 3.45: (-0.9, 1.0), 3.55: (0.0, 0.0),
                1.05: (1.0, 1.0)}
    for x, (tsdf, weight) in expected.items():
        r, c = vol.cell_of(x, 0.0)
        cx, _ = vol.cell_center(r, c)
        assert float(cx) == pytest.approx(x), "cell centres sit on 0.05 + 0.1 k"
        assert float(vol.tsdf[int(r), int(c), layer]) == pytest.approx(tsdf, abs=1e-5), f"x={x}"
        assert float(vol.weight[int(r), int(c), layer]) == weight, f"x={x}"


def test_a_second_identical_frame_keeps_the_values_and_doubles_the_weight() -> None:
    """Eq. 2-3 of Curless & Levoy: the running weighted mean of equal observations is the observation."""
    vol, _ = _volume(tsdf_kernel.integrate_columns)
    before = vol.tsdf.copy()
    K, T = _camera()
    vol.integrate(np.full((H, W), WALL, dtype=np.float32), K, T)
    observed = vol.weight > 0
    np.testing.assert_allclose(vol.tsdf[observed], before[observed], atol=1e-6)
    assert set(np.unique(vol.weight[observed]).tolist()) == {2.0}
