"""Manipulation skills of the simulated robot (HELIOS section 4.1): the oracle ``pick``, the heuristic ``place``,
and the collision test of a base motion.

* **pick** is the OVMM benchmark's oracle skill: it does not model grasping; it succeeds exactly when a target
  object instance is in the current frame (at least :data:`PICK_MIN_PIXELS_FRAC` of the image) and within
  reach (:data:`REACH_M` from the base centre to the nearest point of the object's box, horizontally). A failed
  pick therefore reveals ground truth ("not here"), which is why the paper counts and limits the attempts.
* **place** is the paper's heuristic (the OVMM baseline's heuristic place): the region in front of the robot
  (:data:`PLACE_REGION`) is probed downwards; the probes that land on the goal receptacle's class stand for the
  class's segmentation mask in the frame (a perfect mask: the OVMM ground-truth-semantics setting), and the
  placement point is the mask's probe with the most mask probes at its height (within :data:`SLAB_HEIGHT_M`)
  around it (within :data:`SLAB_RADIUS_M`) -- the flattest free spot of the receptacle, away from what stands on
  it and from its edges. With no probe on the class the object is dropped above the highest point in front.
  It is dropped from :data:`DROP_CLEARANCE_M` above that point, falls straight down until its footprint touches
  the scene, and stays only when its contacts surround its centre with a margin (else it tips away from them
  and falls to what is below). Success = it stays, on an instance of the goal receptacle. The scene's geometry
  is probed with open3d ray casts, like the renderer.
* **collisions**: a base motion collides when the straight segments of its path pass closer than
  :data:`COLLISION_RADIUS_M` to a wall or furniture (ground-truth navigable grid); the sim teleports the robot
  to valid goals, so a colliding path is counted (OVMM counts collisions as failures), not simulated.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from eqa import grid as gridm
from eqa import robot
from eqa.messages import Pose2D
from services.sim.camera import camera_pose, intrinsics
from services.sim.motion import GRID_RES, clearance_map
from services.sim.scene import Scene

REACH_M = robot.REACH_M  # base centre to the object's box, horizontally
PICK_MIN_PIXELS_FRAC = 0.0003  # share of the image the target must cover to count as "in frame"
PLACE_REGION = (0.3, 1.0, 0.3)  # in front of the robot: from 0.3 m to 1.0 m ahead, +-0.3 m sideways
PLACE_PROBE_STEP = 0.05  # m between downward probes of the region
PROBE_TOP_Z = 2.0  # m, probes start here (below the 2.7 m ceiling, above every surface an arm can reach)
DROP_CLEARANCE_M = 0.05  # the object is released this far above the highest point
CONTACT_TOL_M = 0.01  # footprint probes within this of the rest height touch the support
STABILITY_MARGIN = 0.25  # share of the half footprint the contacts must extend past the centre on each side
# the placement slab of the heuristic place: neighbours within this horizontal radius and this height of a
# candidate point count for it (OVMM's heuristic place scores points the same way: 0.2 m around, 1.5 cm)
SLAB_RADIUS_M = 0.2
SLAB_HEIGHT_M = 0.015
COLLISION_RADIUS_M = robot.COLLISION_RADIUS_M  # a path closer than this to an obstacle collides


def _ray_scene(scene: Scene, exclude: frozenset[int] = frozenset()) -> tuple[Any, np.ndarray | None]:
    """The scene's ray-casting structure without the instances ``exclude`` (the held object) and the map from
    its triangle ids to the scene's (None: every triangle)."""
    import open3d as o3d

    key = ("raycast", exclude) if exclude else ("raycast",)
    got = scene.cache.get(key)
    if got is None:
        keep = None
        tris = scene.triangles
        if exclude:
            keep = np.flatnonzero(~np.isin(scene.triangle_instance, np.array(sorted(exclude), np.int64)))
            tris = scene.triangles[keep]
        rc = o3d.t.geometry.RaycastingScene()
        rc.add_triangles(o3d.core.Tensor(np.ascontiguousarray(scene.vertices, np.float32)),
                         o3d.core.Tensor(np.ascontiguousarray(tris, np.uint32)))
        got = scene.cache[key] = (rc, keep)
    return got


def cast_down(scene: Scene, xy: np.ndarray, top_z: float = PROBE_TOP_Z,
              exclude: frozenset[int] = frozenset()) -> tuple[np.ndarray, np.ndarray]:
    """Heights (``-inf`` where nothing is hit) and instance ids (-1) of the first surface below ``top_z`` at
    each ``xy`` point (``(N, 2)``); the instances ``exclude`` (the object in the gripper) are not there."""
    import open3d as o3d

    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    rays = np.zeros((len(xy), 6), np.float32)
    rays[:, :2] = xy
    rays[:, 2] = top_z
    rays[:, 5] = -1.0
    rc, keep = _ray_scene(scene, exclude)
    out = rc.cast_rays(o3d.core.Tensor(rays))
    t = out["t_hit"].numpy()
    ok = np.isfinite(t)
    z = np.where(ok, top_z - t, -np.inf)
    prim = out["primitive_ids"].numpy().astype(np.int64)
    if keep is not None:
        prim[ok] = keep[prim[ok]]
    inst = np.full(len(xy), -1, np.int64)
    inst[ok] = scene.triangle_instance[prim[ok]]
    return z, inst


def box_distance_xy(x: float, y: float, centre: tuple[float, ...], size: tuple[float, ...]) -> float:
    """Horizontal distance from ``(x, y)`` to the axis-aligned box (0 inside it)."""
    dx = max(abs(x - centre[0]) - size[0] / 2, 0.0)
    dy = max(abs(y - centre[1]) - size[1] / 2, 0.0)
    return math.hypot(dx, dy)


# ---- pick -------------------------------------------------------------------------------------------------


@dataclass
class PickResult:
    success: bool
    reason: str
    object_id: int | None = None  # the instance picked
    pixels: int = 0
    distance_m: float = math.inf


def pick(scene: Scene, pose: Pose2D, instances: np.ndarray, target_ids: list[int]) -> PickResult:
    """The oracle pick (module doc): succeeds when one of ``target_ids`` covers enough of the frame whose
    per-pixel ``instances`` are given and is within reach of ``pose``; the nearest such instance is taken."""
    if not target_ids:
        return PickResult(False, "the task has no target object")
    ids = np.asarray(instances).ravel()
    min_px = max(1, math.ceil(PICK_MIN_PIXELS_FRAC * ids.size))
    best: PickResult | None = None
    seen_far = False
    for oid in target_ids:
        info = scene.instances.get(int(oid))
        if info is None:
            continue
        px = int(np.count_nonzero(ids == oid))
        if px < min_px:
            continue
        dist = box_distance_xy(pose.x, pose.y, info.position, info.size)
        if dist > REACH_M:
            seen_far = True
            continue
        if best is None or dist < best.distance_m:
            best = PickResult(True, f"picked {info.category} {oid}", int(oid), px, dist)
    if best is not None:
        return best
    if seen_far:
        return PickResult(False, f"the target is in view but farther than the reach of {REACH_M} m")
    return PickResult(False, "no target object in frame")


def pick_poses(scene: Scene, target_id: int, reach: np.ndarray, origin: tuple[float, float],
               max_candidates: int = 24, width: int = 160, height: int = 120) -> list[Pose2D]:
    """Reachable poses (cells of ``reach``, a :data:`~services.sim.motion.GRID_RES` grid with ``origin``)
    from which :func:`pick` of ``target_id`` succeeds, facing the object (rendered at ``width x height``)."""
    from services.sim.render import Renderer

    info = scene.instances[target_id]
    ox, oy = origin
    ii, jj = np.nonzero(reach)
    if ii.size == 0:
        return []
    xs, ys = gridm.cell_center(ii, jj, (ox, oy), GRID_RES)
    dx = np.maximum(np.abs(xs - info.position[0]) - info.size[0] / 2, 0.0)
    dy = np.maximum(np.abs(ys - info.position[1]) - info.size[1] / 2, 0.0)
    near = np.flatnonzero(np.hypot(dx, dy) <= REACH_M - 0.05)
    if near.size == 0:
        return []
    if near.size > max_candidates:
        near = near[np.linspace(0, near.size - 1, max_candidates).astype(int)]
    renderer = scene.cache.get(("renderer",))
    if renderer is None:
        renderer = scene.cache[("renderer",)] = Renderer(scene)
    K = intrinsics(width, height)
    out = []
    for k in near:
        x, y = float(xs[k]), float(ys[k])
        pose = Pose2D(x=round(x, 3), y=round(y, 3),
                      yaw=round(math.atan2(info.position[1] - y, info.position[0] - x), 4))
        r = renderer.render(camera_pose(pose), K, width, height)  # type: ignore[union-attr]
        if pick(scene, pose, r.instances, [target_id]).success:
            out.append(pose)
    return out


# ---- place ------------------------------------------------------------------------------------------------


@dataclass
class PlaceResult:
    success: bool
    reason: str
    drop_xyz: tuple[float, float, float] | None = None
    rest_xyz: tuple[float, float, float] | None = None
    support_id: int | None = None  # the instance the object rests on (-1: nothing)


def _region_points(pose: Pose2D) -> np.ndarray:
    near, far, half = PLACE_REGION
    a = np.arange(near, far + 1e-9, PLACE_PROBE_STEP)
    b = np.arange(-half, half + 1e-9, PLACE_PROBE_STEP)
    A, B = np.meshgrid(a, b)
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    x = pose.x + A * c - B * s
    y = pose.y + A * s + B * c
    return np.stack([x.ravel(), y.ravel()], axis=1)


def _slab_point(pts: np.ndarray, z: np.ndarray, mask: np.ndarray) -> int:
    """The probe of ``mask`` with the most probes of ``mask`` within SLAB_RADIUS_M around it and SLAB_HEIGHT_M
    of its height (ties: the one nearest their centroid)."""
    idx = np.flatnonzero(mask)
    P, Z = pts[idx], z[idx]
    near = (np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2) <= SLAB_RADIUS_M) & (
        np.abs(Z[:, None] - Z[None, :]) <= SLAB_HEIGHT_M)
    score = near.sum(axis=1)
    best = np.flatnonzero(score == score.max())
    centroid = P[best].mean(axis=0)
    return int(idx[best[np.argmin(np.linalg.norm(P[best] - centroid, axis=1))]])


def place(scene: Scene, pose: Pose2D, object_size: tuple[float, float, float], goal_ids: list[int],
          held_id: int | None = None, goal_category: str | None = None) -> PlaceResult:
    """The heuristic place with its drop test (module doc). ``held_id``: the object in the gripper, which is no
    longer where it was picked (it must not be landed on). ``goal_category``: the goal receptacle's class, whose
    probes are the segmentation mask the placement point is chosen on (None: the highest point in front)."""
    ex = frozenset() if held_id is None else frozenset({int(held_id)})
    pts = _region_points(pose)
    z, inst = cast_down(scene, pts, exclude=ex)
    structure = np.array([inst[k] >= 0 and scene.instances.get(int(inst[k])) is not None
                          and scene.instances[int(inst[k])].is_structure and scene.instances[int(inst[k])].category
                          != "floor" for k in range(len(inst))], bool)
    usable = np.isfinite(z) & ~structure
    if not usable.any():
        return PlaceResult(False, "nothing in front of the robot to place on")
    on_goal = usable & np.array([goal_category is not None and int(inst[k]) in scene.instances
                                 and scene.instances[int(inst[k])].category == goal_category
                                 for k in range(len(inst))], bool)
    if on_goal.any():
        k = _slab_point(pts, z, on_goal)
        top = float(z[k])
    else:
        zz = np.where(usable, z, -np.inf)
        top = float(zz.max())
        # a flat top gives many equally high probes: take the one nearest to their centroid
        level = np.flatnonzero(zz >= top - CONTACT_TOL_M)
        centroid = pts[level].mean(axis=0)
        k = int(level[np.argmin(np.linalg.norm(pts[level] - centroid, axis=1))])
    drop = (float(pts[k, 0]), float(pts[k, 1]), top + DROP_CLEARANCE_M)
    # footprint of the object (axis-aligned, as the gripper holds it), 5 x 5 probes, from just below the release
    w, d, h = object_size
    u = np.linspace(-w / 2, w / 2, 5)
    v = np.linspace(-d / 2, d / 2, 5)
    U, V = np.meshgrid(u, v)
    foot = np.stack([drop[0] + U.ravel(), drop[1] + V.ravel()], axis=1)
    fz, finst = cast_down(scene, foot, top_z=drop[2], exclude=ex)
    if not np.isfinite(fz).any():
        return PlaceResult(False, "the object fell through (no surface below it)", drop)
    rest = float(np.max(fz[np.isfinite(fz)]))
    contact = np.isfinite(fz) & (fz >= rest - CONTACT_TOL_M)
    cu, cv = U.ravel()[contact], V.ravel()[contact]
    # the centre of mass must lie inside the contacts' extent with a margin along both footprint axes (an
    # object balanced on one point or on its edge tips over)
    mu, mv = STABILITY_MARGIN * w / 2, STABILITY_MARGIN * d / 2
    stable = bool(cu.min() <= -mu + 1e-9 and cu.max() >= mu - 1e-9 and cv.min() <= -mv + 1e-9
                  and cv.max() >= mv - 1e-9)
    if stable:
        support_ids = finst[contact]
        support = int(np.bincount(support_ids[support_ids >= 0]).argmax()) if (support_ids >= 0).any() else -1
        rest_xyz = (drop[0], drop[1], rest + h / 2)
    else:
        # it tips away from its contacts (forward, away from the robot, when they are centred) and falls
        away = -np.array([cu.mean(), cv.mean()])
        if np.linalg.norm(away) < 1e-6:
            away = np.array([math.cos(pose.yaw), math.sin(pose.yaw)])
        away /= np.linalg.norm(away)
        land = np.array(drop[:2]) + away * (max(w, d) / 2 + 0.02)
        cz, cinst = cast_down(scene, land[None, :], top_z=rest - 1e-3, exclude=ex)
        support = int(cinst[0])
        rest_xyz = (float(land[0]), float(land[1]), (float(cz[0]) if np.isfinite(cz[0]) else 0.0) + h / 2)
    name = scene.instances[support].category if support in scene.instances else "nothing"
    if support not in set(goal_ids):
        how = "tipped over and fell onto" if not stable else "came to rest on"
        return PlaceResult(False, f"the object {how} the {name}, not on a goal receptacle", drop, rest_xyz,
                           support)
    if not stable:
        return PlaceResult(True, f"tipped over but stayed on the {name} {support}", drop, rest_xyz, support)
    return PlaceResult(True, f"placed on the {name} {support}", drop, rest_xyz, support)


# ---- collisions -------------------------------------------------------------------------------------------


def motion_path(before: tuple[float, float], path: list[tuple[float, float]],
                goal: tuple[float, float]) -> list[tuple[float, float]]:
    """The polyline of one base motion as the sim judges it (question and task episodes alike): from the pose
    before the step, along the goal's path, to the goal pose."""
    return [(float(before[0]), float(before[1])), *[(float(x), float(y)) for x, y in path],
            (float(goal[0]), float(goal[1]))]


def path_collides(scene: Scene, points: list[tuple[float, float]], radius: float = COLLISION_RADIUS_M) -> bool:
    """Whether the polyline ``points`` passes closer than ``radius`` to an obstacle (module doc)."""
    ok, ox, oy = clearance_map(scene, radius)
    if len(points) == 0:
        return False
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if len(pts) == 1:
        pts = np.vstack([pts, pts])
    for a, b in itertools.pairwise(pts):
        n = max(2, math.ceil(float(np.linalg.norm(b - a)) / (GRID_RES / 2)) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        s = a + t * (b - a)
        i, j = gridm.cell_of(s[:, 0], s[:, 1], (ox, oy), GRID_RES)
        inside = gridm.inside(i, j, ok.shape)
        if not inside.all() or not ok[i, j].all():
            return True
    return False
