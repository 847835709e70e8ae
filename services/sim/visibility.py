"""Which objects of a scene the robot can see: for each object, a reachable pose it is visible from.

Rays are cast from reachable camera positions (1.5 m high) to points on the object, within the vertical field
of view of the tilted camera. The question generator asks only about visible objects
(:mod:`services.sim.questions`), and the house changes put objects only where they are visible
(:mod:`services.sim.changes`).
"""

from __future__ import annotations

import math

import numpy as np

from eqa.messages import Pose2D
from services.sim.camera import CAMERA_HEIGHT, HFOV_DEG, TILT_DEG, vfov_deg
from services.sim.motion import reachable_map
from services.sim.scene import Scene

VIEW_MIN, VIEW_MAX = 0.6, 3.5  # m, distances from which an object is looked at


def witness_poses(scene: Scene, start: Pose2D | None = None, ids: list[int] | None = None,
                  candidates: int = 32) -> dict[int, Pose2D]:
    """For each object (or each of ``ids``) visible from a reachable pose, one such pose, facing it.

    A pose witnesses an object when a ray from the camera centre (1.5 m above the pose) to its centre or
    its top first hits that object, at an elevation inside the tilted camera's vertical field of view.
    """
    import open3d as o3d

    objs = [scene.instances[i] for i in ids] if ids is not None else scene.objects()
    if not objs:
        return {}
    reach, ox, oy = reachable_map(scene, start)
    step = 5  # every 0.25 m
    sub = reach[::step, ::step]
    ii, jj = np.nonzero(sub)
    cams = np.stack([ox + (jj * step + 0.5) * 0.05, oy + (ii * step + 0.5) * 0.05], axis=1)
    half_v = vfov_deg(4, 3, HFOV_DEG) / 2.0 - 3.0
    lo_el, hi_el = math.radians(TILT_DEG - half_v), math.radians(TILT_DEG + half_v)
    rays_l, owner_l, cam_l, dist_l = [], [], [], []
    for o in objs:
        p = np.asarray(o.position, np.float64)
        dist = np.hypot(cams[:, 0] - p[0], cams[:, 1] - p[1])
        near = np.flatnonzero((dist > VIEW_MIN) & (dist < VIEW_MAX))
        if near.size == 0:
            continue
        near = near[np.argsort(dist[near], kind="stable")]
        if near.size > candidates:
            near = near[np.linspace(0, near.size - 1, candidates).astype(int)]
        origins = np.column_stack([cams[near], np.full(near.size, CAMERA_HEIGHT)])
        top = p + np.array([0.0, 0.0, o.size[2] / 2 - 0.01])
        for target in (p, top):
            d = target[None, :] - origins
            n = np.linalg.norm(d, axis=1)
            el = np.arcsin(d[:, 2] / n)
            keep = (el >= lo_el) & (el <= hi_el)
            rays_l.append(np.column_stack([origins[keep], d[keep] / n[keep, None]]))
            owner_l.append(np.full(int(keep.sum()), o.id))
            cam_l.append(near[keep])
            dist_l.append(n[keep])
    rays = np.concatenate(rays_l) if rays_l else np.zeros((0, 6))
    owners = np.concatenate(owner_l) if owner_l else np.zeros(0, int)
    cam_idx = np.concatenate(cam_l) if cam_l else np.zeros(0, int)
    dists = np.concatenate(dist_l) if dist_l else np.zeros(0)
    if len(rays) == 0:
        return {}
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(scene.vertices), o3d.core.Tensor(scene.triangles.astype(np.uint32)))
    out = rc.cast_rays(o3d.core.Tensor(np.asarray(rays, np.float32)))
    prim = out["primitive_ids"].numpy()
    t = out["t_hit"].numpy()
    ok = np.isfinite(t)
    ok[ok] = scene.triangle_instance[prim[ok]] == owners[ok]
    found: dict[int, tuple[float, int]] = {}
    for oid, c, n in zip(owners[ok].tolist(), cam_idx[ok].tolist(), dists[ok].tolist(), strict=True):
        score = abs(n - 1.6)  # prefer a comfortable viewing distance
        if oid not in found or score < found[oid][0]:
            found[oid] = (score, c)
    poses = {}
    for oid, (_, c) in found.items():
        p = scene.instances[oid].position
        yaw = math.atan2(p[1] - cams[c, 1], p[0] - cams[c, 0])
        poses[oid] = Pose2D(x=round(float(cams[c, 0]), 3), y=round(float(cams[c, 1]), 3), yaw=round(yaw, 4))
    return poses
