"""Questions on generated houses, the benchmark, and the real HM-EQA loader."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import open3d as o3d
import pytest

from eqa.messages import PADDING_CHOICE
from eqa.settings import Settings
from services.sim.camera import camera_pose, intrinsics
from services.sim.catalog import COLORS, PLURAL_ONLY, ROOM_KINDS, display_name
from services.sim.hmeqa import load_hmeqa, missing_scans, scan_path
from services.sim.housegen import generate_house
from services.sim.motion import pose_error, reachable_map
from services.sim.questions import (
    CATEGORIES,
    NUMBER_WORDS,
    benchmark,
    benchmark_candidates,
    generate_questions,
    witness_poses,
)
from services.sim.render import Renderer
from services.sim.service import load_scene

HMEQA = "/work/shared/data/hm-eqa"


@pytest.fixture(scope="module")
def qsets() -> list:
    out = []
    for seed in (2, 4, 9):
        sc = generate_house(seed)
        out.append((sc, generate_questions(sc, np.random.default_rng(seed))))
    return out


def test_question_form(qsets) -> None:
    seen = Counter()
    for sc, qs in qsets:
        for q in qs:
            seen[q.category] += 1
            assert q.category in CATEGORIES and q.query["type"] == q.category
            assert len(q.choices) == 4 and q.answer in "ABCD" and q.scene == sc.id
            assert q.max_steps == int(3 * math.sqrt(sc.floor_area_m2))
            assert pose_error(sc, q.start_pose, clearance=0.5) is None
            answer = q.choices["ABCD".index(q.answer)]
            assert "answer" not in q.query and all(v != answer for v in q.query.values())
            if q.category in ("existence", "state"):
                assert sorted(q.choices) == sorted(["Yes", "No", PADDING_CHOICE, PADDING_CHOICE])
            if q.category == "identification":
                assert all(c.lower() in COLORS for c in q.choices) and q.query["attribute"] == "color"
                ob = sc.instances[q.evidence_ids[0]]
                assert answer.lower() == ob.attributes["color"]
            if q.category == "counting":
                assert all(c in NUMBER_WORDS for c in q.choices)
                assert NUMBER_WORDS.index(answer) == len(q.evidence_ids)
                assert all(sc.instances[i].category == q.query["category"] for i in q.evidence_ids)
            if q.category == "state":
                ob = sc.instances[q.evidence_ids[0]]
                assert (answer == "Yes") == (ob.attributes["state"] == q.query["value"])
            if q.category == "location":
                assert all(any(display_name(k) in c for k in ROOM_KINDS) for c in q.choices)
                ob = sc.instances[q.evidence_ids[0]]
                assert answer == f"In the {display_name(ob.room_kind)}"
            if q.category == "existence":
                present = any(o.category == q.query["category"] and o.room_kind == q.query["room_kind"]
                              for o in sc.objects())
                assert (answer == "Yes") == present
    assert set(seen) == set(CATEGORIES)


def test_plural_only_categories_agree_in_number() -> None:
    """Benchmark question gen-00148-loc0 asks about shoes: "Where are the white shoes?", never "is the shoes"."""
    q = benchmark_candidates(0, 148)["location"][0]
    assert q.id == "gen-00148-loc0" and q.query["category"] == "shoes"
    assert q.text in ("Where are the white shoes?", "In which room did I leave the white shoes?"), q.text
    checked = 0
    for seed in range(40):
        for q in generate_questions(generate_house(seed), np.random.default_rng(seed)):
            if q.query.get("category") in PLURAL_ONLY:
                assert "is the shoes" not in q.text.lower() and "a shoes" not in q.text, q.text
                checked += 1
    assert checked >= 3


def test_every_evidence_object_is_visible_from_a_reachable_pose(qsets) -> None:
    K = intrinsics(320, 240)
    for sc, qs in qsets:
        rend = Renderer(sc)
        reach, ox, oy = reachable_map(sc, qs[0].start_pose)
        ids = sorted({i for q in qs for i in q.evidence_ids})
        poses = witness_poses(sc, qs[0].start_pose, ids)
        assert set(poses) == set(ids)
        for i in ids:
            p = poses[i]
            assert pose_error(sc, p) is None
            assert reach[int((p.y - oy) / 0.05), int((p.x - ox) / 0.05)]
            out = rend.render(camera_pose(p), K, 320, 240)
            assert (out.instances == i).any(), (sc.id, sc.instances[i].category)


def test_same_seed_same_questions() -> None:
    sc = generate_house(11)
    a = generate_questions(sc, np.random.default_rng(5))
    b = generate_questions(generate_house(11), np.random.default_rng(5))
    assert [q.model_dump_json() for q in a] == [q.model_dump_json() for q in b]


def test_small_benchmark_is_deterministic_with_proportions(tmp_path) -> None:
    a = benchmark(3, tmp_path / "scenes", size=50, calibration=30)
    b = benchmark(3, None, size=50, calibration=30)
    assert [q.model_dump_json() for q in a.questions] == [q.model_dump_json() for q in b.questions]
    assert len(a.calibration) == 30 and len(a.test) == 20
    counts = Counter(q.category for q in a.questions)
    assert counts == {"identification": 8, "counting": 8, "existence": 11, "state": 10, "location": 13}
    assert len({q.id for q in a.questions}) == 50
    assert len(a.scenes) >= 50 // 3
    assert (tmp_path / "scenes" / a.scenes[0] / "scene.json").exists()
    a.save(tmp_path / "b.json")
    assert (tmp_path / "b.json").read_text() == b.save(tmp_path / "c.json").read_text()


def test_hmeqa_loader_reads_the_real_files() -> None:
    qs = load_hmeqa(HMEQA)
    assert len(qs) == 500
    assert all(q.start_pose is not None and q.answer in q.labels for q in qs)
    assert all(len(q.choices) == 4 for q in qs)
    msg = missing_scans(qs, None)
    assert msg is not None and "EQA_HM3D_DIR" in msg and "00004-VqCaAuuoeWk" in msg and "266" in msg


def test_hmeqa_scan_found_when_present(tmp_path) -> None:
    qs = [q for q in load_hmeqa(HMEQA) if q.scene == "00004-VqCaAuuoeWk"]
    folder = tmp_path / "00004-VqCaAuuoeWk"
    folder.mkdir()
    box = o3d.geometry.TriangleMesh.create_box(5.0, 5.0, 2.5)
    box.compute_vertex_normals()
    o3d.io.write_triangle_mesh(str(folder / "VqCaAuuoeWk.ply"), box)
    assert scan_path(tmp_path, "00004-VqCaAuuoeWk") == folder / "VqCaAuuoeWk.ply"
    msg = missing_scans(qs, tmp_path)
    assert msg is None
    sc = load_scene(Settings(hm3d_dir=tmp_path, data_dir=tmp_path / "var"), "00004-VqCaAuuoeWk")
    assert sc.instances == {} and sc.floor_area_m2 > 15
