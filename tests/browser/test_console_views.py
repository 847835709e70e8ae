"""The console's images (gateway/views.py): where things land on the map and on the camera view, what the
cache keeps. Pure numpy + Pillow, no fleet."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from eqa.messages import Frame, Frontier, Goal, GridSpec, MapUpdate, Pose2D, PromptPoint
from gateway import views


def _img(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def _frame(eid: str, step: int, x: float = 1.0, y: float = 1.0) -> Frame:
    return Frame(
        episode_id=eid, step=step, pose=Pose2D(x=x, y=y), camera_pose=np.eye(4), intrinsics=np.eye(3),
        rgb=np.zeros((120, 160, 3), np.uint8), depth=np.zeros((120, 160), np.float32),
    )


def _map(eid: str, step: int, points: list[PromptPoint] | None = None) -> MapUpdate:
    rows, cols = 40, 80  # 0.1 m cells: x in [0, 8), y in [0, 4)
    occupied = np.zeros((rows, cols), bool)
    occupied[rows - 1, :] = True  # the wall at the largest y (row index rows-1)
    free = np.zeros((rows, cols), bool)
    free[:10, :] = True
    return MapUpdate(
        episode_id=eid, step=step, grid=GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=rows, cols=cols),
        occupied=occupied, free=free, explored=free.copy(), pose=Pose2D(x=1.0, y=0.5, yaw=0.0),
        frontiers=[Frontier(x=7.0, y=0.5, nx=1, ny=0, size=5, weight=2.0)], prompt_points=points or [],
    )


def test_map_north_up_with_robot_frontier_and_path() -> None:
    m = _map("ep-a", 0)
    view = views.MapView(step=0, grid=m.grid, occupied=m.occupied, free=m.free, explored=m.explored,
                         frontiers=m.frontiers, pose=m.pose, prompt_points=[])
    img = _img(views.render_map(view, path=[(1.0, 0.5), (4.0, 0.5)], trail=[]))
    scale = views.MAP_MAX_PX // 80
    assert img.shape == (40 * scale, 80 * scale, 3)
    assert tuple(img[1, 5]) == views.OCCUPIED  # the wall at the largest y is drawn at the top
    assert tuple(img[-2, 5 * scale]) == views.EXPLORED  # explored floor at the bottom (small y)
    assert tuple(img[20 * scale, 40 * scale]) == views.UNKNOWN
    row = (40 - 5) * scale  # y = 0.5 m
    assert tuple(img[row, 10 * scale]) == views.ROBOT  # x = 1 m
    assert tuple(img[row, 70 * scale]) == views.FRONTIER  # x = 7 m
    assert tuple(img[row, 30 * scale]) == views.PATH  # on the way to x = 4 m


def test_frame_scaled_up_with_prompt_points_where_the_scorer_saw_them() -> None:
    rgb = np.zeros((120, 160, 3), np.uint8)
    png = views.render_frame(rgb, [PromptPoint(label="1", x=0, y=0, u=40.0, v=30.0)])
    img = _img(png)
    assert img.shape == (360, 480, 3)  # 160 px wide scaled to 480
    assert tuple(img[90, 122]) == views.POINT  # (40, 30) * 3, just off the centre (the number is drawn there)
    assert tuple(img[300, 400]) == (0, 0, 0)


def test_cache_keeps_the_latest_per_episode_and_a_bounded_number_of_episodes() -> None:
    cache = views.ViewCache(max_episodes=3)
    assert cache.png("ep-0", "frame") is None
    cache.offer(_frame("ep-0", 0))
    cache.offer(_map("ep-0", 0, [PromptPoint(label="1", x=0, y=0, u=10, v=10)]))
    cache.offer(Goal(episode_id="ep-0", step=0, path=[(1.0, 1.0), (2.0, 1.0), (3.0, 1.0)]))
    cache.offer(_frame("ep-0", 1, x=3.0))
    cache.offer(_frame("ep-0", 0))  # a resent older frame is not the latest
    step, png = cache.png("ep-0", "frame")  # type: ignore[misc]
    assert step == 1 and cache.png("ep-0", "frame")[1] is png  # type: ignore[index]  # rendered once
    assert cache.png("ep-0", "map")[0] == 0  # type: ignore[index]
    assert cache._eps["ep-0"].trail == [(1.0, 1.0), (1.0, 1.0), (2.0, 1.0), (3.0, 1.0), (3.0, 1.0)]
    for i in range(1, 5):
        cache.offer(_frame(f"ep-{i}", 0))
    assert cache.png("ep-0", "frame") is None and cache.png("ep-1", "frame") is None  # the oldest went
    assert cache.steps("ep-4") == (0, -1)
