"""The mapper's whole per-episode state and one step of work on it, without any I/O.

:class:`EpisodeMap` ties the pure parts together: TSDF fusion (:mod:`.tsdf`), the 2D projection
(:mod:`.projection`), prompt points (:mod:`.prompt_points`), the layered semantic value map
(:mod:`.semantic_map`) and frontiers with Eq. A6 weights (:mod:`.frontiers`). :meth:`EpisodeMap.snapshot`
/ :meth:`EpisodeMap.restore` turn the state into bytes and back, exactly (a restarted mapper continues).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eqa.codec import packb, packed_array, unpackb
from eqa.messages import PERFECT_VALUE_RULE, EpisodeStart, Frame, Frontier, GridSpec, MapUpdate, Pose2D, PromptPoint
from services.mapper.frontiers import FrontierConfig, find_frontiers, target_weights, weigh_frontiers
from services.mapper.projection import Maps2D, ProjectionConfig, project
from services.mapper.prompt_points import PromptConfig, prompt_points
from services.mapper.semantic_map import (
    QUESTION_LAYER,
    combine_view_bins,
    ground_truth_scores,
    neutral_value,
    semantic_value,
    temperatures,
    view_plane_names,
    write_values,
    write_values_binned,
)
from services.mapper.tsdf import TSDFVolume, VolumeConfig, check_frame

SNAPSHOT_VERSION = 2  # 2: arrays as eqa.codec extensions (1: dicts of zlib bytes)


@dataclass(frozen=True)
class MapperConfig:
    volume: VolumeConfig = field(default_factory=VolumeConfig)
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    frontier: FrontierConfig = field(default_factory=FrontierConfig)
    prompt: PromptConfig = field(default_factory=PromptConfig)
    sigma: float = 1.0  # Gaussian smoothing of semantic values (m)
    footprint_radius: float = 0.3  # cells within this radius of a robot pose are free & explored
    tau_lsv: float = 1.0
    tau_gsv: float = 1.0
    tau_sv: float = 1.0
    tau_sv_normal: float = 1.0
    view_bins: int = 0  # best value per viewing-direction bin (semantic_map.py); 0 = off
    view_agree: int = 2  # bins that must have seen a cell before a below-neutral value is believed


_arr = packed_array  # one array of a snapshot, encoded by eqa.codec (the wire's array extension) when taken


class Timer:
    def __init__(self) -> None:
        self.ms: dict[str, float] = {}

    def lap(self, name: str, t0: float) -> float:
        now = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (now - t0) * 1000.0
        return now


class EpisodeMap:
    """Map state of one episode. ``layers`` names the semantic value layers (``["question"]`` for EQA;
    HELIOS would use e.g. ``["pick", "place"]``)."""

    def __init__(
        self, start: EpisodeStart, config: MapperConfig | None = None, layers: list[str] | None = None
    ) -> None:
        self.start = start
        self.config = config or MapperConfig()
        self.volume = TSDFVolume(self.config.volume)
        self.volume.add_plane("traversed", False, bool)
        self.layers = list(layers or [QUESTION_LAYER])
        for name in self.layers:
            self.volume.add_plane(f"value/{name}", 0.0, np.float32)
        self.step = -1  # last integrated step
        self.pose: Pose2D | None = None
        self.maps: Maps2D | None = None
        self.frontiers: list[Frontier] = []
        self.prompts: list[PromptPoint] = []
        # (sent_at, timing_ms) of the MapUpdate of step ``step``: a re-published update is the same message
        self.made: tuple[float, dict[str, float]] | None = None

    @property
    def episode_id(self) -> str:
        return self.start.episode_id

    @property
    def strategy(self) -> str:
        return self.start.strategy

    @property
    def resolution(self) -> float:
        return self.config.volume.voxel_size

    @property
    def origin(self) -> tuple[float, float]:
        return (self.volume.origin_x, self.volume.origin_y)

    def layer(self, name: str = QUESTION_LAYER) -> np.ndarray:
        return self.volume.planes[f"value/{name}"]

    def add_layer(self, name: str) -> None:
        """One more semantic value layer (zeros), e.g. a task class's; a layer it has already is kept."""
        if name not in self.layers:
            self.layers.append(name)
            self.volume.add_plane(f"value/{name}", 0.0, np.float32)

    # ---- one step --------------------------------------------------------------------------------------
    def integrate(self, frame: Frame, timer: Timer | None = None) -> Maps2D:
        """Validate and fuse a frame, mark the robot footprint, project to 2D and compute the prompt
        points. Raises :class:`services.mapper.tsdf.FrameError` (map unchanged) on a bad frame."""
        timer = timer or Timer()
        t0 = time.perf_counter()
        check_frame(frame.depth, frame.intrinsics, frame.camera_pose)
        self.volume.integrate(frame.depth, frame.intrinsics, frame.camera_pose)
        self._mark_footprint(frame.pose)
        t0 = timer.lap("integrate", t0)
        self.maps = project(self.volume, (frame.pose.x, frame.pose.y), self.config.projection)
        t0 = timer.lap("project", t0)
        self.prompts = prompt_points(
            self.maps.free,
            self.origin,
            self.resolution,
            frame.depth,
            frame.intrinsics,
            frame.camera_pose,
            self.config.prompt,
        )
        timer.lap("prompt_points", t0)
        self.step = frame.step
        self.pose = frame.pose
        self.made = None
        return self.maps

    def _mark_footprint(self, pose: Pose2D) -> None:
        r = self.config.footprint_radius
        self.volume.ensure(pose.x - r, pose.x + r, pose.y - r, pose.y + r)
        r0, c0 = self.volume.cell_of(pose.x - r, pose.y - r)
        r1, c1 = self.volume.cell_of(pose.x + r, pose.y + r)
        rr, cc = np.mgrid[int(r0) : int(r1) + 1, int(c0) : int(c1) + 1]
        xs, ys = self.volume.cell_center(rr, cc)
        inside = (xs - pose.x) ** 2 + (ys - pose.y) ** 2 <= r * r
        self.volume.planes["traversed"][rr[inside], cc[inside]] = True

    def apply_scores(
        self,
        lsv: list[float],
        gsv: float,
        layer: str = QUESTION_LAYER,
        points: list[PromptPoint] | None = None,
    ) -> list[float]:
        """Write Eq. 3 values of the prompt points into a layer; returns the SV per point ([] when the
        strategy uses no semantic values)."""
        temps = temperatures(self.strategy, self.config.tau_lsv, self.config.tau_gsv)
        pts = self.prompts if points is None else points
        if temps is None or not pts:
            return []
        if len(lsv) != len(pts):
            raise ValueError(f"{len(lsv)} LSV values for {len(pts)} prompt points")
        if self.strategy in PERFECT_VALUE_RULE:  # yardstick: the ground truth's values replace the scorer's
            cam = (self.pose.x, self.pose.y) if self.pose is not None else (0.0, 0.0)
            lsv, gsv = ground_truth_scores([(p.x, p.y) for p in pts], list(self.start.question.targets), cam)
        sv = [semantic_value(lv, gsv, temps[0], temps[1]) for lv in lsv]
        if self.config.view_bins > 0:  # per viewing-direction bin (planes made at the first
            # write of a layer: the HELIOS task layers, written by object_shell, have none), combined into the layer
            *bins, neutral = (self.volume.add_plane(n) for n in view_plane_names(layer, self.config.view_bins))
            cam = (self.pose.x, self.pose.y) if self.pose is not None else (0.0, 0.0)
            write_values_binned(bins, neutral, self.origin, self.resolution, [(p.x, p.y) for p in pts], sv,
                                neutral_value(len(pts), gsv, temps[0], temps[1]), cam, self.config.sigma)
            self.layer(layer)[...] = combine_view_bins(bins, neutral, self.config.view_agree)
            return sv
        write_values(
            self.layer(layer), self.origin, self.resolution, [(p.x, p.y) for p in pts], sv, self.config.sigma
        )
        return sv

    def find_frontier_candidates(self) -> list[Frontier]:
        """Unweighted frontiers of the current maps (they do not depend on the semantic values)."""
        if self.maps is None or self.pose is None:
            return []
        return find_frontiers(
            self.maps.free,
            self.maps.explored,
            self.maps.occupied,
            self.origin,
            self.resolution,
            (self.pose.x, self.pose.y),
            self.config.frontier,
        )

    def compute_frontiers(
        self, layer: str = QUESTION_LAYER, timer: Timer | None = None, candidates: list[Frontier] | None = None
    ) -> list[Frontier]:
        """Frontiers with their Eq. A6 weights from ``layer``. ``candidates``: :meth:`find_frontier_candidates`
        taken since the last :meth:`integrate` (the service finds them while the scorer works)."""
        timer = timer or Timer()
        t0 = time.perf_counter()
        if self.maps is None or self.pose is None:
            return []
        fr = self.find_frontier_candidates() if candidates is None else candidates
        if self.strategy == "target_oracle":  # yardstick: weights from the ground-truth targets
            self.frontiers = target_weights(fr, list(self.start.question.targets), self.start.target_paths)
            timer.lap("frontiers", t0)
            return self.frontiers
        semantic = temperatures(self.strategy, self.config.tau_lsv, self.config.tau_gsv) is not None
        self.frontiers = weigh_frontiers(
            fr,
            self.layer(layer) if semantic else None,
            self.origin,
            self.resolution,
            self.config.tau_sv,
            self.config.tau_sv_normal,
            self.config.frontier.d_sv,
            self.config.frontier.normal_scored_only,
            self.config.frontier.unscored_sv,
        )
        timer.lap("frontiers", t0)
        return self.frontiers

    def grid(self) -> GridSpec:
        ny, nx = self.volume.shape2d
        return GridSpec(
            origin_x=self.volume.origin_x,
            origin_y=self.volume.origin_y,
            resolution=self.resolution,
            rows=ny,
            cols=nx,
        )

    def explored_area_m2(self) -> float:
        if self.maps is None:
            return 0.0
        return float(self.maps.explored.sum()) * self.resolution**2

    def map_update(self, timing_ms: dict[str, float] | None = None) -> MapUpdate:
        """The map update of the last integrated step; once :attr:`made` is set, with its ``sent_at`` and
        timings (the update of a step is one message however often it is published)."""
        if self.maps is None or self.pose is None:
            raise RuntimeError("no frame integrated yet")
        m = self.maps
        made: dict[str, Any] = {}
        if self.made is not None:
            made = {"sent_at": self.made[0]}
            timing_ms = self.made[1]
        return MapUpdate(
            **made,
            episode_id=self.episode_id,
            step=self.step,
            grid=self.grid(),
            occupied=m.occupied,
            free=m.free,
            explored=m.explored,
            values={name: self.layer(name) for name in self.layers},
            frontiers=self.frontiers,
            prompt_points=self.prompts,
            pose=self.pose,
            explored_area_m2=self.explored_area_m2(),
            timing_ms=dict(timing_ms or {}),
        )

    # ---- snapshot --------------------------------------------------------------------------------------
    def snapshot_volume(self) -> dict[str, Any]:
        """The bulky part of :meth:`snapshot` (the voxel arrays), which only :meth:`integrate` changes: the
        service computes it while the scorer works on the step and hands it to :meth:`snapshot`."""
        v = self.volume
        seen = v.weight > 0
        return {
            # only observed voxels carry data: a bit mask + their tsdf and (integer) weights
            "shape": list(v.tsdf.shape),
            "observed": _arr(np.packbits(seen, axis=None)),
            "tsdf": _arr(v.tsdf[seen], compress=False),  # float noise: zlib costs more than it saves
            "weight": _arr(v.weight[seen].astype(np.uint16)),
            "explored": _arr(np.packbits(v.explored, axis=None)),
        }

    def snapshot(self, volume: dict[str, Any] | None = None) -> bytes:
        """The whole state as bytes (msgpack; arrays zlib-compressed). ``volume``: :meth:`snapshot_volume`
        taken since the last :meth:`integrate` (the same bytes result either way)."""
        v = self.volume
        vol = volume if volume is not None else self.snapshot_volume()
        body = {
            "version": SNAPSHOT_VERSION,
            "start": self.start.model_dump(mode="json"),
            "layers": self.layers,
            "step": self.step,
            "pose": self.pose.model_dump() if self.pose else None,
            "origin": [v.origin_x, v.origin_y],
            "shape": vol["shape"],
            "observed": vol["observed"],
            "tsdf": vol["tsdf"],
            "weight": vol["weight"],
            "explored": vol["explored"],
            "planes": {k: _arr(a) for k, a in v.planes.items()},
            "frontiers": [f.model_dump() for f in self.frontiers],
            "prompts": [p.model_dump() for p in self.prompts],
        }
        return packb(body)

    @classmethod
    def restore(cls, data: bytes, config: MapperConfig | None = None) -> EpisodeMap:
        body = unpackb(data)
        if not isinstance(body, dict) or body.get("version") != SNAPSHOT_VERSION:
            raise ValueError(f"not a mapper snapshot of version {SNAPSHOT_VERSION}")

        def arr(a: Any) -> np.ndarray:
            if not isinstance(a, np.ndarray):
                raise ValueError(f"snapshot field is a {type(a).__name__}, not an array")
            return a.copy()  # decoded arrays are read-only views of the payload

        episode_map = cls(EpisodeStart.model_validate(body["start"]), config, layers=list(body["layers"]))
        v = episode_map.volume
        v.origin_x, v.origin_y = (float(x) for x in body["origin"])
        shape = tuple(body["shape"])
        size = int(np.prod(shape))
        seen = np.unpackbits(arr(body["observed"]), count=size).astype(bool).reshape(shape)
        v.tsdf = np.zeros(shape, dtype=np.float32)
        v.tsdf[seen] = arr(body["tsdf"])
        v.weight = np.zeros(shape, dtype=np.float32)
        v.weight[seen] = arr(body["weight"])
        v.explored = (
            np.unpackbits(arr(body["explored"]), count=v.tsdf.size).astype(bool).reshape(v.tsdf.shape)
        )
        v.planes = {k: arr(a) for k, a in body["planes"].items()}
        episode_map.step = int(body["step"])
        episode_map.pose = Pose2D.model_validate(body["pose"]) if body["pose"] else None
        episode_map.frontiers = [Frontier.model_validate(f) for f in body["frontiers"]]
        episode_map.prompts = [PromptPoint.model_validate(p) for p in body["prompts"]]
        if episode_map.pose is not None:
            episode_map.maps = project(v, (episode_map.pose.x, episode_map.pose.y), episode_map.config.projection)
        return episode_map
