"""The object a task robot holds is not rendered where it was picked (services/sim/render.py), a
question episode renders exactly as before, and the object layer scores gaze points for the camera's own tilt."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_sim_tasks import _room_scene

from eqa.messages import GridSpec, Pose2D
from services.mapper.object_map import ObjectMap
from services.mapper.objects.layer import pixel_classes
from services.sim.camera import TILT_DEG, camera_pose, intrinsics
from services.sim.render import Renderer

W, H = 320, 240


def test_held_object_is_not_rendered_and_nothing_else_changes() -> None:
    scene = _room_scene()
    r = Renderer(scene)
    pose = camera_pose(Pose2D(x=1.6, y=2.5, yaw=0.0))
    K = intrinsics(W, H)
    before = r.render(pose, K, W, H)
    assert int((before.instances == 4).sum()) > 50  # the mug on the table, in view
    held = r.render(pose, K, W, H, frozenset({4}))
    assert not (held.instances == 4).any()
    gone = before.instances == 4
    # where the mug was, the table top (or what is behind) shows, farther away; every other pixel is the same
    assert (held.depth[gone] > before.depth[gone]).all()
    assert set(np.unique(held.instances[gone]).tolist()) <= {1, 2}
    for a, b in ((held.rgb, before.rgb), (held.depth, before.depth), (held.instances, before.instances)):
        assert np.array_equal(a[~gone], b[~gone])
    # nothing hidden: byte-identical to the render of a fresh renderer (the question-episode path)
    again = Renderer(scene).render(pose, K, W, H)
    assert before.rgb.tobytes() == again.rgb.tobytes() and before.depth.tobytes() == again.depth.tobytes()
    assert before.instances.tobytes() == again.instances.tobytes()


def test_gaze_points_carry_the_fixed_camera_tilt() -> None:
    scene = _room_scene()
    r = Renderer(scene)
    K = intrinsics(W, H)
    om = ObjectMap(["mug", "dining_table"], [0.25, 0.35])
    for step, x in enumerate((1.4, 1.6)):
        T = camera_pose(Pose2D(x=x, y=2.5, yaw=0.0))
        fr = r.render(T, K, W, H)
        dets = [("mug", 0.9, fr.instances == 4), ("dining_table", 0.8, fr.instances == 2)]
        om.layer.update(fr.depth, pixel_classes(dets, om.layer.classes, fr.depth.shape), T, K, step)
    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=60, cols=60)
    occ = np.zeros((60, 60), bool)
    tilt = math.radians(TILT_DEG)
    fixed = om.summaries(grid, occ, None, camera_height=1.5, camera_pitch=tilt)
    free = om.summaries(grid, occ, None, camera_height=1.5)
    gf = [g for o in fixed for g in o.gaze]
    gp = [g for o in free for g in o.gaze]
    assert gf and len(gf) == len(gp)
    assert all(g.pitch == round(tilt, 6) for g in gf)
    assert any(abs(g.pitch - tilt) > 0.05 for g in gp)  # the paper's pitch towards the top differs
    assert any(abs(a.psi_prime - b.psi_prime) > 1e-6 for a, b in zip(gf, gp, strict=True))  # scored for that view


def test_place_ignores_the_held_object_where_it_was_picked() -> None:
    from services.sim.skills import place

    room = _room_scene()
    # in front of the robot: the table with the mug (4) on it; the mug's top (0.86 m) is the highest point
    front = Pose2D(x=2.0, y=2.5, yaw=0.0)
    r = place(room, front, (0.2, 0.2, 0.1), goal_ids=[2])
    # as if the mug were still there: dropped above its top, balanced on it, tipped over
    assert r.drop_xyz is not None and r.drop_xyz[2] == pytest.approx(0.86 + 0.05, abs=0.01) and "tipped" in r.reason
    held = place(room, front, (0.2, 0.2, 0.1), goal_ids=[2], held_id=4)
    # the mug is in the gripper: dropped above the table top, resting flat on it
    assert held.drop_xyz is not None and held.drop_xyz[2] == pytest.approx(0.75 + 0.05, abs=0.01)
    assert held.success and held.support_id == 2 and held.reason.startswith("placed on")
