"""What the web console shows of an episode besides its events: the latest camera view with the prompt points
and the top-down map with frontiers, path and trail, as PNG images.

:class:`ViewCache` keeps, per episode, only the latest :class:`Frame` image, the latest :class:`MapUpdate`
grids and the latest :class:`Goal` path (bounded: the newest ``max_episodes`` episodes, a trail of at most
``MAX_TRAIL`` poses), fed from the bus by :mod:`gateway.routers.console`. The renderers are pure functions of
those arrays (numpy + Pillow); a rendered image is cached until the next message of its episode.
"""

from __future__ import annotations

import io
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, ImageDraw

from eqa.grid import fractional_cell
from eqa.messages import Frame, Frontier, Goal, GridSpec, MapUpdate, Message, Pose2D, PromptPoint

MAX_TRAIL = 2000  # poses of the robot's trail kept per episode
MAX_FRONTIERS_DRAWN = 64
MAP_MAX_PX = 640  # longer side of the map image
FRAME_MIN_W = 480  # small simulator frames are scaled up to this width

# colours (RGB)
UNKNOWN = (205, 205, 205)
FREE = (250, 250, 250)
EXPLORED = (214, 234, 248)
OCCUPIED = (60, 60, 60)
FRONTIER = (230, 120, 0)
PATH = (30, 90, 220)
TRAIL = (40, 160, 80)
ROBOT = (200, 20, 20)
POINT = (255, 210, 0)


@dataclass
class MapView:
    step: int
    grid: GridSpec
    occupied: np.ndarray
    free: np.ndarray
    explored: np.ndarray
    frontiers: list[Frontier]
    pose: Pose2D
    prompt_points: list[PromptPoint]


@dataclass
class EpisodeViews:
    """The latest view of one episode (all fields replaced, never mutated in place, so readers need no lock
    beyond taking the references)."""

    frame_step: int = -1
    rgb: np.ndarray | None = None
    map: MapView | None = None
    path: list[tuple[float, float]] = field(default_factory=list)  # the latest Goal's path (planned)
    path_step: int = -1  # the step that Goal follows
    trail: list[tuple[float, float]] = field(default_factory=list)  # the paths driven so far
    version: int = 0
    rendered: dict[str, tuple[int, bytes]] = field(default_factory=dict)  # kind -> (version, png)


class ViewCache:
    """Latest frame, map and path per episode (thread-safe: fed on Zenoh threads, read by HTTP handlers)."""

    def __init__(self, max_episodes: int = 32) -> None:
        self.max_episodes = max_episodes
        self._eps: OrderedDict[str, EpisodeViews] = OrderedDict()
        self._lock = threading.Lock()

    def _get(self, episode_id: str) -> EpisodeViews:
        v = self._eps.get(episode_id)
        if v is None:
            v = self._eps[episode_id] = EpisodeViews()
            while len(self._eps) > self.max_episodes:
                self._eps.popitem(last=False)
        else:
            self._eps.move_to_end(episode_id)
        return v

    def offer(self, msg: Message) -> None:
        """Keep what the console draws from a Frame, MapUpdate or Goal; ignore anything else."""
        if not isinstance(msg, Frame | MapUpdate | Goal):
            return
        with self._lock:
            v = self._get(msg.episode_id)
            if isinstance(msg, Frame):
                if msg.step < v.frame_step:
                    return  # a resent older step
                v.frame_step, v.rgb = msg.step, np.ascontiguousarray(msg.rgb)
                driven = v.path if v.path_step == msg.step - 1 else []  # the path that led to this frame
                v.trail = [*v.trail, *driven, (msg.pose.x, msg.pose.y)][-MAX_TRAIL:]
                if driven:
                    v.path = []
            elif isinstance(msg, MapUpdate):
                if v.map is not None and msg.step < v.map.step:
                    return
                v.map = MapView(
                    step=msg.step,
                    grid=msg.grid,
                    occupied=np.asarray(msg.occupied, dtype=bool),
                    free=np.asarray(msg.free, dtype=bool),
                    explored=np.asarray(msg.explored, dtype=bool),
                    frontiers=sorted(msg.frontiers, key=lambda f: -f.weight)[:MAX_FRONTIERS_DRAWN],
                    pose=msg.pose,
                    prompt_points=list(msg.prompt_points),
                )
            else:
                v.path, v.path_step = [(float(x), float(y)) for x, y in msg.path], msg.step
            v.version += 1

    def png(self, episode_id: str, kind: str) -> tuple[int, bytes] | None:
        """``(step, png bytes)`` of the latest ``"frame"`` or ``"map"`` of an episode, None before the first."""
        with self._lock:
            v = self._eps.get(episode_id)
            if v is None:
                return None
            cached = v.rendered.get(kind)
            if cached is not None and cached[0] == v.version:
                png = cached[1]
                return (v.frame_step if kind == "frame" else v.map.step if v.map else -1), png
            rgb, frame_step, mp, path, trail, version = v.rgb, v.frame_step, v.map, v.path, v.trail, v.version
        if kind == "frame":
            if rgb is None:
                return None
            points = mp.prompt_points if mp is not None and mp.step == frame_step else []
            step, png = frame_step, render_frame(rgb, points)
        else:
            if mp is None:
                return None
            step, png = mp.step, render_map(mp, path, trail)
        with self._lock:
            live = self._eps.get(episode_id)
            if live is not None and live.version == version:
                live.rendered[kind] = (version, png)
        return step, png

    def steps(self, episode_id: str) -> tuple[int, int] | None:
        """``(frame step, map step)`` held for an episode (-1 for none), or None."""
        with self._lock:
            v = self._eps.get(episode_id)
            return None if v is None else (v.frame_step, v.map.step if v.map else -1)


def _png(img: Image.Image) -> bytes:
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=False, compress_level=3)
    return buf.getvalue()


def render_frame(rgb: np.ndarray, prompt_points: list[PromptPoint]) -> bytes:
    """The camera image (scaled up to ``FRAME_MIN_W`` wide when smaller) with each prompt point as a numbered
    circle at its pixel ``(u, v)`` (the points the scorer rates, Explore-EQA Eq. 1)."""
    if rgb.ndim != 3 or rgb.shape[2] < 3:
        raise ValueError(f"frame of shape {rgb.shape} is not HxWx3")
    img = Image.fromarray(np.ascontiguousarray(rgb[:, :, :3]).astype(np.uint8), "RGB")
    scale = max(1.0, FRAME_MIN_W / img.width)
    if scale > 1.0:
        img = img.resize((round(img.width * scale), round(img.height * scale)), Image.Resampling.BILINEAR)
    draw = ImageDraw.Draw(img)
    r = max(6, round(img.width / 60))
    for i, p in enumerate(prompt_points, start=1):
        if not (math.isfinite(p.u) and math.isfinite(p.v)):
            continue
        u, v = p.u * scale, p.v * scale
        draw.ellipse((u - r, v - r, u + r, v + r), fill=POINT, outline=(0, 0, 0), width=2)
        draw.text((u - r / 2, v - r * 0.8), str(i), fill=(0, 0, 0))
    return _png(img)


def render_map(view: MapView, path: list[tuple[float, float]], trail: list[tuple[float, float]]) -> bytes:
    """Top-down map, north (+y) up: unknown grey, free white, explored light blue, occupied dark; frontiers as
    orange dots sized by their Eq. A6 weight, the planned path in blue, the trail in green, the robot in red."""
    rows, cols = view.grid.rows, view.grid.cols
    img_arr = np.empty((rows, cols, 3), dtype=np.uint8)
    img_arr[:] = UNKNOWN
    for mask, colour in ((view.free, FREE), (view.explored, EXPLORED), (view.occupied, OCCUPIED)):
        if mask.shape == (rows, cols):
            img_arr[mask] = colour
    scale = max(1, MAP_MAX_PX // max(rows, cols))
    img = Image.fromarray(img_arr[::-1], "RGB")  # row 0 is the lowest y: flip so +y is up
    img = img.resize((cols * scale, rows * scale), Image.Resampling.NEAREST)
    draw = ImageDraw.Draw(img)
    origin, res = (view.grid.origin_x, view.grid.origin_y), view.grid.resolution

    def px(x: float, y: float) -> tuple[float, float]:
        r, c = fractional_cell(x, y, origin, res)
        return c * scale, (rows - r) * scale

    if len(trail) >= 2:
        draw.line([px(x, y) for x, y in trail], fill=TRAIL, width=max(2, scale // 2))
    if path:
        line = [px(view.pose.x, view.pose.y), *(px(x, y) for x, y in path)]
        draw.line(line, fill=PATH, width=max(2, scale // 2))
    wmax = max((f.weight for f in view.frontiers), default=1.0) or 1.0
    for f in view.frontiers:
        u, v = px(f.x, f.y)
        r = max(3.0, scale * (1.0 + 2.0 * max(0.0, f.weight) / wmax))
        draw.ellipse((u - r, v - r, u + r, v + r), fill=FRONTIER, outline=(90, 40, 0))
    u, v = px(view.pose.x, view.pose.y)
    r = max(5.0, scale * 1.5)
    draw.ellipse((u - r, v - r, u + r, v + r), fill=ROBOT, outline=(255, 255, 255), width=2)
    draw.line((u, v, u + 2.2 * r * math.cos(view.pose.yaw), v - 2.2 * r * math.sin(view.pose.yaw)),
              fill=ROBOT, width=3)
    return _png(img)
