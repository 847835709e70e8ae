"""One obstacle height for the sim's collisions and the task map: objects as low as shoes (0.12 m) are obstacles
for the sim (anything above eqa.robot.OBSTACLE_MIN_Z_M) and must be mapped as occupied in a task episode, or the
task paths drive over them and collide."""

from __future__ import annotations

import math

import numpy as np

from eqa import grid as gridm
from eqa import robot as body
from eqa.messages import EpisodeStart, Frame, Pose2D, Question
from services.mapper.episode_map import EpisodeMap, MapperConfig
from services.mapper.object_shell import task_map_config
from services.sim import camera
from services.sim.housegen import generate_house
from services.sim.motion import pose_error
from services.sim.render import Renderer
from services.sim.scene import OBSTACLE_MIN_Z


def _shoe_view(scene):
    """A free pose 1.2-1.8 m from a pair of shoes, facing them, with the shoes in the frame."""
    ren = Renderer(scene)
    K = camera.intrinsics(160, 120)
    for inst in scene.instances.values():
        if inst.category != "shoes":
            continue
        sx, sy = float(inst.position[0]), float(inst.position[1])
        for d in (1.2, 1.5, 1.8):
            for a in np.linspace(0, 2 * math.pi, 16, endpoint=False):
                p = Pose2D(x=sx + d * math.cos(a), y=sy + d * math.sin(a), yaw=float(a + math.pi))
                if pose_error(scene, p) is not None:
                    continue
                r = ren.render(camera.camera_pose(p), K, 160, 120)
                if (r.instances == inst.id).sum() >= 20:
                    return ren, K, p, inst, r
    raise AssertionError("no view of shoes in the house")


def test_shoes_are_mapped_as_obstacles_in_task_episodes() -> None:
    assert OBSTACLE_MIN_Z == body.OBSTACLE_MIN_Z_M  # the sim's navigable grid starts where the robot's model does
    scene = generate_house(115000)
    ren, K, pose, shoe, r = _shoe_view(scene)
    frame = Frame(episode_id="e", step=0, pose=pose, camera_pose=camera.camera_pose(pose), intrinsics=K,
                  rgb=r.rgb, depth=r.depth, instances=r.instances, labels=ren.labels(r.instances))
    start = EpisodeStart(episode_id="e", robot="r", question=Question(text="q", scene=scene.id, start_pose=pose),
                         max_steps=5, record=False)
    occupied = {}
    for name, cfg in (("question", MapperConfig()), ("task", task_map_config(MapperConfig()))):
        em = EpisodeMap(start, cfg)
        em.integrate(frame)
        occ = em.maps.occupied
        g = em.grid()
        hx, hy = float(shoe.size[0]) / 2, float(shoe.size[1]) / 2
        xs = np.linspace(shoe.position[0] - hx, shoe.position[0] + hx, 7)
        ys = np.linspace(shoe.position[1] - hy, shoe.position[1] + hy, 7)
        X, Y = np.meshgrid(xs, ys)
        i, j = gridm.cell_of(X.ravel(), Y.ravel(), (g.origin_x, g.origin_y), g.resolution)
        occupied[name] = bool(occ[i, j].any())
    cfg = task_map_config(MapperConfig())
    z = cfg.volume.z_min + (np.arange(40) + 0.5) * cfg.volume.voxel_size  # the volume's layer centres
    lowest = z[z >= cfg.projection.floor_clearance][0]  # the band's lowest layer holds the obstacle height
    assert lowest - cfg.volume.voxel_size / 2 <= body.OBSTACLE_MIN_Z_M < lowest + cfg.volume.voxel_size / 2
    assert occupied["task"], "the shoes are not on the task map"
    assert not occupied["question"]  # the question map keeps its floor band (its figures are made with it)
