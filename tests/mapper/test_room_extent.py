"""The asked room's extent from the robot's own map and the scorer's IN_ROOM answers (mapper/room_extent.py)."""

from __future__ import annotations

import numpy as np
import pytest

from services.mapper.room_extent import RoomExtent

RES = 0.1


def _down_camera(x: float, y: float, size_px: int = 40, f: float = 20.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A camera 1.5 m above (x, y) looking straight down at the floor: depth 1.5 m, a 3 m x 3 m floor patch."""
    K = np.array([[f, 0, size_px / 2], [0, f, size_px / 2], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # optical axis along -z (down)
    T[:3, 3] = [x, y, 1.5]
    return np.full((size_px, size_px), 1.5, np.float32), K, T


def _maps(shape: tuple[int, int] = (80, 80)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Everything explored and free inside walls one cell thick around the grid."""
    occupied = np.zeros(shape, bool)
    occupied[0, :] = occupied[-1, :] = occupied[:, 0] = occupied[:, -1] = True
    return np.ones(shape, bool), ~occupied, occupied


def test_cells_seen_in_room_views_form_the_room():
    ext = RoomExtent()
    explored, free, occupied = _maps()
    ext.update(*_down_camera(4.0, 4.0), 0.9, explored, free, occupied, (0.0, 0.0), RES)
    assert not ext.room_mask().any()  # 0.9 of a vote is not yet one
    ext.update(*_down_camera(4.0, 4.0), 0.9, explored, free, occupied, (0.0, 0.0), RES)
    room = ext.room_mask()
    assert room is not None
    ys, xs = np.nonzero(room)
    assert 2.2 < xs.min() * RES < 2.8 and 5.2 < xs.max() * RES < 5.8  # the 3 m patch around x = 4 m
    assert 2.2 < ys.min() * RES < 2.8 and 5.2 < ys.max() * RES < 5.8
    cov = ext.coverage(min_area_m2=2.0, max_open=0.2)
    assert 7.0 < cov.area_m2 < 11.0 and cov.open_share == 0.0 and cov.observed
    assert not ext.coverage(min_area_m2=20.0, max_open=0.2).observed


def test_one_misjudged_view_is_outvoted():
    ext = RoomExtent()
    explored, free, occupied = _maps()
    cam = _down_camera(4.0, 4.0)
    ext.update(*cam, 1.0, explored, free, occupied, (0.0, 0.0), RES)  # wrongly "in the room"
    assert ext.room_mask().any()
    ext.update(*cam, 0.1, explored, free, occupied, (0.0, 0.0), RES)
    ext.update(*cam, 0.2, explored, free, occupied, (0.0, 0.0), RES)
    assert not ext.room_mask().any()
    assert not ext.coverage(0.0, 1.0).observed
    none = RoomExtent()
    none.update(*cam, None, explored, free, occupied, (0.0, 0.0), RES)  # not asked: no vote
    assert not none.room_mask().any()


def test_a_room_with_frontiers_in_it_is_not_observed():
    ext = RoomExtent()
    explored, free, occupied = _maps()
    explored[:, 45:] = False  # the right part of the room is unexplored: a frontier along column 44
    ext.update(*_down_camera(4.0, 4.0), 1.0, explored, free, occupied, (0.0, 0.0), RES)
    cov = ext.coverage(min_area_m2=2.0, max_open=0.2)
    assert cov.open_share > 0.2 and not cov.observed


def test_the_room_stays_in_place_when_the_grid_grows():
    ext = RoomExtent()
    explored, free, occupied = _maps()
    ext.update(*_down_camera(4.0, 4.0), 1.0, explored, free, occupied, (0.0, 0.0), RES)
    before = np.argwhere(ext.room_mask())
    assert before.size
    big = _maps((100, 120))
    ext.update(*_down_camera(4.0, 4.0), None, *big, (-2.0, -1.0), RES)  # 10 rows and 20 columns added before
    after = np.argwhere(ext.room_mask())
    assert after.shape == before.shape and (after - before == [10, 20]).all()
    with pytest.raises(ValueError):
        ext.update(*_down_camera(4.0, 4.0), 0.9, *big, (0.0, 0.0), 0.05)


def test_bad_maps_are_refused():
    ext = RoomExtent()
    explored, free, occupied = _maps()
    with pytest.raises(ValueError):
        ext.update(*_down_camera(4.0, 4.0), 0.9, explored[:10], free, occupied, (0.0, 0.0), RES)
    with pytest.raises(ValueError):
        ext.update(*_down_camera(4.0, 4.0), 0.9, explored, free, occupied, (0.0, 0.0), 0.0)
    with pytest.raises(ValueError):
        RoomExtent(min_votes=0.0)


def test_the_extent_survives_the_mappers_stored_state():
    """RoomExtent.state -> the store's codec -> from_state: the same votes, and with the next maps the same room
    (a restarted mapper continues counting across views in the room)."""
    from eqa.codec import packb, unpackb
    from services.mapper.room_extent import room_vote

    ext = RoomExtent()
    explored, free, occupied = _maps()
    for _ in range(2):
        ext.update(*_down_camera(4.0, 4.0), 0.9, explored, free, occupied, (0.0, 0.0), RES)
    back = RoomExtent.from_state(unpackb(packb(ext.state())))
    assert np.array_equal(back.votes_in, ext.votes_in) and np.array_equal(back.votes_out, ext.votes_out)
    back.update(*_down_camera(4.0, 4.0), None, explored, free, occupied, (0.0, 0.0), RES)
    assert np.array_equal(back.room_mask(), ext.room_mask())
    assert back.coverage(2.0, 0.2) == ext.coverage(2.0, 0.2)
    assert RoomExtent.from_state(unpackb(packb(RoomExtent().state()))).room_mask() is None
    assert room_vote(0.3, "kitchen") == 0.3 and room_vote(None, None) == 1.0  # the whole house: every view
