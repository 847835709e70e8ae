"""A home's memory in the mapper, without I/O: the question-free map and the view memory of keyframes.

A home (:mod:`eqa.homes`) keeps what its episodes observed so that the next question in the same house does not
start from an empty map:

* the **home map** (:class:`HomeMap`): the question-free part of an episode's map, i.e. the TSDF volume
  (observed voxels' distances and weights, the explored mask) and the ``traversed`` plane. The 2D maps
  (free / occupied / explored) and the frontiers are functions of the volume and the robot's pose
  (:func:`services.mapper.projection.project`, :func:`services.mapper.frontiers.find_frontiers`), so they are
  recomputed from it at the first frame; the semantic value layers are not kept: they are about one question
  (Eq. 3's LSV / GSV are answers to that question's prompts), the view memory is what gives them back;
* the **view memory** (:class:`Keyframe`): a bounded set of the frames the episodes saw (image, depth, camera
  pose, time, the region it covers), chosen for *coverage, not recency*: :func:`select_views` is the greedy
  maximum-coverage rule over the floor cells each view observes (each pick adds the view that covers the most
  cells not yet covered; ties go to the newer view), under a count and a byte budget. Greedy max-coverage is
  within ``1 - 1/e`` of the best choice of that size (Nemhauser, Wolsey, Fisher 1978); it is the set-cover step
  of 3D-Mem's snapshot selection (there over the objects each snapshot shows; here over observed floor cells,
  which needs no detector and keeps empty rooms too).

Merging two maps of the same home (:meth:`HomeMap.merge`: two episodes in one home at once) is TSDF fusion's
own weighted average on the common voxel grid (every grid is aligned to whole chunks of voxels at the world
origin, so two grids differ only by whole-cell offsets), the union of the explored and traversed masks.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from eqa.codec import packb, packed_array, unpackb
from eqa.messages import InstanceLabel, Pose2D

HOME_MAP_VERSION = 1
KEYFRAME_VERSION = 1
COVER_STRIDE = 4  # every 4th pixel in each direction back-projected for a view's covered cells
MAX_DECODED_HOME = 1 << 30  # decode bound of one home part (the per-home byte budget is checked before)


def union_grid(resolution: float, grids: Sequence[tuple[float, float, tuple[int, ...]]]
               ) -> tuple[float, float, tuple[int, int], list[tuple[slice, slice]]]:
    """The 2D grid holding every one of ``grids`` (``(x0, y0, (rows, cols))`` each, cells of ``resolution`` m
    aligned to the same world lattice): its origin, its shape, and where each grid's cells lie in it."""
    x0 = min(g[0] for g in grids)
    y0 = min(g[1] for g in grids)
    places = []
    ny = nx = 0
    for gx, gy, shape in grids:
        r, c = round((gy - y0) / resolution), round((gx - x0) / resolution)
        places.append((slice(r, r + int(shape[0])), slice(c, c + int(shape[1]))))
        ny, nx = max(ny, r + int(shape[0])), max(nx, c + int(shape[1]))
    return x0, y0, (ny, nx), places


# ---- view memory --------------------------------------------------------------------------------------------
def covered_cells(depth: np.ndarray, intrinsics: np.ndarray, camera_pose: np.ndarray, resolution: float,
                  max_depth: float = 10.0, stride: int = COVER_STRIDE) -> np.ndarray:
    """The world floor cells (``floor(x / res)``, ``floor(y / res)``), int32 ``(n, 2)``, unique, of the surface
    points a depth image sees (every ``stride``-th pixel back-projected with the pinhole model the mapper uses:
    camera ``p_c = R^T (p_w - t)``, ``u = f_x x_c / z_c + c_x``)."""
    d = np.asarray(depth, dtype=np.float64)[::stride, ::stride]
    h, w = d.shape
    vv, uu = np.mgrid[0:h, 0:w]
    uu = uu * stride
    vv = vv * stride
    ok = np.isfinite(d) & (d > 0.05) & (d <= max_depth)
    z = d[ok]
    K = np.asarray(intrinsics, dtype=np.float64)
    pc = np.stack([(uu[ok] - K[0, 2]) * z / K[0, 0], (vv[ok] - K[1, 2]) * z / K[1, 1], z], axis=1)
    T = np.asarray(camera_pose, dtype=np.float64)
    pw = pc @ T[:3, :3].T + T[:3, 3]
    cells = np.floor(pw[:, :2] / resolution).astype(np.int64)
    if len(cells) == 0:
        return np.zeros((0, 2), dtype=np.int32)
    return np.unique(cells, axis=0).astype(np.int32)


def cell_keys(cells: np.ndarray) -> set[int]:
    """One int per cell (for set algebra in :func:`select_views`)."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    return set(((c[:, 0] << 32) ^ (c[:, 1] & 0xFFFFFFFF)).tolist())


@dataclass
class ViewInfo:
    """What the selection needs of one keyframe (the image stays in the store)."""

    view_id: str
    t: float  # when it was seen (unix seconds)
    nbytes: int  # stored size of the keyframe
    cells: np.ndarray  # covered floor cells, int32 (n, 2)
    episode_id: str = ""
    step: int = 0

    def to_json(self) -> dict[str, Any]:
        return {"view_id": self.view_id, "t": self.t, "nbytes": self.nbytes, "episode_id": self.episode_id,
                "step": self.step, "cells": packed_array(np.ascontiguousarray(self.cells, dtype=np.int32))}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ViewInfo:
        cells = np.asarray(d["cells"], dtype=np.int32).reshape(-1, 2)
        return cls(view_id=str(d["view_id"]), t=float(d["t"]), nbytes=int(d["nbytes"]), cells=cells,
                   episode_id=str(d.get("episode_id", "")), step=int(d.get("step", 0)))


def select_views(views: Sequence[ViewInfo], max_views: int, max_bytes: int) -> list[ViewInfo]:
    """Greedy maximum coverage: repeatedly take the view covering the most floor cells no chosen view covers
    (ties: the newer view, then the id), while the count stays <= ``max_views`` and the bytes <= ``max_bytes``;
    a view that adds no cell is not taken. Returned in the order picked (most covering first)."""
    if max_views <= 0 or max_bytes <= 0:
        return []
    remaining = sorted(views, key=lambda v: (-v.t, v.view_id))  # newest first: ties go to the newer view
    sets = {v.view_id: cell_keys(v.cells) for v in remaining}
    covered: set[int] = set()
    chosen: list[ViewInfo] = []
    used = 0
    while remaining and len(chosen) < max_views:
        best, best_gain = None, 0
        for v in remaining:
            if used + v.nbytes > max_bytes:
                continue
            gain = len(sets[v.view_id] - covered)
            if gain > best_gain:
                best, best_gain = v, gain
        if best is None:
            break
        chosen.append(best)
        used += best.nbytes
        covered |= sets[best.view_id]
        remaining = [v for v in remaining if v.view_id != best.view_id]
    return chosen


def coverage(views: Sequence[ViewInfo]) -> int:
    """Floor cells covered by the union of ``views``."""
    out: set[int] = set()
    for v in views:
        out |= cell_keys(v.cells)
    return len(out)


@dataclass
class Keyframe:
    """One remembered view: everything a scorer request needs (image, depth, camera, the simulator's instance
    ids and labels when there are any), with its time and covered cells."""

    view_id: str
    episode_id: str
    step: int
    t: float
    pose: Pose2D
    camera_pose: np.ndarray
    intrinsics: np.ndarray
    rgb: np.ndarray
    depth: np.ndarray
    instances: np.ndarray | None = None
    labels: list[InstanceLabel] = field(default_factory=list)
    cells: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int32))

    @classmethod
    def from_frame(cls, frame: Any, view_id: str, resolution: float, t: float | None = None,
                   max_depth: float = 10.0) -> Keyframe:
        return cls(view_id=view_id, episode_id=frame.episode_id, step=int(frame.step),
                   t=time.time() if t is None else float(t), pose=frame.pose,
                   camera_pose=np.asarray(frame.camera_pose, dtype=np.float64),
                   intrinsics=np.asarray(frame.intrinsics, dtype=np.float64),
                   rgb=np.asarray(frame.rgb, dtype=np.uint8), depth=np.asarray(frame.depth, dtype=np.float32),
                   instances=None if frame.instances is None else np.asarray(frame.instances, dtype=np.int32),
                   labels=list(frame.labels),
                   cells=covered_cells(frame.depth, frame.intrinsics, frame.camera_pose, resolution, max_depth))

    def to_bytes(self) -> bytes:
        body = {
            "version": KEYFRAME_VERSION, "view_id": self.view_id, "episode_id": self.episode_id, "step": self.step,
            "t": self.t, "pose": self.pose.model_dump(), "camera_pose": packed_array(self.camera_pose),
            "intrinsics": packed_array(self.intrinsics), "rgb": packed_array(self.rgb),
            "depth": packed_array(self.depth), "cells": packed_array(self.cells),
            "instances": None if self.instances is None else packed_array(self.instances),
            "labels": [lb.model_dump() for lb in self.labels],
        }
        return packb(body)

    @classmethod
    def from_bytes(cls, data: bytes) -> Keyframe:
        b = unpackb(data, max_decoded=MAX_DECODED_HOME)
        if not isinstance(b, dict) or b.get("version") != KEYFRAME_VERSION:
            raise ValueError(f"not a keyframe of version {KEYFRAME_VERSION}")
        return cls(view_id=str(b["view_id"]), episode_id=str(b["episode_id"]), step=int(b["step"]), t=float(b["t"]),
                   pose=Pose2D.model_validate(b["pose"]), camera_pose=np.array(b["camera_pose"]),
                   intrinsics=np.array(b["intrinsics"]), rgb=np.array(b["rgb"]), depth=np.array(b["depth"]),
                   instances=None if b["instances"] is None else np.array(b["instances"]),
                   labels=[InstanceLabel.model_validate(lb) for lb in b["labels"]],
                   cells=np.array(b["cells"], dtype=np.int32).reshape(-1, 2))

    def info(self, nbytes: int) -> ViewInfo:
        return ViewInfo(self.view_id, self.t, nbytes, self.cells, self.episode_id, self.step)


class ViewPool:
    """The candidate keyframes of one running episode, kept at most ``max_views`` by :func:`select_views` as
    frames arrive (an online greedy: the new frame competes with the kept ones). :meth:`offer` says which
    views to write and which to delete, so only chosen frames reach the store."""

    def __init__(self, max_views: int, max_bytes: int, views: Sequence[ViewInfo] = ()) -> None:
        self.max_views = max_views
        self.max_bytes = max_bytes
        self.views: list[ViewInfo] = list(views)

    def offer(self, view: ViewInfo) -> tuple[bool, list[str]]:
        """Offer a new view: ``(kept, ids of views it evicted)``."""
        if any(v.view_id == view.view_id for v in self.views):
            return False, []
        chosen = select_views([*self.views, view], self.max_views, self.max_bytes)
        ids = {v.view_id for v in chosen}
        evicted = [v.view_id for v in self.views if v.view_id not in ids]
        kept = view.view_id in ids
        self.views = [v for v in [*self.views, view] if v.view_id in ids]
        return kept, evicted


# ---- home map -----------------------------------------------------------------------------------------------
def back_band_cells(occupied_band: float, trunc_voxels: float) -> int:
    """How many cells behind a seen surface the map marks occupied: the occupied band ``occupied_band`` (in
    truncation units, :class:`services.mapper.projection.ProjectionConfig`) times the truncation in voxels."""
    return max(0, math.ceil(occupied_band * trunc_voxels - 1e-9))


def observed_floor(known: np.ndarray, free: np.ndarray, back_band: int) -> np.ndarray:
    """The floor cells a map has observed, inside the house: the ``known`` columns (seen empty or holding a surface
    from the floor clearance to the camera height, :func:`services.mapper.projection.known_columns`) without the
    occupied-only columns within ``back_band`` cells (8-neighbourhood) of the outside, the never-seen cells
    connected to the grid's edge.

    Why that peel: fusion marks ``back_band`` cells *behind* every surface it sees as occupied
    (:func:`back_band_cells`); behind an exterior wall seen from inside those cells lie outside the house. The peel
    removes them and the exterior wall's own columns with them; a free column is never removed. Inside the house a
    wall or a piece of furniture is surrounded by seen columns, not by the outside, so it is kept. Columns never
    seen (the inside of closed furniture, a room not yet entered) are not counted."""
    if known.shape != free.shape:
        raise ValueError(f"known {known.shape} and free {free.shape} are not one grid")
    if known.size == 0:
        return np.zeros(known.shape, dtype=bool)
    unknown = np.pad(~known, 1, constant_values=True)  # a ring of unknown cells joins every edge to one outside
    labels, _ = ndimage.label(unknown)
    outside = labels == labels[0, 0]
    if back_band > 0:
        outside = ndimage.binary_dilation(outside, structure=np.ones((3, 3), dtype=bool), iterations=back_band)
    return known & ~(outside[1:-1, 1:-1] & ~free)


@dataclass
class HomeMap:
    """The question-free map of a home: the TSDF volume's arrays on its grid and the traversed plane."""

    resolution: float
    origin_x: float
    origin_y: float
    tsdf: np.ndarray  # (ny, nx, nz) float32
    weight: np.ndarray  # (ny, nx, nz) float32
    explored: np.ndarray  # (ny, nx, nz) bool
    traversed: np.ndarray  # (ny, nx) bool

    @property
    def shape2d(self) -> tuple[int, int]:
        return (int(self.tsdf.shape[0]), int(self.tsdf.shape[1]))

    def explored_cells(self) -> int:
        """Floor cells with any explored voxel."""
        return int(self.explored.any(axis=2).sum()) if self.explored.size else 0

    @classmethod
    def from_episode(cls, em: Any) -> HomeMap:
        v = em.volume
        traversed = v.planes.get("traversed")
        if traversed is None:
            traversed = np.zeros(v.shape2d, dtype=bool)
        return cls(float(em.resolution), float(v.origin_x), float(v.origin_y), v.tsdf.copy(), v.weight.copy(),
                   v.explored.copy(), np.asarray(traversed, dtype=bool).copy())

    def apply_to(self, em: Any, explored: bool | np.ndarray = True) -> None:
        """Start ``em`` (a fresh :class:`services.mapper.episode_map.EpisodeMap`) from this map: its volume and
        traversed plane; its value layers start neutral on the same grid (the view memory fills them).
        ``explored=False``: the geometry only (distances and weights), nothing counted as explored, so the
        frontiers are those of the episode's own views (a task's search, which the view memory does not guide).
        A 2D mask on this map's grid: only the explored voxels above its cells count as explored (a task's floor
        explored for all of its classes, :meth:`services.mapper.home_objects.HomeObjects.explored_for`)."""
        v = em.volume
        if abs(float(em.resolution) - self.resolution) > 1e-9:
            raise ValueError(f"home map at {self.resolution} m voxels, the mapper uses {em.resolution} m")
        if self.tsdf.shape[2] != v.nz:
            raise ValueError(f"home map has {self.tsdf.shape[2]} voxel layers, the mapper {v.nz}")
        v.origin_x, v.origin_y = self.origin_x, self.origin_y
        v.tsdf = self.tsdf.copy()
        v.weight = self.weight.copy()
        if isinstance(explored, np.ndarray):
            if explored.shape != self.shape2d:
                raise ValueError(f"explored mask {explored.shape} on a home map of {self.shape2d} cells")
            v.explored = self.explored & explored[:, :, None]
        else:
            v.explored = self.explored.copy() if explored else np.zeros_like(self.explored)
        fresh = {}
        for name, plane in v.planes.items():
            fill = plane.flat[0] if plane.size else (False if plane.dtype == bool else 0.0)
            fresh[name] = np.full(self.shape2d, fill, dtype=plane.dtype)
        fresh["traversed"] = self.traversed.copy()
        v.planes = fresh

    def merge(self, other: HomeMap) -> HomeMap:
        """The fusion of two maps of the same home: the union grid; on voxels both observed the weighted mean of
        the distances (TSDF fusion, Curless & Levoy 1996) with the weights added; the explored and traversed
        masks OR-ed."""
        if abs(other.resolution - self.resolution) > 1e-9 or other.tsdf.shape[2] != self.tsdf.shape[2]:
            raise ValueError("home maps of different voxel grids cannot be merged")
        res = self.resolution
        if other.tsdf.size == 0:
            return self
        if self.tsdf.size == 0:
            return other
        x0, y0, (ny, nx), places = self._union(other)
        nz = self.tsdf.shape[2]
        wsum = np.zeros((ny, nx, nz), dtype=np.float64)
        dsum = np.zeros((ny, nx, nz), dtype=np.float64)
        explored = np.zeros((ny, nx, nz), dtype=bool)
        traversed = np.zeros((ny, nx), dtype=bool)
        for m, sl in zip((self, other), places, strict=True):
            wsum[sl] += m.weight
            dsum[sl] += m.weight.astype(np.float64) * m.tsdf
            explored[sl] |= m.explored
            traversed[sl] |= m.traversed
        tsdf = np.where(wsum > 0, dsum / np.where(wsum > 0, wsum, 1.0), 0.0).astype(np.float32)
        return HomeMap(res, x0, y0, tsdf, wsum.astype(np.float32), explored, traversed)

    def with_explored_of(self, other: HomeMap) -> HomeMap:
        """This map's volume, with what ``other`` explored (and traversed) explored too: the commit of an episode
        that started from ``other``'s geometry without its explored mask (:meth:`apply_to`), whose distances and
        weights already hold ``other``'s observations, so only the masks are joined."""
        if abs(other.resolution - self.resolution) > 1e-9 or other.tsdf.shape[2] != self.tsdf.shape[2]:
            raise ValueError("home maps of different voxel grids cannot be joined")
        if other.tsdf.size == 0:
            return self
        if self.tsdf.size == 0:
            return other
        x0, y0, (ny, nx), (mine, theirs) = self._union(other)
        nz = self.tsdf.shape[2]
        tsdf = np.zeros((ny, nx, nz), dtype=np.float32)
        weight = np.zeros((ny, nx, nz), dtype=np.float32)
        explored = np.zeros((ny, nx, nz), dtype=bool)
        traversed = np.zeros((ny, nx), dtype=bool)
        tsdf[mine], weight[mine] = self.tsdf, self.weight
        explored[mine] |= self.explored
        explored[theirs] |= other.explored
        traversed[mine] |= self.traversed
        traversed[theirs] |= other.traversed
        return HomeMap(self.resolution, x0, y0, tsdf, weight, explored, traversed)

    def _union(self, other: HomeMap) -> tuple[float, float, tuple[int, int], tuple[Any, Any]]:
        """The grid holding both maps (origin, rows and columns) and where each one's cells lie in it."""
        x0, y0, shape, places = union_grid(self.resolution, [(self.origin_x, self.origin_y, self.shape2d),
                                                             (other.origin_x, other.origin_y, other.shape2d)])
        return x0, y0, shape, (places[0], places[1])

    def to_bytes(self) -> bytes:
        seen = self.weight > 0
        return packb({
            "version": HOME_MAP_VERSION, "resolution": self.resolution, "origin": [self.origin_x, self.origin_y],
            "shape": list(self.tsdf.shape), "observed": packed_array(np.packbits(seen, axis=None)),
            "tsdf": packed_array(self.tsdf[seen], compress=False),
            "weight": packed_array(self.weight[seen].astype(np.float32)),
            "explored": packed_array(np.packbits(self.explored, axis=None)),
            "traversed": packed_array(np.packbits(self.traversed, axis=None)),
        })

    @classmethod
    def from_bytes(cls, data: bytes) -> HomeMap:
        b = unpackb(data, max_decoded=MAX_DECODED_HOME)
        if not isinstance(b, dict) or b.get("version") != HOME_MAP_VERSION:
            raise ValueError(f"not a home map of version {HOME_MAP_VERSION}")
        shape = tuple(int(s) for s in b["shape"])
        if len(shape) != 3 or math.prod(shape) > MAX_DECODED_HOME:
            raise ValueError(f"bad home map shape {shape}")
        size = math.prod(shape)
        seen = np.unpackbits(np.asarray(b["observed"]), count=size).astype(bool).reshape(shape)
        tsdf = np.zeros(shape, dtype=np.float32)
        tsdf[seen] = np.asarray(b["tsdf"])
        weight = np.zeros(shape, dtype=np.float32)
        weight[seen] = np.asarray(b["weight"])
        explored = np.unpackbits(np.asarray(b["explored"]), count=size).astype(bool).reshape(shape)
        traversed = np.unpackbits(np.asarray(b["traversed"]), count=shape[0] * shape[1]).astype(bool).reshape(
            shape[:2])
        return cls(float(b["resolution"]), float(b["origin"][0]), float(b["origin"][1]), tsdf, weight, explored,
                   traversed)



# ---- stale evidence ---------------------------------------------------------------------------------------------
CHANGE_TOL_M = 0.10  # depth disagreement (m) that counts: well above the mapper's voxel (0.05 m), below objects
CHANGE_MIN_POINTS = 3  # disagreeing sample points a change needs (one or two are a depth edge's aliasing)
CHANGE_STRIDE = 1  # every pixel: a mug at 3 m is about 16 pixels of a 160x120 image, too few to sample sparser
CHANGE_VIEWS = 4  # remembered views a frame is checked against (those sharing most floor cells): ~8 ms each
MAX_CHANGES = 64  # observed changes a home keeps (the newest)


@dataclass
class ObservedChange:
    """A change of the house the robot saw itself: when (unix seconds), which floor cells it touched, and the
    remembered views the current frame contradicted (a view that saw through a spot where something now stands
    covers the wall behind it, not the spot's cells)."""

    t: float
    cells: np.ndarray  # int32 (n, 2)
    views: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "cells": packed_array(np.ascontiguousarray(self.cells, dtype=np.int32)),
                "views": list(self.views)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ObservedChange:
        return cls(t=float(d["t"]), cells=np.asarray(d["cells"], dtype=np.int32).reshape(-1, 2),
                   views=tuple(str(v) for v in d.get("views", ())))


def _surface_points(depth: np.ndarray, intrinsics: np.ndarray, camera_pose: np.ndarray, stride: int,
                    max_depth: float, flat_tol: float | None = None) -> np.ndarray:
    """World points of the depth image's pixels (every ``stride``-th); with ``flat_tol`` only those whose 3x3
    neighbourhood spans less than it in depth (not on a depth edge or a structure thinner than a pixel: a shelf
    board or a chair leg seen from elsewhere falls between the other view's pixels)."""
    from scipy import ndimage

    full = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(full) & (full > 0.05) & (full <= max_depth)
    if flat_tol is not None:
        hi = ndimage.maximum_filter(np.where(valid, full, np.inf), size=3, mode="nearest")
        lo = ndimage.minimum_filter(np.where(valid, full, -np.inf), size=3, mode="nearest")
        valid &= (hi - lo) < flat_tol
    d = full[::stride, ::stride]
    h, w = d.shape
    vv, uu = np.mgrid[0:h, 0:w]
    ok = valid[::stride, ::stride]
    z = d[ok]
    K = np.asarray(intrinsics, dtype=np.float64)
    pc = np.stack([(uu[ok] * stride - K[0, 2]) * z / K[0, 0], (vv[ok] * stride - K[1, 2]) * z / K[1, 1], z], axis=1)
    T = np.asarray(camera_pose, dtype=np.float64)
    return pc @ T[:3, :3].T + T[:3, 3]


def _seen_through(points: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray, camera_pose: np.ndarray,
                  tol: float, max_depth: float) -> np.ndarray:
    """Mask of world ``points`` that the view (depth, camera) sees *through*: inside its image, and every ray of
    the 3x3 pixels around the point's projection ends more than ``tol`` beyond it (the neighbourhood keeps a
    point on a depth edge from counting; a pixel without depth says nothing, so it never counts)."""
    from scipy import ndimage

    T = np.asarray(camera_pose, dtype=np.float64)
    pc = (points - T[:3, 3]) @ T[:3, :3]
    K = np.asarray(intrinsics, dtype=np.float64)
    d = np.asarray(depth, dtype=np.float64)
    h, w = d.shape
    z = pc[:, 2]
    front = z > 0.05
    u = np.full(len(points), -1)
    v = np.full(len(points), -1)
    u[front] = np.round(K[0, 0] * pc[front, 0] / z[front] + K[0, 2]).astype(int)
    v[front] = np.round(K[1, 1] * pc[front, 1] / z[front] + K[1, 2]).astype(int)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    valid = np.where(np.isfinite(d) & (d > 0.05) & (d <= max_depth), d, -np.inf)
    nearest = ndimage.minimum_filter(valid, size=3, mode="constant", cval=-np.inf)
    out = np.zeros(len(points), dtype=bool)
    out[inside] = nearest[v[inside], u[inside]] > z[inside] + tol
    return out


def disagreement(remembered: Keyframe, current: Any, resolution: float, tol: float = CHANGE_TOL_M,
                 min_points: int = CHANGE_MIN_POINTS, stride: int = CHANGE_STRIDE,
                 max_depth: float = 10.0) -> np.ndarray:
    """The floor cells where a current frame contradicts a remembered view's geometry, int32 ``(n, 2)`` (empty:
    they agree, or they do not see the same space).

    A surface the remembered view saw that the current view now sees through (something was taken away or moved
    from there), or a surface the current view sees in space the remembered view saw through (something was
    put there). Free-space violation is the test because it needs no correspondence and no detector, only the
    two depth images and cameras; a surface merely hidden from one of the views violates nothing. Only points on
    locally flat surface are tested (depth edges and sub-pixel structures alias between two viewpoints), and
    fewer than ``min_points`` disagreeing samples are no change."""
    a = _surface_points(remembered.depth, remembered.intrinsics, remembered.camera_pose, stride, max_depth, tol)
    b = _surface_points(current.depth, current.intrinsics, current.camera_pose, stride, max_depth, tol)
    bad = [a[_seen_through(a, current.depth, current.intrinsics, current.camera_pose, tol, max_depth)],
           b[_seen_through(b, remembered.depth, remembered.intrinsics, remembered.camera_pose, tol, max_depth)]]
    pts = np.concatenate(bad)
    if len(pts) < min_points:
        return np.zeros((0, 2), dtype=np.int32)
    return np.unique(np.floor(pts[:, :2] / resolution).astype(np.int64), axis=0).astype(np.int32)


def stale_weights(views: Sequence[ViewInfo], now: float, changes: Sequence[ObservedChange], max_age_s: float,
                  weight: float) -> list[float]:
    """The weight of each remembered view's evidence for a new question: 1 for a fresh view, ``weight`` for a
    stale one.

    A view is stale when it is older than ``max_age_s`` (0 = no age limit), or older than a change the robot
    itself observed (:func:`disagreement`) on a floor cell the view covers or in the view itself.

    Why: a view's re-scored answer is evidence about the house as it was when the view was taken, and the
    stopper's running intersection treats a memory step like a step seen now, so a stale view of an object that
    has since moved can leave a single wrong answer with full confidence. The weight multiplies the view's
    relevance (``Rel``, Eq. 5), and ``rho = Rel * (f - 1)`` (Eq. 8) goes to 0 with it: at weight 0 the view's
    prediction set holds every answer (it constrains nothing), so the question is answered by what the robot
    sees again, while the view's semantic values still lead it back to look. A change is known where it was
    seen; one nobody saw is caught only by the age limit."""
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"stale weight must be in [0, 1], not {weight}")
    change_sets = [(c.t, cell_keys(c.cells), set(c.views)) for c in changes]
    out = []
    for v in views:
        stale = max_age_s > 0 and now - v.t > max_age_s
        if not stale and change_sets:
            mine = cell_keys(v.cells)
            stale = any(t > v.t and (v.view_id in ids or not mine.isdisjoint(cells)) for t, cells, ids in change_sets)
        out.append(weight if stale else 1.0)
    return out


# ---- the home's index ---------------------------------------------------------------------------------------
@dataclass
class HomeIndex:
    """The home's small index part: its version (bumped by every commit: the optimistic check of concurrent
    episodes), the committed views' selection data, the number of episodes that updated it."""

    version: int = 0
    views: list[ViewInfo] = field(default_factory=list)
    episodes: int = 0
    scenes: list[str] = field(default_factory=list)
    map_bytes: int = 0
    created_at: float = field(default_factory=time.time)
    changes: list[ObservedChange] = field(default_factory=list)  # seen by its episodes, newest last
    objects_bytes: int = 0  # the stored object layer (services.mapper.home_objects)
    gaussians: int = 0

    @property
    def view_bytes(self) -> int:
        return sum(v.nbytes for v in self.views)

    def to_bytes(self) -> bytes:
        return packb({"version": self.version, "views": [v.to_json() for v in self.views],
                      "episodes": self.episodes, "scenes": self.scenes, "map_bytes": self.map_bytes,
                      "created_at": self.created_at, "changes": [c.to_json() for c in self.changes],
                      "objects_bytes": self.objects_bytes, "gaussians": self.gaussians})

    @classmethod
    def from_bytes(cls, data: bytes) -> HomeIndex:
        b = unpackb(data, max_decoded=MAX_DECODED_HOME)
        if not isinstance(b, dict):
            raise ValueError("not a home index")
        return cls(version=int(b["version"]), views=[ViewInfo.from_json(v) for v in b["views"]],
                   episodes=int(b["episodes"]), scenes=[str(s) for s in b["scenes"]],
                   map_bytes=int(b.get("map_bytes", 0)), created_at=float(b.get("created_at", time.time())),
                   changes=[ObservedChange.from_json(c) for c in b.get("changes", [])],
                   objects_bytes=int(b.get("objects_bytes", 0)), gaussians=int(b.get("gaussians", 0)))
