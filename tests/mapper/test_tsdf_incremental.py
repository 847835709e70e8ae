"""The projection that follows what a frame changed equals reducing the whole grid, step by step,
across grid growth; the change stamps mark exactly the columns whose voxels changed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from support.scenes import free_cell_walk

from eqa.messages import Pose2D
from services.mapper.projection import project
from services.mapper.tsdf import TSDFVolume
from services.sim.camera import camera_pose, intrinsics
from services.sim.library import load_or_generate
from services.sim.render import Renderer

W, H = 160, 120


@pytest.fixture(scope="module")
def views(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, Pose2D]]:
    scene = load_or_generate("gen-00007", Path(tmp_path_factory.mktemp("scenes")))
    renderer = Renderer(scene)
    K = intrinsics(W, H)
    out = []
    for pose in free_cell_walk(scene, 16, seed=3, turn_rad=2.3):
        T = camera_pose(pose)
        out.append((renderer.render(T, K, W, H).depth, K, T, pose))
    return out


def test_incremental_projection_equals_whole_grid(views: list) -> None:
    vol = TSDFVolume()
    vol.add_plane("traversed", False, bool)
    shapes = set()
    for i, (depth, K, T, pose) in enumerate(views):
        vol.integrate(depth, K, T)
        vol.planes["traversed"][i % 7 :: 9, ::11] = True
        shapes.add(vol.shape2d)
        inc = project(vol, (pose.x, pose.y))
        caches, vol.caches = vol.caches, {}
        whole = project(vol, (pose.x, pose.y))  # no cache: every column reduced
        vol.caches = caches
        for name in ("occupied", "free", "free_all", "explored", "observed"):
            assert np.array_equal(getattr(inc, name), getattr(whole, name)), (i, name)
    assert len(shapes) > 2, "the views should make the grid grow"


def test_stamps_mark_exactly_the_changed_columns(views: list) -> None:
    vol = TSDFVolume()
    checked = 0
    for depth, K, T, _ in views[:10]:
        before = (vol.tsdf.copy(), vol.weight.copy(), vol.explored.copy(), vol.shape2d)
        stamp = vol.stamp
        vol.integrate(depth, K, T)
        if before[3] != vol.shape2d:
            continue  # grown: the old arrays do not line up; the next view checks
        changed = ((before[0] != vol.tsdf) | (before[1] != vol.weight) | (before[2] != vol.explored)).any(axis=2)
        assert np.array_equal(changed | (vol.col_stamp > stamp), vol.col_stamp > stamp)
        # a stamped column had a voxel updated (its weight grew), even when its values came out the same
        assert ((before[1] != vol.weight).any(axis=2) == (vol.col_stamp > stamp)).all()
        checked += 1
    assert checked >= 2
