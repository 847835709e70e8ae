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


def project(
    volume: TSDFVolume, robot_xy: tuple[float, float], config: ProjectionConfig | None = None
) -> Maps2D:
    config = config or ProjectionConfig()
    sl = band(volume, config)
    tsdf = volume.tsdf[:, :, sl]
    seen = volume.weight[:, :, sl] > 0
    traversed = volume.planes.get("traversed")
    if traversed is None:
        traversed = np.zeros(volume.shape2d, dtype=bool)
    free_all = np.all(seen & (tsdf > 0), axis=2) | traversed
    occupied = np.any(seen & (tsdf <= 0) & (tsdf >= -config.occupied_band), axis=2) & ~traversed
    explored = np.any(volume.explored, axis=2) | traversed
    observed = np.any(volume.weight > 0, axis=2) | traversed
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
