"""HELIOS tasks in the simulator: generated episodes, the oracle pick, the heuristic place with its drop test,
collisions."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest

from eqa.instructions import InstructionError, parse_instruction
from eqa.messages import Pose2D, Task
from services.sim.camera import camera_pose, intrinsics
from services.sim.housegen import generate_house
from services.sim.meshbuild import MeshBuilder
from services.sim.motion import reachable_map
from services.sim.render import Renderer
from services.sim.scene import InstanceInfo, Room, Scene
from services.sim.skills import REACH_M, path_collides, pick, pick_poses, place
from services.sim.tasks import GOAL_RECEPTACLES, PICKABLE, generate_tasks, task_benchmark


def _room_scene() -> Scene:
    """A 6 x 6 m room: floor, walls, a table (0.75 m top, x 2..3, y 2..3), a thin post (0.04 m wide, 1 m
    high at x 4.5, y 2.5) and a mug on the table."""
    mb = MeshBuilder()
    inst = {
        0: InstanceInfo(0, "floor", "r0", "kitchen", is_structure=True, position=(3, 3, 0), size=(6, 6, 0)),
        1: InstanceInfo(1, "wall", "r0", "kitchen", is_structure=True, position=(3, 3, 1.35), size=(6, 6, 2.7)),
        2: InstanceInfo(2, "dining_table", "r0", "kitchen", position=(2.5, 2.5, 0.375), size=(1, 1, 0.75)),
        3: InstanceInfo(3, "post", "r0", "kitchen", position=(4.5, 2.5, 0.5), size=(0.04, 0.04, 1.0)),
        4: InstanceInfo(4, "mug", "r0", "kitchen", position=(2.5, 2.5, 0.805), size=(0.1, 0.1, 0.11), support=2),
    }
    mb.quad_z(0, 0, 6, 6, 0.0, 0, (200, 200, 200))
    for lo, hi in (((0, 0, 0), (6, 0.1, 2.7)), ((0, 5.9, 0), (6, 6, 2.7)), ((0, 0, 0), (0.1, 6, 2.7)),
                   ((5.9, 0, 0), (6, 6, 2.7))):
        mb.box(lo, hi, 1, (220, 220, 220))
    mb.box((2, 2, 0.71), (3, 3, 0.75), 2, (120, 80, 40))
    for x, y in ((2, 2), (2.95, 2), (2, 2.95), (2.95, 2.95)):
        mb.box((x, y, 0), (x + 0.05, y + 0.05, 0.71), 2, (100, 70, 30))
    mb.box((4.48, 2.48, 0), (4.52, 2.52, 1.0), 3, (50, 50, 50))
    mb.box((2.45, 2.45, 0.75), (2.55, 2.55, 0.86), 4, (200, 40, 40))
    v, t, ti, tc = mb.arrays()
    return Scene(id="room", seed=None, vertices=v, triangles=t, triangle_instance=ti, triangle_colors=tc,
                 instances=inst, rooms=[Room("r0", "kitchen", (0, 0, 6, 6))])


@pytest.fixture(scope="module")
def room() -> Scene:
    return _room_scene()


def _frame_ids(scene: Scene, pose: Pose2D, w: int = 320, h: int = 240) -> np.ndarray:
    return Renderer(scene).render(camera_pose(pose), intrinsics(w, h), w, h).instances


# ---- pick ---------------------------------------------------------------------------------------------------


def test_pick_needs_the_target_in_frame_and_within_reach(room) -> None:
    facing = Pose2D(x=1.7, y=2.5, yaw=0.0)  # 0.3 m from the table's edge, looking at the mug
    ok = pick(room, facing, _frame_ids(room, facing), [4])
    assert ok.success and ok.object_id == 4 and ok.distance_m == pytest.approx(2.45 - 1.7, abs=1e-6)
    away = Pose2D(x=1.7, y=2.5, yaw=math.pi)  # same place, looking away: not in frame
    r = pick(room, away, _frame_ids(room, away), [4])
    assert not r.success and "in frame" in r.reason and "reach" not in r.reason
    far = Pose2D(x=0.8, y=2.5, yaw=0.0)  # in view but 1.65 m away
    r = pick(room, far, _frame_ids(room, far), [4])
    assert not r.success and "reach" in r.reason
    assert REACH_M < 2.7 and not pick(room, facing, _frame_ids(room, facing), [3]).success  # the post: far
    assert not pick(room, facing, _frame_ids(room, facing), []).success


def test_pick_poses_are_poses_where_pick_succeeds(room) -> None:
    reach, ox, oy = reachable_map(room)
    poses = pick_poses(room, 4, reach, (ox, oy))
    assert poses
    for p in poses[:4]:
        assert pick(room, p, _frame_ids(room, p, 160, 120), [4]).success


# ---- place --------------------------------------------------------------------------------------------------


def test_place_on_the_table_in_front(room) -> None:
    r = place(room, Pose2D(x=1.4, y=2.3, yaw=0.0), (0.1, 0.1, 0.11), goal_ids=[2])
    assert r.success and r.support_id == 2
    # dropped above the highest point in front (the mug's top at 0.86 m is out of this region: y 2.0..2.6 but
    # x 1.7..2.4 only reaches the table's near half) -> rests on the table top at 0.75 m
    assert r.rest_xyz is not None and r.rest_xyz[2] == pytest.approx(0.75 + 0.055, abs=0.012)


def test_place_chooses_a_free_spot_of_the_goal_receptacle_not_what_stands_on_it(room) -> None:
    """The heuristic place chooses its point on the goal receptacle's pixels (the flattest free spot of the
    class's mask), so an object standing on the receptacle is no landing place; with no class given, the highest
    point in front (here the mug's top) takes the object."""
    facing = Pose2D(x=1.6, y=2.5, yaw=0.0)  # the region x 1.9..2.6, y 2.2..2.8 holds the mug at x, y 2.45..2.55
    blind = place(room, facing, (0.1, 0.1, 0.11), goal_ids=[2])
    assert blind.drop_xyz is not None and blind.drop_xyz[2] > 0.86 and "tipped" in blind.reason  # off the mug
    r = place(room, facing, (0.1, 0.1, 0.11), goal_ids=[2], goal_category="dining_table")
    assert r.success and r.support_id == 2 and r.drop_xyz is not None and r.reason.startswith("placed on")
    assert r.rest_xyz is not None and r.rest_xyz[2] == pytest.approx(0.75 + 0.055, abs=0.012)
    assert max(abs(r.drop_xyz[0] - 2.5), abs(r.drop_xyz[1] - 2.5)) >= 0.05 + 0.05  # clear of the mug's box


def test_place_on_a_thin_post_tips_off(room) -> None:
    # the highest point in front is the post's top (1.0 m): a 0.3 m object balanced on 4 cm tips over, falls
    r = place(room, Pose2D(x=3.9, y=2.5, yaw=0.0), (0.3, 0.3, 0.1), goal_ids=[2, 3])
    assert not r.success and "tipped" in r.reason and r.support_id == 0
    assert r.drop_xyz is not None and r.drop_xyz[2] == pytest.approx(1.05, abs=0.01)


def test_place_on_the_wrong_receptacle_fails(room) -> None:
    r = place(room, Pose2D(x=1.4, y=2.3, yaw=0.0), (0.1, 0.1, 0.11), goal_ids=[3])
    assert not r.success and r.support_id == 2 and "not on a goal receptacle" in r.reason


def test_place_over_the_floor_only(room) -> None:
    r = place(room, Pose2D(x=1.0, y=4.5, yaw=0.0), (0.1, 0.1, 0.11), goal_ids=[2])
    assert not r.success and r.support_id == 0


def test_place_tips_off_an_edge() -> None:
    """A wide object dropped with its centre on the table's edge tips off onto the floor."""
    from services.sim import skills

    sc = _room_scene()
    old = skills.PLACE_REGION
    try:
        skills.PLACE_REGION = (0.61, 0.62, 0.0)  # one probe: 0.61 m ahead -> x = 2.01 (table edge at 2.0)
        r = place(sc, Pose2D(x=1.4, y=2.5, yaw=0.0), (0.8, 0.2, 0.1), goal_ids=[2])
        assert not r.success and "tipped" in r.reason and r.support_id == 0
        skills.PLACE_REGION = (0.9, 0.91, 0.0)  # 0.3 m inside the edge: it stays
        assert place(sc, Pose2D(x=1.4, y=2.5, yaw=0.0), (0.4, 0.2, 0.1), goal_ids=[2]).success
    finally:
        skills.PLACE_REGION = old


# ---- collisions ---------------------------------------------------------------------------------------------


def test_path_collides_through_the_table_not_around_it(room) -> None:
    assert path_collides(room, [(1.0, 2.5), (4.0, 2.5)])  # straight through the table
    assert not path_collides(room, [(1.0, 1.0), (4.0, 1.0)])  # along free floor
    assert path_collides(room, [(1.0, 1.0), (7.0, 1.0)])  # out of the house


# ---- episodes -----------------------------------------------------------------------------------------------


def _digest(scene: Scene) -> str:
    h = hashlib.sha256(scene.vertices.tobytes() + scene.triangle_instance.tobytes())
    h.update(repr(sorted((i.id, i.category, i.position, i.support) for i in scene.instances.values())).encode())
    return h.hexdigest()


@pytest.fixture(scope="module")
def gen_tasks() -> list[tuple[Scene, list[Task]]]:
    out = []
    for seed in (115000, 115002):
        sc = generate_house(seed)
        before = _digest(sc)
        tasks = generate_tasks(sc, np.random.default_rng(seed))
        assert _digest(sc) == before  # tasks never change a house
        out.append((sc, tasks))
    return out


def test_generated_tasks_are_well_formed_and_feasible(gen_tasks) -> None:
    kinds = set()
    for sc, tasks in gen_tasks:
        for t in tasks:
            kinds.add(t.kind)
            parsed = parse_instruction(t.text)
            assert parsed.kind == t.kind and parsed.object == t.object
            assert t.max_steps and t.start_pose is not None and t.object_ids
            if t.kind == "pick_place":
                assert parsed.start_receptacle == t.start_receptacle and parsed.goal_receptacle == t.goal_receptacle
                assert t.object in PICKABLE and t.goal_receptacle in GOAL_RECEPTACLES
                assert t.goal_receptacle != t.start_receptacle
                for oid in t.object_ids:
                    info = sc.instances[oid]
                    assert info.category == t.object and sc.instances[info.support].category == t.start_receptacle
                assert all(sc.instances[g].category == t.goal_receptacle for g in t.goal_receptacle_ids)
                reach, ox, oy = reachable_map(sc, t.start_pose)
                assert any(pick_poses(sc, oid, reach, (ox, oy)) for oid in t.object_ids)
            else:
                assert t.shortest_path_m is not None and t.shortest_path_m >= 1.0
                assert all(sc.instances[o].category == t.object for o in t.object_ids)
    assert kinds == {"pick_place", "find_object"}


def test_tasks_are_deterministic() -> None:
    sc = generate_house(115001)
    a = generate_tasks(sc, np.random.default_rng(3))
    b = generate_tasks(generate_house(115001), np.random.default_rng(3))
    assert [t.model_dump() for t in a] == [t.model_dump() for t in b]


def test_task_benchmark_split_and_roles() -> None:
    tune = task_benchmark(11, pick_place=2, find=1)
    ev = task_benchmark(1, pick_place=2, find=1)
    assert tune.role == "tuning" and ev.role == "evaluation"
    assert len(tune.of_kind("pick_place")) == 2 and len(tune.of_kind("find_object")) == 1
    assert not {t.scene for t in tune.tasks} & {t.scene for t in ev.tasks}
    # the question benchmark's houses are gen-{seed*10000 + i}, i < 1000: tasks use another range
    assert all(int(t.scene[4:]) % 10000 >= 5000 for t in tune.tasks + ev.tasks)


def test_instruction_parser() -> None:
    p = parse_instruction("Move the red mug from the kitchen counter to the bedroom table")
    assert (p.kind, p.object, p.object_color, p.start_receptacle, p.goal_receptacle) == (
        "pick_place", "mug", "red", "kitchen_counter", "bedroom_table")
    assert parse_instruction("find a potted plant.").object == "potted_plant"
    for bad in ("", "dance", "Move the mug", "x" * 600, "find a <script>"):
        with pytest.raises(InstructionError):
            parse_instruction(bad)


# ---- one task episode's metrics -----------------------------------------------------------------------------


def _mug_task(**kw: object) -> Task:
    return Task(id="t", kind="pick_place", text="Move the mug from the dining table to the dining table",
                scene="room", object="mug", start_receptacle="dining_table", goal_receptacle="dining_table",
                object_ids=[4], start_receptacle_ids=[2], goal_receptacle_ids=[2], **kw)  # type: ignore[arg-type]


def _run_episode(room: Scene, pick_limit: int | None, through_table: bool = False):
    from services.sim.task_episode import TaskEpisode

    ep = TaskEpisode(_mug_task(), pick_limit=pick_limit)
    far = Pose2D(x=0.8, y=2.5, yaw=0.0)
    ep.observe(room, far, _frame_ids(room, far))
    assert not ep.find_obj
    assert not ep.pick(room, far, _frame_ids(room, far)).success  # a failed attempt (too far)
    near = Pose2D(x=1.7, y=2.5, yaw=0.0)
    ep.move(room, [(0.8, 2.5), (1.7, 2.5)])
    assert ep.pick(room, near, _frame_ids(room, near)).success and ep.find_obj
    ep.observe(room, near, _frame_ids(room, near))
    assert ep.find_rec
    if through_table:
        ep.move(room, [(1.7, 2.5), (3.3, 2.5)])
    back = Pose2D(x=1.4, y=2.3, yaw=0.0)
    assert ep.place(room, back).success
    return ep


def test_task_episode_metrics_pick_limits_and_collisions(room) -> None:
    from services.sim.task_episode import TaskEpisode

    ep = _run_episode(room, None)
    assert ep.metrics() == {"FindObj": 1.0, "Pick": 1.0, "FindRec": 1.0, "Place": 1.0, "SR": 1.0,
                            "collisions": 0.0, "pick_attempts": 2.0}
    assert _run_episode(room, 5).metrics()["SR"] == 1.0
    over = _run_episode(room, 1).metrics()  # 2 attempts with a limit of 1: everything 0
    assert over["FindObj"] == over["Pick"] == over["Place"] == over["SR"] == 0.0
    hit = _run_episode(room, None, through_table=True).metrics()
    assert hit["collisions"] == 1.0 and hit["Place"] == 1.0 and hit["SR"] == 0.0
    again = TaskEpisode.from_json(json.loads(json.dumps(ep.to_json())))
    assert again.metrics() == ep.metrics() and again.task == ep.task


def test_find_object_success_and_spl(room) -> None:
    from services.sim.task_episode import TaskEpisode

    task = Task(id="f", kind="find_object", text="Find a mug", scene="room", object="mug", object_ids=[4],
                shortest_path_m=2.0)
    ep = TaskEpisode(task)
    ep.move(room, [(1.0, 1.0), (1.0, 2.5), (1.7, 2.5)])  # 1.5 + 0.7 = 2.2 m
    assert ep.stop(room, Pose2D(x=1.7, y=2.5))
    assert ep.metrics()["SR"] == 1.0 and ep.metrics()["SPL"] == pytest.approx(2.0 / 2.2)
    miss = TaskEpisode(task)
    assert not miss.stop(room, Pose2D(x=0.5, y=0.5)) and miss.metrics()["SPL"] == 0.0
