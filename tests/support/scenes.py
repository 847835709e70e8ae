"""Frames rendered in a generated house, and the poses the mapper tests take them from."""

from __future__ import annotations

import math

import numpy as np

from eqa.messages import Frame, Pose2D
from services.sim.camera import camera_pose, intrinsics
from services.sim.render import Renderer
from services.sim.scene import Scene

CELL_M = 0.1  # the navigable grid the poses are drawn from


def rendered_frame(renderer: Renderer, pose: Pose2D, episode_id: str, step: int, width: int, height: int,
                   instances: bool = False) -> Frame:
    """The sim's ``Frame`` at ``pose``: RGB-D rendered ``width`` x ``height`` (with the instance ids when
    ``instances``; the mapper then also runs its object steps on them)."""
    K, T = intrinsics(width, height), camera_pose(pose)
    r = renderer.render(T, K, width, height)
    return Frame(episode_id=episode_id, step=step, pose=pose, camera_pose=T, intrinsics=K, rgb=r.rgb, depth=r.depth,
                 instances=r.instances if instances else None)


def free_cell_walk(scene: Scene, n: int, seed: int, turn_rad: float) -> list[Pose2D]:
    """``n`` distinct navigable cells drawn at random (seeded), the yaw turning by ``turn_rad`` from one to the
    next: a walk that keeps seeing new parts of the house, so the map's grid grows."""
    free, ox, oy = scene.navigable_grid(CELL_M)
    rr, cc = np.nonzero(free)
    picks = np.random.default_rng(seed).choice(len(rr), size=n, replace=False)
    return [Pose2D(x=float(ox + (cc[k] + 0.5) * CELL_M), y=float(oy + (rr[k] + 0.5) * CELL_M),
                   yaw=step * turn_rad % math.tau) for step, k in enumerate(picks)]


def largest_room_spot(scene: Scene) -> tuple[float, float]:
    """The centre of the navigable cell nearest the centre of the house's largest room."""
    room = max(scene.rooms, key=lambda r: r.area)
    free, ox, oy = scene.navigable_grid(CELL_M)
    rr, cc = np.nonzero(free)
    cx, cy = room.center
    k = int(np.argmin((ox + (cc + 0.5) * CELL_M - cx) ** 2 + (oy + (rr + 0.5) * CELL_M - cy) ** 2))
    return ox + (cc[k] + 0.5) * CELL_M, oy + (rr[k] + 0.5) * CELL_M
