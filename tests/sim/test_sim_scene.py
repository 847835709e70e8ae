"""The simulator's pure core on generated houses: geometry, rendering, motion, determinism."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from eqa.messages import Pose2D
from services.sim.camera import camera_pose, intrinsics, vfov_deg
from services.sim.catalog import ROOM_KINDS, display_name
from services.sim.housegen import generate_house
from services.sim.library import load_or_generate
from services.sim.motion import pose_error, reachable_map, sample_start_pose
from services.sim.render import Renderer
from services.sim.scene import SceneLoadError, SceneNotFound

SEEDS = (3, 7, 12)


@pytest.fixture(scope="module")
def houses() -> dict[int, tuple]:
    out = {}
    for s in SEEDS:
        sc = generate_house(s)
        out[s] = (sc, Renderer(sc))
    return out


def test_catalog_names() -> None:
    assert len(ROOM_KINDS) == 10 and "living_room" in ROOM_KINDS
    assert display_name("living_room") == "living room"


def test_house_bounds_and_structure(houses) -> None:
    for sc, _ in houses.values():
        assert 100 <= sc.floor_area_m2 <= 800
        assert 4 <= len(sc.rooms) <= 14
        assert set(r.kind for r in sc.rooms) <= set(ROOM_KINDS)
        lo, hi = sc.bounds
        assert abs(hi[2] - 2.7) < 1e-5 and abs(lo[2]) < 1e-6
        for r in sc.rooms:  # floor, walls and ceiling of each room are instances tied to it
            cats = {i.category for i in sc.instances.values() if i.room == r.id and i.is_structure}
            assert cats == {"floor", "wall", "ceiling"}
        small = [o for o in sc.objects() if "state" in o.attributes]
        assert small and all(o.attributes["state"] in {"on", "off", "open", "closed", "folded", "unfolded"}
                             for o in small)


def test_intrinsics_and_camera_pose() -> None:
    K = intrinsics(640, 480)
    assert K[0, 0] == pytest.approx(320 / math.tan(math.radians(60)))
    assert vfov_deg(640, 480) == pytest.approx(2 * math.degrees(math.atan(math.tan(math.radians(60)) * 0.75)))
    T = camera_pose(Pose2D(x=1, y=2, yaw=math.pi / 2))
    assert np.allclose(T[:3, 3], [1, 2, 1.5])
    assert np.allclose(T[:3, 2], [0, math.cos(math.radians(30)), -0.5], atol=1e-9)  # forward, tilted down
    assert np.allclose(T[:3, 0], [1, 0, 0], atol=1e-9)  # right
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3))


def test_depth_matches_analytic_wall_distance(houses) -> None:
    """A level camera facing a wall: every pixel on that wall has depth = perpendicular distance."""
    checked = 0
    for sc, rend in houses.values():
        for room in sc.rooms:
            x0, y0, x1, y1 = room.rect
            cx, cy = room.center
            wall_id = next(i.id for i in sc.instances.values() if i.room == room.id and i.category == "wall")
            for yaw, expected, axis, line in ((0.0, x1 - 0.05 - cx, "y", x1), (math.pi, cx - (x0 + 0.05), "y", x0),
                                              (math.pi / 2, y1 - 0.05 - cy, "x", y1),
                                              (-math.pi / 2, cy - (y0 + 0.05), "x", y0)):
                # walls with a door have jambs (faces across the wall) at other depths: skip them
                if any(room.id in d.rooms and d.axis == axis and abs(d.center[0 if axis == "y" else 1] - line) < 1e-6
                       for d in sc.doors):
                    continue
                pose = Pose2D(x=cx, y=cy, yaw=yaw)
                T = camera_pose(pose, tilt_deg=0.0)
                K = intrinsics(161, 121)
                out = rend.render(T, K, 161, 121)
                band = out.instances[:, 78:83]
                d = out.depth[:, 78:83][band == wall_id]
                if d.size < 10:
                    continue
                assert np.abs(d - expected).max() < 0.01, (sc.id, room.id, yaw)
                checked += 1
    assert checked >= 10


def test_depth_of_floor_at_default_tilt(houses) -> None:
    """Reference camera (1.5 m, tilted 30 deg down): the centre ray meets the floor 3 m away along the axis."""
    sc, rend = houses[SEEDS[0]]
    K = intrinsics(161, 121)
    hits = 0
    for room in sc.rooms:
        for yaw in np.linspace(-math.pi, math.pi, 8, endpoint=False):
            out = rend.render(camera_pose(Pose2D(x=room.center[0], y=room.center[1], yaw=yaw)), K, 161, 121)
            inst = sc.instances.get(int(out.instances[60, 80]))
            if inst is not None and inst.category == "floor":
                assert out.depth[60, 80] == pytest.approx(3.0, abs=0.01)
                hits += 1
    assert hits >= 3


def test_instance_ids_match_the_object_in_front(houses) -> None:
    """Back-project every pixel: its 3D point lies on the box of the instance the renderer names."""
    for sc, rend in houses.values():
        rng = np.random.default_rng(0)
        K = intrinsics(160, 120)
        Kinv = np.linalg.inv(K)
        for _ in range(4):
            pose = sample_start_pose(sc, rng)
            T = camera_pose(pose)
            out = rend.render(T, K, 160, 120)
            v, u = np.nonzero(out.instances >= 0)
            pix = np.stack([u, v, np.ones_like(u)], axis=0).astype(np.float64)
            pts_cam = (Kinv @ pix) * out.depth[v, u]
            pts = (T[:3, :3] @ pts_cam).T + T[:3, 3]
            ids = out.instances[v, u]
            objects = 0
            for i in np.unique(ids):
                info = sc.instances[int(i)]
                p = pts[ids == i]
                lo = np.array(info.position) - np.array(info.size) / 2 - 0.01
                hi = np.array(info.position) + np.array(info.size) / 2 + 0.01
                inside = np.all((p >= lo) & (p <= hi), axis=1)
                assert inside.mean() > 0.995, (sc.id, info.category, inside.mean())
                objects += not info.is_structure
            labels = {lab.id: lab for lab in rend.labels(out.instances)}
            assert set(labels) == set(np.unique(ids).tolist())
            for i, lab in labels.items():
                assert lab.category == sc.instances[i].category and lab.pixels == int((ids == i).sum())


def test_doors_connect_all_rooms() -> None:
    for seed in range(20):
        sc = generate_house(seed)
        # the door graph is connected
        parent = {r.id: r.id for r in sc.rooms}

        def find(a: str, parent: dict[str, str] = parent) -> str:
            while parent[a] != a:
                a = parent[a]
            return a

        for d in sc.doors:
            parent[find(d.rooms[0])] = find(d.rooms[1])
        assert len({find(r.id) for r in sc.rooms}) == 1, seed
        # and the robot can really walk into every room from a start pose
        start = sample_start_pose(sc, np.random.default_rng(seed))
        reach, ox, oy = reachable_map(sc, start)
        for r in sc.rooms:
            x0, y0, x1, y1 = r.rect
            sub = reach[int((y0 - oy) / 0.05) : int((y1 - oy) / 0.05), int((x0 - ox) / 0.05) : int((x1 - ox) / 0.05)]
            assert sub.mean() > 0.25, (seed, r.id, r.kind, sub.mean())


def test_navigable_grid_orientation(houses) -> None:
    sc, _ = houses[SEEDS[1]]
    grid, ox, oy = sc.navigable_grid(0.1)
    room = sc.rooms[0]
    x0, _y0, x1, _y1 = room.rect
    # a cell on the room's own wall slab (x0..x0+0.05) is blocked; row = y, column = x
    i = int((room.center[1] - oy) / 0.1)
    j = int((x0 + 0.02 - ox) / 0.1)
    assert not grid[i, j]
    assert grid.dtype == bool and grid.shape[1] >= int((x1 - ox) / 0.1)
    assert 0.3 < grid.sum() * 0.01 / sc.floor_area_m2 < 1.0


def test_pose_errors(houses) -> None:
    sc, _ = houses[SEEDS[0]]
    good = sample_start_pose(sc, np.random.default_rng(1), clearance=0.5)
    assert pose_error(sc, good) is None
    assert pose_error(sc, good, clearance=0.5) is None
    room = sc.rooms[0]
    in_wall = Pose2D(x=room.rect[0] + 0.02, y=room.center[1], yaw=0.0)
    assert "collision" in pose_error(sc, in_wall)
    assert "off the floor" in pose_error(sc, (-5.0, -5.0, 0.0))
    assert "non-finite" in pose_error(sc, (float("nan"), 1.0, 0.0))
    furniture = [o for o in sc.objects() if o.category in ("bed", "kitchen_counter", "sofa", "wardrobe")]
    assert furniture
    assert "collision" in pose_error(sc, (furniture[0].position[0], furniture[0].position[1], 0.0))


def test_same_seed_gives_byte_identical_scene_files(tmp_path) -> None:
    a = load_or_generate("gen-00005", tmp_path / "a")
    b = load_or_generate("gen-00005", tmp_path / "b")
    assert a.id == b.id == "gen-00005"
    files = sorted(p.name for p in (tmp_path / "a" / "gen-00005").iterdir())
    assert "scene.json" in files and "vertices.npy" in files
    for name in files:
        assert (tmp_path / "a" / "gen-00005" / name).read_bytes() == (tmp_path / "b" / "gen-00005" / name).read_bytes()
    c = load_or_generate("gen-00005", tmp_path / "a")  # reloaded from the files
    assert np.array_equal(c.triangle_instance, a.triangle_instance) and c.instances == a.instances
    other = generate_house(6)
    assert other.vertices.shape != a.vertices.shape or not np.array_equal(other.vertices, a.vertices)


def test_unknown_scene_and_broken_mesh(tmp_path) -> None:
    with pytest.raises(SceneNotFound, match="gen-<seed>"):
        load_or_generate("no-such-house", tmp_path)
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat garbage\n\x00\x01")
    with pytest.raises(SceneLoadError, match="does not parse"):
        load_or_generate("broken", tmp_path)


def test_real_mesh_with_vertex_colours_renders(tmp_path) -> None:
    """A 4 x 3 x 2.5 m room as a .ply with vertex colours loads through the same renderer."""
    box = o3d.geometry.TriangleMesh.create_box(4.0, 3.0, 2.5)
    box.compute_vertex_normals()
    box.vertex_colors = o3d.utility.Vector3dVector(np.tile([[0.8, 0.2, 0.1]], (len(box.vertices), 1)))
    o3d.io.write_triangle_mesh(str(tmp_path / "room.ply"), box)
    sc = load_or_generate("room", tmp_path)
    assert sc.instances == {} and sc.vertex_colors is not None
    out = Renderer(sc).render(camera_pose(Pose2D(x=1.0, y=1.5, yaw=0.0), tilt_deg=0.0), intrinsics(81, 61), 81, 61)
    assert out.depth[30, 40] == pytest.approx(3.0, abs=0.01)  # wall x = 4, camera x = 1
    assert (out.instances == -1).all()
    r, g, b = out.rgb[30, 40].astype(int)
    assert r > 2 * g and r > 2 * b  # the vertex colour shows
    grid, _, _ = sc.navigable_grid(0.1)
    assert 8.0 < grid.sum() * 0.01 < 12.5
