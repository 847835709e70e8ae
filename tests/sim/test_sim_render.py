"""The renderer's compiled per-pixel loops give the bytes of the numpy form they replace (the frames a scene
renders must not change with how they are computed)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from eqa.messages import Pose2D
from services.sim.camera import camera_pose, intrinsics
from services.sim.housegen import generate_house
from services.sim.motion import sample_start_pose
from services.sim.render import Renderer, camera_rays


def _numpy_rays(T: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """World rays the per-column numpy way: (u R0 + v R1) + R2 in float32."""
    dirs_t = np.ascontiguousarray(camera_rays(K, w, h).T)
    rays = np.empty((w * h, 6), np.float32)
    rays[:, :3] = T[:3, 3]
    R = T[:3, :3].astype(np.float32)
    u, v = dirs_t[0, :w], dirs_t[1, ::w]
    for j in range(3):
        out = rays[:, 3 + j].reshape(h, w)
        np.add((u * R[j, 0])[None, :], (v * R[j, 1])[:, None], out=out)
        out += R[j, 2]
    return rays


def test_frames_are_the_bytes_of_the_numpy_form() -> None:
    scene = generate_house(5)
    rend = Renderer(scene)
    w, h = 96, 72
    K = intrinsics(w, h)
    rng = np.random.default_rng(7)
    for _ in range(12):
        T = camera_pose(sample_start_pose(scene, rng, 0.3))
        rays = _numpy_rays(T, K, w, h)
        rend.cast(T, K, w, h)
        assert rend._camera_rays(K, w, h)[2].tobytes() == rays.tobytes()  # the buffer the cast used
        hit = rend._rc.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t, prim = hit["t_hit"].numpy(), hit["primitive_ids"].numpy()
        ok = np.isfinite(t)
        p = np.where(ok, prim, np.uint32(rend._miss)).astype(np.intp)
        out = rend.render(T, K, w, h)
        assert out.depth.dtype == np.float32 and out.instances.dtype == np.int32 and out.rgb.dtype == np.uint8
        assert out.depth.tobytes() == np.where(ok, t, np.float32(0.0)).astype(np.float32).tobytes()
        assert out.instances.tobytes() == np.take(rend._tri_instance, p).tobytes()
        assert out.rgb.tobytes() == np.take(rend._tri_rgb, p, axis=0).tobytes()
        assert (out.instances >= 0).any()


def test_a_ray_that_hits_nothing_is_depth_0_and_instance_minus_1() -> None:
    scene = generate_house(5)
    rend = Renderer(scene)
    hi = scene.bounds[1]
    T = camera_pose(Pose2D(x=float(hi[0]) + 50.0, y=float(hi[1]) + 50.0, yaw=0.0))  # outside, looking away
    out = rend.render(T, intrinsics(16, 12), 16, 12)
    assert (out.depth == 0).all() and (out.instances == -1).all() and (out.rgb == 0).all()
