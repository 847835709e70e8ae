"""Incremental snapshots of an episode's map: what changed since the last save, not the whole map.

The mapper stores its state before it publishes a step (a restarted mapper continues from it). The whole map
(:meth:`services.mapper.episode_map.EpisodeMap.snapshot`) is ~1.5 MB and ~15 ms a step at 640x480; here a step
writes

* a **delta part** with what changed since the last save: the voxel columns an integration changed
  (``TSDFVolume.col_stamp``; the whole column: observed mask, tsdf, weight, explored) and the cells of the 2D
  planes (traversed, value layers) that differ from the last saved copy (a new plane whole);
* a small **header** (the service's envelope state): step, pose, frontiers, prompt points, the grid, and the
  names of the full part and of the deltas to replay on it, in order.

A delta names the grid it was taken on; when the grid grew since the previous part (whole chunks added at its
sides), the replay pads the arrays the same way first. Every ``compact_every`` deltas, or when the deltas
together outweigh the full part ``compact_bytes`` times, the step writes a new **full part** instead (the
episode start, the grid, every observed voxel column and every plane, uncompressed: zlib would cost more
than it saves on float noise) and the old parts are deleted after the header that no longer names them
(:class:`eqa.episode_service.StateParts`). :func:`restore` = full part + deltas in order + header:
the same arrays, planes, frontiers and prompt points as the live map (tests/mapper/test_snapshot_log.py).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eqa.codec import packb, packed_array, unpackb
from eqa.messages import EpisodeStart, Frontier, Pose2D, PromptPoint
from services.mapper.episode_map import EpisodeMap, MapperConfig
from services.mapper.projection import project

LOG_VERSION = 1
COMPACT_EVERY = 30  # deltas between two full parts (a restore replays at most this many)
COMPACT_BYTES = 16  # ... or fewer, once the deltas weigh this many times the full part
MAX_DELTAS = 1000  # a header naming more is refused on restore


@dataclass
class _Log:
    """What the last save wrote, to know what changed since."""

    gen: int = 0  # number of the current full part
    full: str | None = None
    full_bytes: int = 0
    deltas: list[str] = field(default_factory=list)
    delta_bytes: int = 0
    stamp: int = 0  # volume stamp at the last save
    grid: tuple[float, float, int, int] = (0.0, 0.0, 0, 0)  # origin and shape at the last save
    planes: dict[str, np.ndarray] = field(default_factory=dict)  # copies as last saved


_logs: weakref.WeakKeyDictionary[EpisodeMap, _Log] = weakref.WeakKeyDictionary()


def _grid(episode_map: EpisodeMap) -> tuple[float, float, int, int]:
    v = episode_map.volume
    return (v.origin_x, v.origin_y, *v.shape2d)


def _header(episode_map: EpisodeMap, log: _Log) -> bytes:
    return packb({
        "version": LOG_VERSION,
        "full": log.full,
        "deltas": list(log.deltas),
        "step": episode_map.step,
        "pose": episode_map.pose.model_dump() if episode_map.pose else None,
        "grid": list(_grid(episode_map)),
        "frontiers": [f.model_dump() for f in episode_map.frontiers],
        "prompts": [p.model_dump() for p in episode_map.prompts],
    })


def _columns(episode_map: EpisodeMap, idx: np.ndarray) -> dict[str, Any]:
    """Voxel columns ``idx`` (flat ``row * cols + col``) as stored: observed mask, tsdf and weight of the
    observed voxels, explored mask."""
    v = episode_map.volume
    r, c = np.divmod(idx, v.shape2d[1])  # indexed, not reshaped: the volume's arrays are views (no copy)
    tsdf = v.tsdf[r, c]
    weight = v.weight[r, c]
    seen = weight > 0
    return {
        "cols": packed_array(idx.astype(np.int32), compress=False),
        "observed": packed_array(np.packbits(seen, axis=None), compress=False),
        "tsdf": packed_array(tsdf[seen], compress=False),
        "weight": packed_array(weight[seen].astype(np.uint16), compress=False),
        "explored": packed_array(np.packbits(v.explored[r, c], axis=None), compress=False),
    }


def _full_part(episode_map: EpisodeMap) -> bytes:
    """Everything: the episode start and layers, the grid, every observed column, every plane whole."""
    v = episode_map.volume
    observed = np.flatnonzero((v.weight > 0).any(axis=2).reshape(-1))
    return packb({
        "version": LOG_VERSION,
        "kind": "full",
        "start": episode_map.start.model_dump(mode="json"),
        "layers": episode_map.layers,
        "grid": list(_grid(episode_map)),
        "planes": {k: {"all": packed_array(a, compress=False)} for k, a in v.planes.items()},
        **_columns(episode_map, observed),
    })


def _from_full(data: bytes, config: MapperConfig | None) -> EpisodeMap:
    body = unpackb(data)
    if not isinstance(body, dict) or body.get("version") != LOG_VERSION or body.get("kind") != "full":
        raise ValueError(f"not a full mapper snapshot part of version {LOG_VERSION}")
    episode_map = EpisodeMap(EpisodeStart.model_validate(body["start"]), config,
                             layers=[str(x) for x in body["layers"]])
    v = episode_map.volume
    grid = body["grid"]
    if not (isinstance(grid, list) and len(grid) == 4) or not (0 <= int(grid[2]) <= 100_000
                                                               and 0 <= int(grid[3]) <= 100_000):
        raise ValueError("full snapshot part: bad grid")
    ny, nx = int(grid[2]), int(grid[3])
    v.origin_x, v.origin_y = float(grid[0]), float(grid[1])
    v.tsdf = np.zeros((ny, nx, v.nz), dtype=np.float32)
    v.weight = np.zeros((ny, nx, v.nz), dtype=np.float32)
    v.explored = np.zeros((ny, nx, v.nz), dtype=bool)
    v.planes = {}
    _apply(episode_map, data)
    return episode_map


def snapshot_step(episode_map: EpisodeMap, compact_every: int = COMPACT_EVERY,
                  compact_bytes: float = COMPACT_BYTES) -> tuple[bytes, dict[str, bytes], list[str]]:
    """The step's save: ``(header, parts to write, parts to delete)`` (see the module docstring)."""
    log = _logs.get(episode_map)
    v = episode_map.volume
    full = (
        log is None
        or log.full is None
        or len(log.deltas) >= compact_every
        or _padding(log.grid, _grid(episode_map), episode_map.resolution) is None
        or v.col_stamp.shape != v.shape2d
        or log.delta_bytes > compact_bytes * log.full_bytes
        or any(name not in v.planes for name in log.planes)
    )
    if full:
        old = [] if log is None else [n for n in (log.full, *log.deltas) if n]
        gen = 0 if log is None else log.gen + 1
        data = _full_part(episode_map)
        log = _Log(gen=gen, full=f"f{gen}", full_bytes=len(data), stamp=v.stamp, grid=_grid(episode_map),
                   planes={k: a.copy() for k, a in v.planes.items()})
        _logs[episode_map] = log
        return _header(episode_map, log), {log.full: data}, old
    assert log is not None
    pad = _padding(log.grid, _grid(episode_map), episode_map.resolution)
    if pad and any(pad):  # the grid grew: the saved copies of the planes grow the same way (zeros)
        log.planes = {k: np.pad(a, pad) for k, a in log.planes.items()}
    changed = np.flatnonzero(v.col_stamp.reshape(-1) > log.stamp) if v.stamp != log.stamp else np.zeros(0, np.int64)
    planes: dict[str, Any] = {}
    for name, arr in v.planes.items():
        last = log.planes.get(name)
        if last is None:  # a plane added since (a new value layer): whole
            planes[name] = {"all": packed_array(arr)}
        else:
            cells = np.flatnonzero(arr.reshape(-1) != last.reshape(-1))
            if cells.size:
                planes[name] = {"cells": packed_array(cells.astype(np.int32), compress=False),
                                "values": packed_array(arr.reshape(-1)[cells], compress=False)}
        if name in planes:
            log.planes[name] = arr.copy()
    body = {"version": LOG_VERSION, "step": episode_map.step, "grid": list(_grid(episode_map)), "planes": planes,
            **_columns(episode_map, changed)}
    data = packb(body)
    name = f"d{log.gen}.{len(log.deltas)}"
    log.deltas.append(name)
    log.delta_bytes += len(data)
    log.stamp = v.stamp
    log.grid = _grid(episode_map)
    return _header(episode_map, log), {name: data}, []


def _padding(old: tuple[float, float, int, int], new: tuple[float, float, int, int],
             res: float) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """``((top, bottom), (left, right))`` cells that turn grid ``old`` into ``new`` (as TSDFVolume.ensure
    grows it), or None when ``new`` is not ``old`` grown at its sides."""
    top, left = round((old[1] - new[1]) / res), round((old[0] - new[0]) / res)
    bottom, right = new[2] - old[2] - top, new[3] - old[3] - left
    if min(top, left, bottom, right) < 0 or abs(old[1] - top * res - new[1]) > 1e-6 * max(1.0, abs(new[1])) \
            or abs(old[0] - left * res - new[0]) > 1e-6 * max(1.0, abs(new[0])):
        return None
    return ((top, bottom), (left, right))


def _grow(episode_map: EpisodeMap, grid: Any) -> None:
    """Pad the restored arrays to a delta's grid (the growth the live volume went through)."""
    if not (isinstance(grid, list) and len(grid) == 4):
        raise ValueError("snapshot delta without its grid")
    new = (float(grid[0]), float(grid[1]), int(grid[2]), int(grid[3]))
    if max(new[2], new[3]) > 100_000:
        raise ValueError("snapshot delta grid too large")
    v = episode_map.volume
    pad = _padding(_grid(episode_map), new, episode_map.resolution)
    if pad is None:
        raise ValueError("snapshot delta grid is not the grid grown at its sides")
    if not any(pad[0] + pad[1]):
        return
    pad3 = (*pad, (0, 0))
    v.tsdf = np.pad(v.tsdf, pad3)
    v.weight = np.pad(v.weight, pad3)
    v.explored = np.pad(v.explored, pad3)
    v.planes = {k: np.pad(a, pad) for k, a in v.planes.items()}
    v.origin_x, v.origin_y = new[0], new[1]


def forget(episode_map: EpisodeMap) -> None:
    """Start over with a full part at the next save (e.g. after a map restored from elsewhere)."""
    _logs.pop(episode_map, None)


def _arr(a: Any, dtype: Any, what: str) -> np.ndarray:
    if not isinstance(a, np.ndarray) or a.dtype != np.dtype(dtype) or a.ndim != 1:
        raise ValueError(f"snapshot delta field {what} is not a 1D {np.dtype(dtype).name} array")
    return a


def _apply(episode_map: EpisodeMap, data: bytes) -> None:
    body = unpackb(data)
    if not isinstance(body, dict) or body.get("version") != LOG_VERSION:
        raise ValueError(f"not a mapper snapshot delta of version {LOG_VERSION}")
    _grow(episode_map, body.get("grid"))
    v = episode_map.volume
    nz = v.nz
    ncols = v.shape2d[0] * v.shape2d[1]
    cols = _arr(body["cols"], np.int32, "cols").astype(np.int64)
    if cols.size and (cols.min() < 0 or cols.max() >= ncols):
        raise ValueError("snapshot delta names columns outside the grid")
    n = cols.size * nz
    seen = np.unpackbits(_arr(body["observed"], np.uint8, "observed"), count=n).astype(bool).reshape(-1, nz)
    tsdf_obs = _arr(body["tsdf"], np.float32, "tsdf")
    weight_obs = _arr(body["weight"], np.uint16, "weight")
    if tsdf_obs.size != int(seen.sum()) or weight_obs.size != tsdf_obs.size:
        raise ValueError("snapshot delta: observed voxels and their values disagree")
    tsdf = np.zeros((cols.size, nz), np.float32)
    weight = np.zeros((cols.size, nz), np.float32)
    tsdf[seen] = tsdf_obs
    weight[seen] = weight_obs
    r, c = np.divmod(cols, v.shape2d[1])  # indexed (the arrays may be views of larger buffers)
    v.tsdf[r, c] = tsdf
    v.weight[r, c] = weight
    explored = np.unpackbits(_arr(body["explored"], np.uint8, "explored"), count=n).astype(bool)
    v.explored[r, c] = explored.reshape(-1, nz)
    for name, change in body["planes"].items():
        if "all" in change:
            arr = change["all"]
            if not isinstance(arr, np.ndarray) or arr.shape != v.shape2d:
                raise ValueError(f"snapshot delta: plane {name} has the wrong shape")
            v.planes[str(name)] = arr.copy()
            continue
        plane = v.planes.get(str(name))
        cells = _arr(change["cells"], np.int32, "cells")
        if plane is None or (cells.size and (cells.min() < 0 or cells.max() >= ncols)):
            raise ValueError(f"snapshot delta: plane {name} unknown or cells outside it")
        plane.reshape(-1)[cells] = change["values"]


def restore(header: bytes, read_part: Any, config: MapperConfig | None = None) -> EpisodeMap:
    """The map from a header of :func:`snapshot_step` and ``read_part(name) -> bytes``; the next save
    continues the same log (deltas on the same full part)."""
    head = unpackb(header)
    if isinstance(head, dict) and "full" not in head:  # a whole-map snapshot (the earlier format)
        return EpisodeMap.restore(header, config)
    if not isinstance(head, dict) or head.get("version") != LOG_VERSION or not isinstance(head.get("full"), str):
        raise ValueError(f"not a mapper snapshot header of version {LOG_VERSION}")
    deltas = head.get("deltas")
    if not isinstance(deltas, list) or len(deltas) > MAX_DELTAS or not all(isinstance(d, str) for d in deltas):
        raise ValueError("bad list of snapshot deltas")
    full = read_part(head["full"])
    episode_map = _from_full(full, config)
    for name in deltas:
        _apply(episode_map, read_part(name))
    v = episode_map.volume
    if [v.origin_x, v.origin_y, *v.shape2d] != list(head["grid"]):
        raise ValueError("snapshot header and parts disagree on the grid")
    episode_map.step = int(head["step"])
    episode_map.pose = Pose2D.model_validate(head["pose"]) if head["pose"] else None
    episode_map.frontiers = [Frontier.model_validate(f) for f in head["frontiers"]]
    episode_map.prompts = [PromptPoint.model_validate(p) for p in head["prompts"]]
    # arrays written in place above: change stamps start over, the projection reads the grid whole again
    v.stamp = 0
    v.col_stamp = np.zeros(v.shape2d, dtype=np.int64)
    v.caches.clear()
    pose = episode_map.pose
    episode_map.maps = None if pose is None else project(v, (pose.x, pose.y), episode_map.config.projection)
    gen = int(head["full"][1:]) if head["full"][1:].isdigit() else 0
    _logs[episode_map] = _Log(gen=gen, full=head["full"], full_bytes=len(full), deltas=list(deltas), stamp=0,
                     grid=_grid(episode_map), planes={k: a.copy() for k, a in v.planes.items()})
    return episode_map


# ---- what rides along with the map in the stored envelope ------------------------------------------------------
# The envelope's state is the map's header alone, or a dict {"map": header, <part>: ...} when an episode carries
# more (the HELIOS task layer "objects", a question's object layer, the joint answer views).


def with_state_part(state: Any, key: str, value: Any) -> Any:
    """``state`` with ``value`` under ``key`` (wrapping a bare map header as ``{"map": header}``)."""
    return {**state, key: value} if isinstance(state, dict) else {"map": state, key: value}


def without_state_part(data: Any, key: str) -> tuple[Any, Any]:
    """Stored state -> (the rest, as the other loaders read it: a bare map header when only it is left; the value
    under ``key`` or None)."""
    if isinstance(data, dict) and key in data:
        rest = {k: v for k, v in data.items() if k != key}
        return (rest["map"] if set(rest) == {"map"} else rest), data[key]
    return data, None
