"""Houses that change (services/sim/changes.py, services/sim/change_impact.py): seeded rounds, the mesh and
scene graph really changed, rendered frames (also from the sim service over real Zenoh), and which questions the
changes affect.

The hand-checked cases are of house gen-00042 (its changes of rounds 1 and 2 are listed in
``test_rounds_of_gen_42``): round 1 opens the white hallway trash can (31), switches the kitchen kettle on (46)
and removes the living room's potted plant (85); round 2 switches the living room television off (87) and moves
the black trash can (32) from the hallway to a bedroom and the gray one (74) from a bedroom to the hallway.
"""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from support.fleet import wait_for
from support.services import serving

from eqa import keys
from eqa.bus import Bus
from eqa.messages import EpisodeStart, ErrorReply, Frame, Question
from services.sim.camera import camera_pose, intrinsics
from services.sim.catalog import SMALL_OBJECTS
from services.sim.change_impact import impact, rederive
from services.sim.changes import (
    CHANGES_PER_ROUND,
    MAX_ROUNDS,
    changed_house,
    changed_scene_id,
    changes_of,
    parse_changed_id,
)
from services.sim.housegen import generate_house
from services.sim.library import floor_area, load_or_generate
from services.sim.motion import pose_error, reachable_map
from services.sim.questions import generate_questions, witness_poses
from services.sim.render import Renderer
from services.sim.scene import SceneNotFound
from services.sim.service import SimService, load_scene

BASE = "gen-00042"


@pytest.fixture(scope="module")
def houses() -> dict[int, tuple]:
    base = generate_house(42)
    out: dict[int, tuple] = {0: (base, [])}
    for k in (1, 2):
        out[k] = changed_house(base, k)
    return out


def _kinds(changes) -> list[tuple[int, str, int]]:
    return [(c.round, c.kind, c.object_id) for c in changes]


def test_rounds_of_gen_42(houses) -> None:
    _, ch2 = houses[2]
    assert _kinds(ch2) == [(1, "state", 31), (1, "state", 46), (1, "remove", 85),
                           (2, "state", 87), (2, "move", 32), (2, "move", 74)]
    by_id = {(c.round, c.object_id): c for c in ch2}
    assert by_id[(1, 31)].before["state"] == "closed" and by_id[(1, 31)].after["state"] == "open"
    assert by_id[(2, 87)].before["state"] == "on" and by_id[(2, 87)].after["state"] == "off"
    move = by_id[(2, 32)]
    assert move.before["room_kind"] == "hallway" and move.after["room_kind"] == "bedroom"
    assert all(len([c for c in ch2 if c.round == r]) == CHANGES_PER_ROUND for r in (1, 2))


def test_deterministic_and_one_history(houses) -> None:
    base, _ = houses[0]
    again, ch_again = changed_house(generate_house(42), 2)
    sc2, ch2 = houses[2]
    assert [c.to_json() for c in ch_again] == [c.to_json() for c in ch2]
    for name in ("vertices", "triangles", "triangle_instance", "triangle_colors"):
        assert np.array_equal(getattr(again, name), getattr(sc2, name)), name
    assert again.graph() == sc2.graph() and sc2.id == "gen-00042-c2" and sc2.seed == 42
    # rounds 1..k of "-c<k>" are the first rounds of every later house of the same base
    assert _kinds(houses[1][1]) == _kinds(ch2)[:CHANGES_PER_ROUND]
    assert _kinds(changes_of(base, 3))[: len(ch2)] == _kinds(ch2)
    # the base house is left as it was
    assert base.graph() == generate_house(42).graph()


def test_mesh_and_graph_really_changed(houses) -> None:
    base, _ = houses[0]
    sc, _ = houses[2]
    # removed: no triangle and no graph entry left
    assert 85 in base.instances and 85 not in sc.instances
    assert not (sc.triangle_instance == 85).any() and (base.triangle_instance == 85).any()
    # moved: the object's triangles are at its new scene-graph position, in the other room
    tri = sc.vertices[sc.triangles[sc.triangle_instance == 32]].reshape(-1, 3)
    centre = (tri.min(axis=0) + tri.max(axis=0)) / 2
    assert np.allclose(centre, sc.instances[32].position, atol=1e-3)
    assert sc.room_at(*centre[:2]).kind == "bedroom"
    assert base.room_at(*base.instances[32].position[:2]).kind == "hallway"
    assert np.hypot(*(np.array(sc.instances[32].position[:2]) - base.instances[32].position[:2])) > 3.0
    # switched: the television's screen shows "off" (dark) where the base house shows "on" (lit)
    lit, dark = (150, 190, 255), (12, 12, 14)

    def colours(s, iid):
        return {tuple(c) for c in s.triangle_colors[s.triangle_instance == iid].tolist()}

    assert lit in colours(base, 87) and dark not in colours(base, 87)
    assert dark in colours(sc, 87) and lit not in colours(sc, 87)
    assert sc.instances[87].attributes["state"] == "off"
    # every vertex is used (removed geometry compacted away) and the robot can still reach the whole house
    assert len(np.unique(sc.triangles)) == len(sc.vertices)
    assert reachable_map(sc)[0].sum() >= reachable_map(base)[0].sum() * 0.97


def test_rendered_frames_show_the_move(houses) -> None:
    base, _ = houses[0]
    sc, _ = houses[2]
    K = intrinsics(160, 120)
    seen_before = witness_poses(base, None, ids=[32])[32]
    seen_after = witness_poses(sc, None, ids=[32])[32]

    def ids_at(s, pose) -> set[int]:
        return set(np.unique(Renderer(s).render(camera_pose(pose), K, 160, 120).instances).tolist())

    assert 32 in ids_at(base, seen_before) and 32 not in ids_at(sc, seen_before)
    assert 32 in ids_at(sc, seen_after) and 32 not in ids_at(base, seen_after)
    # the labels a frame carries (what the oracle perception models read) say the new state and room
    tv_pose = witness_poses(sc, None, ids=[87])[87]
    for s, state in ((base, "on"), (sc, "off")):
        r = Renderer(s)
        labels = {lab.id: lab for lab in r.labels(r.render(camera_pose(tv_pose), K, 160, 120).instances)}
        assert labels[87].attributes["state"] == state
    r = Renderer(sc)
    labels = {lab.id: lab for lab in r.labels(r.render(camera_pose(seen_after), K, 160, 120).instances)}
    assert labels[32].room_kind == "bedroom"


def test_saved_reloaded_and_bad_ids(tmp_path, houses) -> None:
    sc = load_or_generate("gen-00042-c2", tmp_path)
    assert (tmp_path / "gen-00042-c2" / "scene.json").exists() and (tmp_path / BASE / "scene.json").exists()
    again = load_or_generate("gen-00042-c2", tmp_path)  # from the files
    assert again.graph() == sc.graph() == houses[2][0].graph()
    assert json.loads((tmp_path / "gen-00042-c2" / "scene.json").read_text())["id"] == "gen-00042-c2"
    # built round by round from the cached house before it: the same arrays as all rounds at once
    assert (tmp_path / "gen-00042-c1" / "scene.json").exists()
    for name in ("vertices", "triangles", "triangle_instance", "triangle_colors"):
        assert np.array_equal(getattr(again, name), getattr(houses[2][0], name)), name
    assert floor_area("gen-00042-c2", tmp_path) == houses[0][0].floor_area_m2
    assert not (tmp_path / "gen-00042-c3").exists()
    floor_area("gen-00042-c3", tmp_path)  # the gateway's budget check builds no changed house
    assert not (tmp_path / "gen-00042-c3").exists()
    for bad in ("gen-00042-c0", f"gen-00042-c{MAX_ROUNDS + 1}"):
        for load in (load_or_generate, floor_area):
            with pytest.raises(SceneNotFound, match="rounds of changes"):
                load(bad, tmp_path)
    with pytest.raises(SceneNotFound, match="unknown scene"):
        load_or_generate("gen-00042-c", tmp_path)
    assert parse_changed_id("gen-00042-c7") == (BASE, 7) and parse_changed_id(BASE) is None
    assert changed_scene_id(BASE, 0) == BASE and changed_scene_id(BASE, 3) == "gen-00042-c3"
    with pytest.raises(ValueError, match="generated house"):
        changed_scene_id("room", 1)


def test_rederive_reproduces_the_generator() -> None:
    """In the question's own house the re-derived ground truth is the generator's, for every question made."""
    n = 0
    for seed in (42, 5, 9):
        sc = generate_house(seed)
        for q in generate_questions(sc, np.random.default_rng([0, seed, 11])):
            again = rederive(q, sc)
            assert again is not None and again.answer == q.answer and again.evidence_ids == sorted(q.evidence_ids)
            assert again.targets == q.targets and again.start_pose == q.start_pose and again.id == q.id
            n += 1
    assert n >= 25


def _q(qid: str, text: str, choices: list[str], answer: str, evidence: list[int], query: dict[str, str]) -> Question:
    return Question(id=qid, text=text, choices=choices, scene=BASE, category=query["type"], query=query,
                    answer=answer, evidence_ids=evidence)


def test_affected_questions_hand_checked(houses) -> None:
    base, _ = houses[0]
    (sc1, ch1), (sc2, ch2) = houses[1], houses[2]
    yes_no = ["Yes", "(Do not choose this option)", "No", "(Do not choose this option)"]

    # state: the television is switched off in round 2 ("Is it off?" No -> Yes)
    tv = _q("tv", "Is the television in the living room off?", yes_no, "C", [87],
            {"type": "state", "category": "television", "room_kind": "living_room", "attribute": "state",
             "value": "off"})
    assert rederive(tv, base).answer == "C"
    assert not impact(tv, ch1, sc1).affected
    im = impact(tv, ch2, sc2)
    assert im.affected and im.answer_changed and im.question.answer == "A" and im.touched == [87]
    assert im.question.scene == "gen-00042-c2" and im.question.id == "tv-c2"

    # counting: three trash cans in the hallway before and after, but not the same three (evidence changed)
    cans = _q("cans", "How many trash cans are there in the hallway?", ["One", "Three", "Five", "Two"], "B",
              [31, 32, 34], {"type": "counting", "category": "trash_can", "room_kind": "hallway"})
    im = impact(cans, ch2, sc2)
    assert im.affected and not im.answer_changed and im.evidence_changed
    assert im.question.answer == "B" and im.question.evidence_ids == [31, 34, 74]
    im1 = impact(cans, ch1, sc1)  # round 1 only opens can 31: same cans, one of them changed
    assert im1.affected and not im1.answer_changed and im1.question.evidence_ids == [31, 32, 34] and im1.touched == [31]

    # existence: the living room's only potted plant is removed in round 1 (Yes -> No, no evidence left)
    assert [o.id for o in base.objects() if o.category == "potted_plant" and o.room_kind == "living_room"] == [85]
    plant = _q("plant", "Is there a potted plant in the living room?", yes_no, "A", [85],
               {"type": "existence", "category": "potted_plant", "room_kind": "living_room"})
    im = impact(plant, ch1, sc1)
    assert im.affected and im.answer_changed and im.question.answer == "C" and im.question.evidence_ids == []

    # location: the only black trash can of the hallway... is not unique (57 is black too): no ground truth
    black = _q("black", "Where is the black trash can?", ["In the hallway", "In the bedroom", "In the kitchen",
                                                          "In the garage"], "A", [32],
               {"type": "location", "category": "trash_can", "color": "black"})
    assert rederive(black, base) is None and impact(black, ch2, sc2).question is None

    # unaffected: the mug in the living room and every generated question no change touches
    qs = generate_questions(base, np.random.default_rng([0, 42, 11]))
    touched = {c.object_id for c in ch2}
    for q in qs:
        im = impact(q, ch2, sc2)
        if not (set(q.evidence_ids) | set(im.question.evidence_ids if im.question else [])) & touched:
            assert not im.affected and im.question.answer == q.answer, q.id
        assert im.question is None or pose_error(sc2, im.question.start_pose, clearance=0.5) is None
    assert [q.id for q in qs if impact(q, ch2, sc2).affected] == ["gen-00042-sta0"]


def test_sim_service_renders_a_changed_house(hub_settings, settings, houses) -> None:
    """Over real Zenoh: an episode in gen-00042-c2 is rendered from the changed house (the moved can is where
    the change put it), one in gen-00042 from the base house, at the same pose."""
    sc = houses[2][0]
    pose = witness_poses(sc, None, ids=[32])[32]
    frames: dict[str, Frame] = {}
    lock = threading.Lock()
    with Bus(hub_settings, "gateway", "test") as bus:
        def on_frame(k: str, m: Frame) -> None:
            with lock:
                frames.setdefault(m.episode_id, m)

        bus.subscribe(keys.any_robot(keys.SIM_FRAME), Frame, on_frame)
        errors: list[ErrorReply] = []
        bus.subscribe(keys.any_robot(keys.SIM_ERROR), ErrorReply, lambda _k, m: errors.append(m))
        with serving(SimService(settings)):
            for ep, robot, scene in (("ep-c2", "r0", "gen-00042-c2"), ("ep-base", "r1", BASE),
                                     ("ep-bad", "r2", f"gen-00042-c{MAX_ROUNDS + 1}")):
                q = Question(text="Where is the black trash can?", choices=["In the hallway", "In the bedroom"],
                             scene=scene, start_pose=pose)
                bus.publish(keys.stream(robot, keys.EPISODE_START),
                            EpisodeStart(episode_id=ep, robot=robot, question=q, max_steps=5, seed=1, record=False))
            assert wait_for(lambda: len(frames) >= 2 and errors, timeout=60.0)
    assert [(e.episode_id, e.step) for e in errors] == [("ep-bad", 0)] and "rounds of changes" in errors[0].reason
    assert "ep-bad" not in frames
    changed, base = frames["ep-c2"], frames["ep-base"]
    assert changed.scene == "gen-00042-c2" and base.scene == BASE
    assert 32 in set(np.unique(changed.instances).tolist()) and 32 not in set(np.unique(base.instances).tolist())
    assert (settings.scenes_path / "gen-00042-c2" / "scene.json").exists()
    assert load_scene(settings, "gen-00042-c2").graph() == sc.graph()


def test_cli_lists_changes_and_affected_questions(tmp_path, capsys, houses) -> None:
    from services.sim.cli import main

    assert main(["sim", "changes", "--scene", BASE, "--rounds", "2", "--questions", "--scenes-dir", str(tmp_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scene"] == "gen-00042-c2" and out["changes"] == [c.to_json() for c in houses[2][1]]
    affected = [q["id"] for q in out["questions"] if q["affected"]]
    assert affected == ["gen-00042-sta0"] and len(out["questions"]) == 10
    for bad in (["--scene", "gen-00042-c1"], ["--scene", BASE, "--rounds", "0"], ["--scene", BASE, "--rounds", "21"]):
        assert main(["sim", "changes", *bad, "--scenes-dir", str(tmp_path)]) == 2


@pytest.mark.parametrize("seed", [3, 17, 10_001, 20_002, 30_003])
def test_changed_houses_stay_consistent(seed: int) -> None:
    """Over several houses: the mesh and the scene graph agree after the changes (every object's triangles
    are where its graph entry says, no triangle of a removed object), small objects only, the robot's free space
    is not cut."""
    base = generate_house(seed)
    sc, changes = changed_house(base, 3)
    assert len(changes) == 3 * CHANGES_PER_ROUND
    assert {c.category for c in changes} <= set(SMALL_OBJECTS)
    ids = set(np.unique(sc.triangle_instance).tolist())
    assert ids == set(sc.instances), (ids ^ set(sc.instances))
    for c in changes:
        if c.after is None or c.object_id not in sc.instances:  # removed (maybe in a later round)
            continue
        o = sc.instances[c.object_id]
        if c.after["position"] != list(o.position):  # changed again in a later round
            continue
        tri = sc.vertices[sc.triangles[sc.triangle_instance == o.id]].reshape(-1, 3)
        assert np.allclose((tri.min(axis=0) + tri.max(axis=0)) / 2, o.position, atol=1e-3), c
        assert np.allclose(tri.max(axis=0) - tri.min(axis=0), o.size, atol=1e-3), c
        assert sc.room_at(o.position[0], o.position[1]).id == o.room
        if o.support is not None:
            assert sc.instances[o.support].category not in SMALL_OBJECTS
    assert reachable_map(sc)[0].sum() >= reachable_map(base)[0].sum() * 0.97


def test_a_start_pose_an_added_object_stands_on_moves_to_free_floor(houses) -> None:
    base = houses[0][0]
    sc, changes = changed_house(base, 3)
    added = [c for c in changes if c.kind == "add" and c.after["support"] is None]
    assert [(c.round, c.category) for c in added] == [(3, "laundry_basket")]
    x, y, _ = sc.instances[added[0].object_id].position
    q = Question(id="q", text="Is there a laundry basket in the bedroom?", choices=["Yes", "No"], scene=BASE,
                 category="existence",
                 query={"type": "existence", "category": "laundry_basket", "room_kind": "bedroom"},
                 answer="B", start_pose={"x": x, "y": y, "yaw": 0.5})
    assert rederive(q.model_copy(update={"start_pose": None}), base).answer == "B"  # no basket in a bedroom before
    assert pose_error(sc, q.start_pose, clearance=0.5) is not None  # the basket stands there now
    moved = rederive(q, sc)
    assert moved.answer == "A" and moved.evidence_ids == [added[0].object_id]
    assert pose_error(sc, moved.start_pose, clearance=0.5) is None and moved.start_pose.yaw == 0.5
    assert np.hypot(moved.start_pose.x - x, moved.start_pose.y - y) < 1.5
