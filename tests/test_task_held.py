"""Issue 17: the object a task robot holds is not rendered where it was picked (services/sim/render.py), a
question episode renders exactly as before, and the object layer scores gaze points for the camera's own tilt."""

from __future__ import annotations

import math

import numpy as np
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
