"""Object-layer scenarios in generated houses (tests and eqa_app/benches/objects.py): views of an instance from
free floor around it, rendered with open3d, detected by the simulated detector, fused into an ObjectLayer."""

from __future__ import annotations

import math
import queue
from dataclasses import dataclass

import numpy as np
import torch

from eqa import grid as gridm
from eqa import keys
from eqa.bus import Bus
from eqa.messages import DetectRequest, Frame, Pose2D, StepScores
from services.mapper.objects.layer import ObjectLayer, camera_from_gaze, pixel_classes
from services.sim.camera import CAMERA_HEIGHT, intrinsics
from services.sim.render import Rendered, Renderer
from services.sim.scene import Scene
from services.vlm_scorer.detector.oracle import OracleDetector


@dataclass
class View:
    x: float
    y: float
    yaw: float
    pitch: float
    pose: np.ndarray  # 4x4 camera-to-world
    K: np.ndarray
    frame: Rendered
    pixels: int  # of the instance


def frame_of(view: View, renderer: Renderer, episode_id: str, step: int) -> Frame:
    """The sim's Frame message of ``view`` (rendered RGB-D, instances and their labels) at ``step``."""
    fr = view.frame
    return Frame(episode_id=episode_id, step=step, pose=Pose2D(x=view.x, y=view.y, yaw=view.yaw),
                 camera_pose=view.pose, intrinsics=view.K, rgb=fr.rgb, depth=fr.depth, instances=fr.instances,
                 labels=renderer.labels(fr.instances))


def look_at(x: float, y: float, target: tuple[float, float, float]) -> tuple[float, float]:
    dx, dy, dz = target[0] - x, target[1] - y, target[2] - CAMERA_HEIGHT
    return math.atan2(dy, dx), math.atan2(dz, math.hypot(dx, dy))


def ring_views(
    scene: Scene, renderer: Renderer, instance_id: int, width: int, height: int,
    radius: float = 1.4, n: int = 16, min_pixels: int = 30,
) -> list[View]:
    """Views of ``instance_id`` from ``n`` points on a circle of ``radius`` around it, on free floor, looking
    at its centre; only those that show it with ``min_pixels`` pixels, most pixels first."""
    info = scene.instances[instance_id]
    free, ox, oy = scene.navigable_grid(0.1)
    K = intrinsics(width, height)
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        x, y = info.position[0] + radius * math.cos(a), info.position[1] + radius * math.sin(a)
        r, c = gridm.cell_of_point(x, y, (ox, oy), 0.1)
        if not (0 <= r < free.shape[0] and 0 <= c < free.shape[1]) or not free[r, c]:
            continue
        yaw, pitch = look_at(x, y, info.position)
        pose = camera_from_gaze(x, y, yaw, pitch, CAMERA_HEIGHT).double().numpy()
        fr = renderer.render(pose, K, width, height)
        px = int((fr.instances == instance_id).sum())
        if px >= min_pixels:
            out.append(View(x, y, yaw, pitch, pose, K, fr, px))
    return sorted(out, key=lambda v: -v.pixels)


def detect(
    detector: OracleDetector, renderer: Renderer, view: View, classes: list[str], thresholds: list[float],
    step: int, seed: int = 0, episode_id: str = "ep-objects",
) -> list[tuple[str, float, np.ndarray]]:
    fr = view.frame
    req = DetectRequest(
        episode_id=episode_id, step=step, rgb=fr.rgb, classes=classes, thresholds=thresholds,
        instances=fr.instances, labels=renderer.labels(fr.instances), depth=fr.depth, seed=seed,
    )
    h, w = fr.depth.shape
    return [(d.cls, d.score, d.full_mask(h, w)) for d in detector.detect(req)]


def fuse(layer: ObjectLayer, view: View, dets: list[tuple[str, float, np.ndarray]], step: int) -> None:
    pc = pixel_classes(dets, layer.classes, view.frame.depth.shape)
    layer.update(view.frame.depth, pc, view.pose, view.K, step)


def instances_near(layer: ObjectLayer, xyz: tuple[float, float, float], radius: float = 0.8) -> list:
    """The layer's instances whose centre lies within ``radius`` of ``xyz`` in the ground plane."""
    return [i for i in layer.instances() if math.hypot(i.centre[0] - xyz[0], i.centre[1] - xyz[1]) <= radius]


def best_gaze(layer: ObjectLayer, instance_id: int, cls: int, views: list[View]) -> list[tuple[float, View]]:
    """Views ordered by Psi' (Eq. 11) of ``instance_id`` seen as ``cls`` from each (the local-search choice)."""
    scored = []
    for v in views:
        opt = layer.optimistic(instance_id, cls, [torch.as_tensor(v.pose, dtype=torch.float32)])
        scored.append((opt.psi_prime, v))
    return sorted(scored, key=lambda t: -t[0])


def run_steps(bus: Bus, scores: queue.Queue[StepScores], renderer: Renderer, views: list[View], episode_id: str,
              steps: range, robot: str = "r0") -> list[StepScores]:
    """Publish the frames of ``steps`` (view ``step`` of ``views``, cyclically) to the mapper of ``robot`` one by
    one, each after the previous step's StepScores arrived on ``scores``; those StepScores."""
    got = []
    for step in steps:
        bus.publish(keys.stream(robot, keys.SIM_FRAME), frame_of(views[step % len(views)], renderer, episode_id, step))
        s = scores.get(timeout=60)
        assert s.episode_id == episode_id and s.step == step
        got.append(s)
    return got

