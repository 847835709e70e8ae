"""3D voxel map -> 2D maps (Explore-EQA section IV-B, appendix B).

* occupied: some voxel between ``floor_clearance`` and the camera height (1.5 m) lies on or just behind a
  surface (``-occupied_band <= tsdf <= 0``).
* free: every voxel of the column from ``floor_clearance`` up to the camera height has been observed and is
  in front of every surface (``tsdf > 0``): "a 2D point is considered free if all voxels up until 1.5 m are
  marked free". The floor clearance (0.1 m) skips the voxels that straddle the floor plane itself.
* explored: some voxel of the column was seen through the narrow view. The paper's wording asks for "all
  voxels along H"; with the narrow view being the lower half of a camera that looks 30 deg down from 1.5 m,
  no voxel above the camera, let alone under the ceiling, is ever in it, so the literal rule would never
  mark a cell. We therefore use "any explored voxel in the column", which is also what the reference code
  computes (``np.sum(explore_vol, axis=-1) > 0``).
* cells the robot stood on (``traversed``) are free and explored: the camera cannot see its own footprint.
* the free island: the 4-connected component of free cells that holds the robot.

The per-column reductions over the voxels are kept between calls (:class:`_ColumnCache` in
``volume.caches``, grown with the grid) and recomputed only for the columns an integration changed since
(``volume.col_stamp``): the same values as reducing the whole grid, at a cost that follows what a frame sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from services.mapper.tsdf import TSDFVolume

_FOUR = ndimage.generate_binary_structure(2, 1)


@dataclass(frozen=True)
class ProjectionConfig:
    camera_height: float = 1.5
    floor_clearance: float = 0.1
    occupied_band: float = 0.4  # in tsdf units (x truncation): 0.2 m behind a surface counts as occupied


@dataclass
class Maps2D:
    occupied: np.ndarray
    free: np.ndarray  # free cells reachable from the robot (the island)
    free_all: np.ndarray  # every free cell, reachable or not
    explored: np.ndarray
    observed: np.ndarray
    robot_cell: tuple[int, int]


def band(volume: TSDFVolume, config: ProjectionConfig) -> slice:
    """Voxel layers whose centres are in ``[floor_clearance, camera_height]``."""
    z = volume.z_centers
    idx = np.nonzero((z >= config.floor_clearance) & (z <= config.camera_height))[0]
    return slice(int(idx[0]), int(idx[-1]) + 1)


@dataclass
class _ColumnCache:
    """Per-column reductions of the voxels (before the traversed cells are applied), valid at ``stamp``."""

    arrays: tuple[int, int, int]  # ids of the volume's tsdf, weight, explored arrays they were read from
    stamp: int
    free: np.ndarray
    occupied: np.ndarray
    explored: np.ndarray
    observed: np.ndarray

    def grow(self, pad: tuple[tuple[int, int], tuple[int, int]], volume: TSDFVolume) -> None:
        """The grid grew by ``pad`` cells (TSDFVolume.ensure): the new columns were never observed, so each
        of their reductions is False."""
        self.free = np.pad(self.free, pad)
        self.occupied = np.pad(self.occupied, pad)
        self.explored = np.pad(self.explored, pad)
        self.observed = np.pad(self.observed, pad)
        self.arrays = (id(volume.tsdf), id(volume.weight), id(volume.explored))


def _columns(volume: TSDFVolume, sl: slice, occupied_band: float, rows: np.ndarray | slice,
             cols: np.ndarray | slice) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """free / occupied / explored / observed of the columns ``(rows, cols)`` (the rules of the module docstring,
    without the traversed cells)."""
    tsdf = volume.tsdf[rows, cols, sl]
    seen = volume.weight[rows, cols, sl] > 0
    free = np.all(seen & (tsdf > 0), axis=-1)
    occupied = np.any(seen & (tsdf <= 0) & (tsdf >= -occupied_band), axis=-1)
    explored = np.any(volume.explored[rows, cols], axis=-1)
    observed = np.any(volume.weight[rows, cols] > 0, axis=-1)
    return free, occupied, explored, observed


def column_maps(volume: TSDFVolume, config: ProjectionConfig) -> _ColumnCache:
    """The per-column reductions of the whole grid, updated in the columns changed since the last call."""
    sl = band(volume, config)
    key = ("project", sl.start, sl.stop, config.occupied_band)
    ids = (id(volume.tsdf), id(volume.weight), id(volume.explored))
    cache = volume.caches.get(key)
    col_stamp = volume.col_stamp
    if (not isinstance(cache, _ColumnCache) or cache.arrays != ids or cache.free.shape != volume.shape2d
            or col_stamp.shape != volume.shape2d):
        free, occupied, explored, observed = _columns(volume, sl, config.occupied_band, slice(None), slice(None))
        cache = _ColumnCache(ids, volume.stamp, free, occupied, explored, observed)
        volume.caches[key] = cache
        return cache
    if volume.stamp != cache.stamp:
        rr, cc = np.nonzero(col_stamp > cache.stamp)
        if rr.size:
            free, occupied, explored, observed = _columns(volume, sl, config.occupied_band, rr, cc)
            cache.free[rr, cc] = free
            cache.occupied[rr, cc] = occupied
            cache.explored[rr, cc] = explored
            cache.observed[rr, cc] = observed
        cache.stamp = volume.stamp
    return cache


def known_columns(volume: TSDFVolume, config: ProjectionConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(known, free)`` of every column: ``free`` as :func:`project`'s ``free_all`` (traversed cells included),
    ``known`` = free or occupied: the columns whose band from the floor clearance to the camera height the map has
    seen, empty or holding a surface. Reads the arrays only (the projection's column cache is left alone)."""
    free, occupied, _, _ = _columns(volume, band(volume, config), config.occupied_band, slice(None), slice(None))
    traversed = volume.planes.get("traversed")
    if traversed is not None:
        free = free | traversed
    return free | occupied, free


def project(
    volume: TSDFVolume, robot_xy: tuple[float, float], config: ProjectionConfig | None = None
) -> Maps2D:
    config = config or ProjectionConfig()
    cols = column_maps(volume, config)
    traversed = volume.planes.get("traversed")
    if traversed is None:
        traversed = np.zeros(volume.shape2d, dtype=bool)
    free_all = cols.free | traversed
    occupied = cols.occupied & ~traversed
    explored = cols.explored | traversed
    observed = cols.observed | traversed
    row, col = volume.cell_of(robot_xy[0], robot_xy[1])
    rc = (int(row), int(col))
    free = island(free_all, rc)
    return Maps2D(
        occupied=occupied, free=free, free_all=free_all, explored=explored, observed=observed, robot_cell=rc
    )


def island(free: np.ndarray, cell: tuple[int, int], search_radius: int = 5) -> np.ndarray:
    """The 4-connected component of ``free`` holding ``cell`` (or the nearest free cell within
    ``search_radius`` cells when the robot's own cell is not free); all False if there is none."""
    ny, nx = free.shape
    r, c = cell
    if not (0 <= r < ny and 0 <= c < nx):
        return np.zeros_like(free)
    if not free[r, c]:
        r0, r1 = max(r - search_radius, 0), min(r + search_radius + 1, ny)
        c0, c1 = max(c - search_radius, 0), min(c + search_radius + 1, nx)
        rr, cc = np.nonzero(free[r0:r1, c0:c1])
        if rr.size == 0:
            return np.zeros_like(free)
        k = int(np.argmin((rr + r0 - r) ** 2 + (cc + c0 - c) ** 2))
        r, c = int(rr[k] + r0), int(cc[k] + c0)
    labels, _ = ndimage.label(free, structure=_FOUR)
    return labels == labels[r, c]
