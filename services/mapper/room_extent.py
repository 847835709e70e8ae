"""The extent of an asked room, from the robot's own map and the scorer's "is this the <room>?" answers.

Pure numpy, no I/O. A question such as "Is there a mug in the kitchen?" is about one room, but the mapper has
no floor plan (the robot does not know the house; :mod:`services.mapper.question_objects` explains why the
benchmark's floor-plan region is a simplification the product does not have). This module estimates the room
from what the robot saw:

* **attribution**: every step, the cells the frame's depth pixels fall in (its surface points within
  ``max_range_m``) get a vote: ``p`` for the room and ``1 - p`` against it, with ``p`` the scorer's P(Yes) to the
  step's ``IN_ROOM`` prompt ("Is this image taken in the <room>?"); a cell belongs to the room when its votes for
  outweigh those against and add up to at least ``min_votes``. A cell is seen from many views, so one view
  the scorer misjudges (or one looking through a door into the next room) does not decide it;
  The voted cells are sparse (one depth pixel in ``stride`` of each row and column); the room is their
  morphological closing (``CLOSE_CELLS``) with the holes filled;
* **coverage**: the room counts as observed once it covers at least ``min_area_m2`` and its open share is at
  most ``max_open``: the frontier cells of the explored map (Explore-EQA's frontiers, the ones the planner
  goes to: an explored free cell next to unexplored space, :func:`services.mapper.frontiers.frontier_cells`)
  within ``CLOSE_CELLS`` of the room, per boundary cell of the room. A room with no frontier left in it has
  been explored; one whose boundary is mostly frontier is still being entered.

The thresholds are declared in ``docs/results/closed-world-answers.md`` (the vote rule is not tuned; min_area_m2
and max_open are chosen on the tuning seed only).

The map grows (:meth:`services.mapper.tsdf.TSDFVolume.ensure` pads the grid); the attributed mask is carried
over by the origin shift, so it stays aligned with the maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from eqa import grid, npy
from services.mapper.frontiers import frontier_cells

_EIGHT = np.ones((3, 3), dtype=bool)
CLOSE_CELLS = 2  # closing of the voted cells, and the reach of a frontier into the room (0.2 m at 0.1 m cells)
MAX_CELLS = 4_000_000  # a map of 200 m x 200 m at 0.1 m: refuse larger grids (memory bound)
# an object belongs to the room when its centre lies within this many cells of the room (0.3 m at 0.1 m cells):
# an object against a wall has its centre at the room's edge, where the voted cells end
REACH_CELLS = 3


def room_vote(in_room: float | None, room_kind: str | None) -> float | None:
    """A step's vote for :meth:`RoomExtent.update`: P(Yes) to IN_ROOM when a room is asked; a question about the
    whole house has every view "in the region" (1.0)."""
    return in_room if room_kind else 1.0


@dataclass(frozen=True)
class RoomCoverage:
    """One step's coverage of the asked room: attributed area, open share of its boundary, and the verdict."""

    area_m2: float
    open_share: float  # share of the room's boundary cells within one cell of a frontier (1.0 when empty)
    observed: bool


class RoomExtent:
    """The asked room's cells over an episode (module docstring)."""

    def __init__(self, min_votes: float = 1.0, max_range_m: float = 6.0, stride: int = 2) -> None:
        if not (min_votes > 0 and max_range_m > 0 and stride >= 1):
            raise ValueError("min_votes and max_range_m must be positive and stride >= 1")
        self.min_votes, self.max_range_m, self.stride = float(min_votes), float(max_range_m), int(stride)
        self.votes_in: np.ndarray | None = None
        self.votes_out: np.ndarray | None = None
        self.origin: tuple[float, float] = (0.0, 0.0)
        self.resolution = 0.0
        self._maps: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _align(self, shape: tuple[int, int], origin: tuple[float, float], resolution: float) -> None:
        if shape[0] * shape[1] > MAX_CELLS:
            raise ValueError(f"grid of {shape} cells exceeds {MAX_CELLS}")
        if self.votes_in is None or self.votes_out is None:
            self.votes_in, self.votes_out = np.zeros(shape), np.zeros(shape)
        elif self.votes_in.shape != shape or self.origin != origin:
            if resolution != self.resolution:
                raise ValueError("the map's resolution changed within an episode")
            dr = round((self.origin[1] - origin[1]) / resolution)
            dc = round((self.origin[0] - origin[0]) / resolution)
            old = (self.votes_in, self.votes_out)
            new = (np.zeros(shape), np.zeros(shape))
            sr, sc = max(-dr, 0), max(-dc, 0)  # first old row/col kept
            rows = min(old[0].shape[0] - sr, shape[0] - max(dr, 0))
            cols = min(old[0].shape[1] - sc, shape[1] - max(dc, 0))
            if rows > 0 and cols > 0:
                for o, n in zip(old, new, strict=True):
                    n[max(dr, 0):max(dr, 0) + rows, max(dc, 0):max(dc, 0) + cols] = o[sr:sr + rows, sc:sc + cols]
            self.votes_in, self.votes_out = new
        self.origin, self.resolution = origin, resolution

    def update(self, depth: np.ndarray, intrinsics: np.ndarray, camera_pose: np.ndarray, in_room: float | None,
               explored: np.ndarray, free: np.ndarray, occupied: np.ndarray, origin: tuple[float, float],
               resolution: float) -> None:
        """One step: the frame's cells vote with ``in_room`` (P(Yes) to IN_ROOM; None = not asked: no vote);
        ``explored``/``free``/``occupied`` are the mapper's maps after the frame (for :meth:`coverage`)."""
        from services.mapper.home_memory import _surface_points

        observed = np.asarray(explored, dtype=bool)
        if observed.shape != np.shape(free) or observed.shape != np.shape(occupied):
            raise ValueError("explored, free and occupied must have one shape")
        if not (resolution > 0 and np.isfinite(resolution)):
            raise ValueError(f"resolution must be positive, got {resolution!r}")
        self._align(observed.shape, (float(origin[0]), float(origin[1])), float(resolution))
        assert self.votes_in is not None and self.votes_out is not None
        self._maps = (observed, np.asarray(free, dtype=bool), np.asarray(occupied, dtype=bool))
        if in_room is None or not np.isfinite(in_room):
            return
        p = float(min(max(in_room, 0.0), 1.0))
        pts = _surface_points(depth, intrinsics, camera_pose, self.stride, self.max_range_m)
        if pts.size == 0:
            return
        r, c = (np.asarray(a, dtype=np.int64) for a in grid.cell_of(pts[:, 0], pts[:, 1], self.origin, resolution))
        ok = (r >= 0) & (r < observed.shape[0]) & (c >= 0) & (c < observed.shape[1])
        cells = np.unique(r[ok] * observed.shape[1] + c[ok])  # one vote per cell and view
        self.votes_in.flat[cells] += p
        self.votes_out.flat[cells] += 1.0 - p

    def state(self) -> dict[str, object]:
        """The extent's votes for the mapper's stored state (the maps come back with the next update)."""
        import io

        buf = io.BytesIO()
        empty = np.zeros((0, 0))
        np.savez_compressed(buf, votes_in=empty if self.votes_in is None else self.votes_in,
                            votes_out=empty if self.votes_out is None else self.votes_out)
        return {"votes": buf.getvalue(), "origin": list(self.origin), "resolution": self.resolution,
                "params": [self.min_votes, self.max_range_m, self.stride]}

    @classmethod
    def from_state(cls, data: dict[str, object]) -> RoomExtent:
        min_votes, max_range_m, stride = data["params"]  # type: ignore[misc]
        ext = cls(float(min_votes), float(max_range_m), int(stride))
        z = npy.load_npz(data["votes"])  # type: ignore[arg-type]
        if z["votes_in"].size:
            if z["votes_in"].size > MAX_CELLS or z["votes_in"].shape != z["votes_out"].shape:
                raise ValueError("stored room extent votes are malformed")
            ext.votes_in, ext.votes_out = z["votes_in"].astype(np.float64), z["votes_out"].astype(np.float64)
        ox, oy = data["origin"]  # type: ignore[misc]
        ext.origin, ext.resolution = (float(ox), float(oy)), float(data["resolution"])  # type: ignore[arg-type]
        return ext

    def room_mask(self) -> np.ndarray | None:
        """The room's cells (aligned with the last maps), or None before the first update."""
        if self.votes_in is None or self.votes_out is None:
            return None
        voted = (self.votes_in > self.votes_out) & (self.votes_in >= self.min_votes)
        closed = ndimage.binary_closing(voted, structure=_EIGHT, iterations=CLOSE_CELLS, border_value=0)
        return ndimage.binary_fill_holes(closed | voted)

    def coverage(self, min_area_m2: float, max_open: float) -> RoomCoverage:
        """The room's coverage on the last maps given to :meth:`update`."""
        room = self.room_mask()
        if room is None or self._maps is None or not room.any():
            return RoomCoverage(0.0, 1.0, False)
        explored, free, occupied = self._maps
        area = float(room.sum()) * self.resolution**2
        frontier, _ = frontier_cells(free, explored, occupied)
        near = ndimage.binary_dilation(room, structure=_EIGHT, iterations=CLOSE_CELLS)
        boundary = room & ~ndimage.binary_erosion(room, structure=_EIGHT, border_value=0)
        n_boundary = int(boundary.sum())
        open_share = min(1.0, float((frontier & near).sum()) / n_boundary) if n_boundary else 1.0
        return RoomCoverage(area, open_share, area >= min_area_m2 and open_share <= max_open)
