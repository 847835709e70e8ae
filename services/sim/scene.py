"""A scene: a triangle mesh with per-triangle instance ids and colours, plus a scene graph.

Generated scenes (``gen-00042`` = the house of seed 42, see :mod:`services.sim.housegen`) are saved under
``scenes_dir/<id>/`` as plain ``.npy`` arrays and a ``scene.json`` graph (rooms, doors, instances with
categories, attributes and positions), byte-identical for the same seed, and reloaded from there next time.
Real meshes (``.glb``/``.gltf``/``.ply``/``.obj``, e.g. HM3D or Replica scans) load with
:func:`load_mesh_scene`; they carry colours (vertex colours or textures) but no semantics.

World frame (see :mod:`eqa.messages`): metres, ``z`` up, floor at ``z = 0``.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from eqa import npy
from eqa import robot as body
from eqa.homes import CHANGED_SCENE

log = logging.getLogger(__name__)

GEN_ID = re.compile(r"^gen-(\d{1,9})$")
CHANGED_ID = CHANGED_SCENE  # a generated house after k rounds of changes (services.sim.changes)
MESH_SUFFIXES = (".glb", ".gltf", ".ply", ".obj")
SCENE_FORMAT = 1
OBSTACLE_MIN_Z = body.OBSTACLE_MIN_Z_M  # lower than this is floor (rugs, thresholds)
OBSTACLE_MAX_Z = 1.5  # up to the camera height


class SceneNotFound(LookupError):  # noqa: N818 (public API name)
    """An unknown scene id; the message says which ids exist and how to add one."""


class SceneLoadError(ValueError):
    """A scene file that exists but cannot be read (a mesh that does not parse, a broken graph)."""


@dataclass
class InstanceInfo:
    id: int
    category: str
    room: str | None
    room_kind: str | None
    attributes: dict[str, str] = field(default_factory=dict)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    is_structure: bool = False
    size: tuple[float, float, float] = (0.0, 0.0, 0.0)  # axis-aligned extent
    support: int | None = None  # instance id of the furniture it stands on


@dataclass
class Room:
    id: str
    kind: str
    rect: tuple[float, float, float, float]  # x0, y0, x1, y1

    @property
    def polygon(self) -> list[tuple[float, float]]:
        x0, y0, x1, y1 = self.rect
        return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]

    @property
    def area(self) -> float:
        x0, y0, x1, y1 = self.rect
        return (x1 - x0) * (y1 - y0)

    @property
    def center(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.rect
        return ((x0 + x1) / 2, (y0 + y1) / 2)

    def contains(self, x: float, y: float) -> bool:
        x0, y0, x1, y1 = self.rect
        return x0 <= x <= x1 and y0 <= y <= y1


@dataclass
class Door:
    rooms: tuple[str, str]
    center: tuple[float, float]
    width: float
    axis: str  # "x": the wall runs along x (door passes along y); "y": the wall runs along y


@dataclass
class Scene:
    id: str
    seed: int | None
    vertices: np.ndarray  # (N,3) float32
    triangles: np.ndarray  # (M,3) int32
    triangle_instance: np.ndarray  # (M,) int32, -1 = none
    triangle_colors: np.ndarray | None = None  # (M,3) uint8 flat colour per triangle
    vertex_colors: np.ndarray | None = None  # (N,3) uint8
    triangle_uvs: np.ndarray | None = None  # (M,3,2) float32 texture coordinates per corner
    triangle_material: np.ndarray | None = None  # (M,) int32 index into textures
    textures: list[np.ndarray] = field(default_factory=list)  # (H,W,3) uint8 each
    instances: dict[int, InstanceInfo] = field(default_factory=dict)
    rooms: list[Room] = field(default_factory=list)
    doors: list[Door] = field(default_factory=list)
    wall_height: float = 2.7
    source: str = "generated"
    _grids: dict[float, tuple[np.ndarray, float, float]] = field(default_factory=dict, repr=False)
    cache: dict[object, object] = field(default_factory=dict, repr=False)  # derived maps (see motion.py)

    # ---- geometry facts -----------------------------------------------------------------------------------
    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(min_xyz, max_xyz)`` of the mesh."""
        return self.vertices.min(axis=0).astype(np.float64), self.vertices.max(axis=0).astype(np.float64)

    @property
    def floor_area_m2(self) -> float:
        if self.rooms:
            return float(sum(r.area for r in self.rooms))
        grid, _, _ = self.navigable_grid(0.1, obstacles=False)
        return float(grid.sum()) * 0.01

    def room(self, room_id: str) -> Room:
        for r in self.rooms:
            if r.id == room_id:
                return r
        raise KeyError(room_id)

    def room_at(self, x: float, y: float) -> Room | None:
        for r in self.rooms:
            if r.contains(x, y):
                return r
        return None

    def objects(self) -> list[InstanceInfo]:
        """Instances that are not floors, walls or ceilings."""
        return [i for i in self.instances.values() if not i.is_structure]

    # ---- navigable ground truth ---------------------------------------------------------------------------
    def navigable_grid(self, resolution: float = 0.1, obstacles: bool = True) -> tuple[np.ndarray, float, float]:
        """Ground truth ``(grid, origin_x, origin_y)``: floor cells with no wall or furniture between
        ``z = 0.05`` and ``z = 1.5`` m. Row ``i`` = y, column ``j`` = x, as :class:`eqa.messages.GridSpec`:
        cell ``(i, j)`` covers ``[origin_x + j*res, +res) x [origin_y + i*res, +res)``."""
        key = float(resolution) if obstacles else -float(resolution)
        if key in self._grids:
            g, ox, oy = self._grids[key]
            return g.copy(), ox, oy
        lo, hi = self.bounds
        ox = float(np.floor(lo[0] / resolution) * resolution)
        oy = float(np.floor(lo[1] / resolution) * resolution)
        cols = int(np.ceil((hi[0] - ox) / resolution)) + 1
        rows = int(np.ceil((hi[1] - oy) / resolution)) + 1
        floor = self._floor_cells(rows, cols, ox, oy, resolution)
        grid = floor
        if obstacles:
            grid = floor & ~self._obstacle_cells(rows, cols, ox, oy, resolution)
        self._grids[key] = (grid, ox, oy)
        return grid.copy(), ox, oy

    def _cell_centers(self, rows: int, cols: int, ox: float, oy: float, res: float) -> tuple[np.ndarray, np.ndarray]:
        xs = ox + (np.arange(cols) + 0.5) * res
        ys = oy + (np.arange(rows) + 0.5) * res
        return np.meshgrid(xs, ys)

    def _floor_cells(self, rows: int, cols: int, ox: float, oy: float, res: float) -> np.ndarray:
        X, Y = self._cell_centers(rows, cols, ox, oy, res)
        if self.rooms:
            out = np.zeros((rows, cols), bool)
            for r in self.rooms:
                x0, y0, x1, y1 = r.rect
                out |= (x0 < X) & (x1 > X) & (y0 < Y) & (y1 > Y)
            return out
        # Real mesh: a cell is floor when a ray cast down from camera height first hits a surface at z ~ 0.
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles.astype(np.uint32)))
        rays = np.zeros((rows * cols, 6), np.float32)
        rays[:, 0] = X.ravel()
        rays[:, 1] = Y.ravel()
        rays[:, 2] = OBSTACLE_MAX_Z
        rays[:, 5] = -1.0
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        z = OBSTACLE_MAX_Z - t
        return (np.abs(z) < 0.15).reshape(rows, cols)

    def _obstacle_cells(self, rows: int, cols: int, ox: float, oy: float, res: float) -> np.ndarray:
        tri = self.vertices[self.triangles]  # (M,3,3)
        zmin = tri[:, :, 2].min(axis=1)
        zmax = tri[:, :, 2].max(axis=1)
        keep = (zmax > OBSTACLE_MIN_Z) & (zmin < OBSTACLE_MAX_Z)
        if self.instances:
            structure_floor = np.array(
                [i.category in ("floor", "ceiling") for i in self.instances.values()], bool
            )
            ids = np.array(list(self.instances), np.int64)
            lut = np.zeros(int(ids.max()) + 2, bool)
            lut[ids] = structure_floor
            ti = self.triangle_instance.astype(np.int64)
            keep &= ~lut[np.where(ti >= 0, ti, lut.size - 1)]
        tri = tri[keep]
        out = np.zeros((rows, cols), bool)
        if len(tri) == 0:
            return out
        # Cells covered by each triangle's xy bounding box (exact for the axis-aligned boxes of generated
        # scenes, conservative for scans). A bounding box edge on a cell border does not cover the next cell.
        eps = 1e-4
        j0 = np.clip(np.floor((tri[:, :, 0].min(axis=1) - ox + eps) / res), 0, cols - 1).astype(np.int64)
        j1 = np.clip(np.floor((tri[:, :, 0].max(axis=1) - ox - eps) / res), 0, cols - 1).astype(np.int64)
        i0 = np.clip(np.floor((tri[:, :, 1].min(axis=1) - oy + eps) / res), 0, rows - 1).astype(np.int64)
        i1 = np.clip(np.floor((tri[:, :, 1].max(axis=1) - oy - eps) / res), 0, rows - 1).astype(np.int64)
        j1 = np.maximum(j1, j0)
        i1 = np.maximum(i1, i0)
        # 2D difference array: +1 at (i0,j0), -1 at (i0,j1+1) ... then cumulative sums.
        acc = np.zeros((rows + 1, cols + 1), np.int32)
        np.add.at(acc, (i0, j0), 1)
        np.add.at(acc, (i0, j1 + 1), -1)
        np.add.at(acc, (i1 + 1, j0), -1)
        np.add.at(acc, (i1 + 1, j1 + 1), 1)
        cover = acc.cumsum(axis=0).cumsum(axis=1)[:rows, :cols]
        return cover > 0

    # ---- files --------------------------------------------------------------------------------------------
    def graph(self) -> dict[str, Any]:
        """The scene graph as JSON-ready data."""
        return {
            "format": SCENE_FORMAT,
            "id": self.id,
            "seed": self.seed,
            "source": self.source,
            "wall_height": self.wall_height,
            "floor_area_m2": round(self.floor_area_m2, 4),
            "rooms": [asdict(r) for r in self.rooms],
            "doors": [asdict(d) for d in self.doors],
            "instances": [asdict(i) for i in sorted(self.instances.values(), key=lambda i: i.id)],
        }

    def save(self, directory: Path) -> Path:
        """Write the scene to ``directory`` (atomically: a temporary directory renamed into place)."""
        directory = Path(directory)
        directory.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{directory.name}-", dir=directory.parent))
        try:
            np.save(tmp / "vertices.npy", self.vertices.astype(np.float32))
            np.save(tmp / "triangles.npy", self.triangles.astype(np.int32))
            np.save(tmp / "triangle_instance.npy", self.triangle_instance.astype(np.int32))
            if self.triangle_colors is not None:
                np.save(tmp / "triangle_colors.npy", self.triangle_colors.astype(np.uint8))
            (tmp / "scene.json").write_text(json.dumps(self.graph(), indent=1, sort_keys=True) + "\n")
            try:
                os.replace(tmp, directory)
            except OSError:  # another process saved it first
                if not (directory / "scene.json").exists():
                    raise
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
        return directory

    @classmethod
    def load(cls, directory: Path) -> Scene:
        directory = Path(directory)
        try:
            graph = json.loads((directory / "scene.json").read_text())
            colors = directory / "triangle_colors.npy"
            scene = cls(
                id=graph["id"],
                seed=graph["seed"],
                vertices=npy.load(directory / "vertices.npy"),
                triangles=npy.load(directory / "triangles.npy"),
                triangle_instance=npy.load(directory / "triangle_instance.npy"),
                triangle_colors=npy.load(colors) if colors.exists() else None,
                wall_height=float(graph.get("wall_height", 2.7)),
                source=graph.get("source", "generated"),
                rooms=[Room(r["id"], r["kind"], tuple(r["rect"])) for r in graph["rooms"]],
                doors=[Door(tuple(d["rooms"]), tuple(d["center"]), d["width"], d["axis"]) for d in graph["doors"]],
            )
            for i in graph["instances"]:
                info = InstanceInfo(**{**i, "position": tuple(i["position"]), "size": tuple(i["size"])})
                scene.instances[info.id] = info
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise SceneLoadError(f"scene files in {directory} are broken ({type(exc).__name__}: {exc}); "
                                 f"delete the directory to regenerate it") from exc
        return scene


def _textures_of(mesh: Any) -> list[np.ndarray]:
    out = []
    for tex in mesh.textures:
        img = np.asarray(tex)
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        if img.dtype != np.uint8:
            img = (np.clip(img, 0, 1) * 255).astype(np.uint8) if img.dtype.kind == "f" else img.astype(np.uint8)
        out.append(np.ascontiguousarray(img[:, :, :3]))
    return out


def load_mesh_scene(path: Path, scene_id: str | None = None, y_up: bool | None = None,
                    floor_z: float = 0.0) -> Scene:
    """Load a real mesh (.glb/.gltf/.ply/.obj) as a scene without semantics.

    Colours come from vertex colours or textures (else a uniform gray). glTF files are ``y``-up by
    specification (HM3D, Replica exports), so they are turned to our ``z``-up frame (``(x, y, z) ->
    (x, -z, y)``) unless ``y_up=False``; ``floor_z`` is the height of the floor to put at ``z = 0``.
    Raises :class:`SceneLoadError` when the file does not parse or holds no triangles."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise SceneNotFound(f"mesh file {path} does not exist")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SceneLoadError(f"{path.name}: unsupported mesh format (use one of {', '.join(MESH_SUFFIXES)})")
    mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=True)
    if len(mesh.triangles) == 0:
        raise SceneLoadError(f"{path}: the file does not parse as a triangle mesh (no triangles read)")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if y_up is None:
        y_up = path.suffix.lower() in (".glb", ".gltf")
    if y_up:
        v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)
    v[:, 2] -= floor_z
    tris = np.asarray(mesh.triangles, dtype=np.int32)
    if not np.isfinite(v).all():
        raise SceneLoadError(f"{path}: the mesh has non-finite vertex coordinates")
    scene = Scene(
        id=scene_id or path.stem,
        seed=None,
        vertices=v.astype(np.float32),
        triangles=tris,
        triangle_instance=np.full(len(tris), -1, np.int32),
        source=str(path),
    )
    if mesh.has_textures() and mesh.has_triangle_uvs() and len(mesh.textures) > 0:
        scene.textures = _textures_of(mesh)
        scene.triangle_uvs = np.asarray(mesh.triangle_uvs, np.float32).reshape(-1, 3, 2)
        if mesh.has_triangle_material_ids():
            scene.triangle_material = np.asarray(mesh.triangle_material_ids, np.int32)
        else:
            scene.triangle_material = np.zeros(len(tris), np.int32)
        scene.triangle_material = np.clip(scene.triangle_material, 0, len(scene.textures) - 1)
    if mesh.has_vertex_colors():
        scene.vertex_colors = (np.clip(np.asarray(mesh.vertex_colors), 0, 1) * 255).astype(np.uint8)
    if scene.textures == [] and scene.vertex_colors is None:
        scene.triangle_colors = np.full((len(tris), 3), 180, np.uint8)
    return scene
