"""The task episode's object layer read per phase (services/mapper/object_map.py, object_shell.py, gaze.py,
objects/layer.py): frontier values and gaze points for the current phase's class, Eq. 10's IG over the pose set
P, misses beyond the detector's range, gaze points clear of obstacles, the trusting agent's single-frame layer."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from support.objects import frame_of, ring_views

from eqa.messages import DetectResult, GridSpec, Task
from services.mapper import gaze as gz
from services.mapper import object_map as omod
from services.mapper import object_shell
from services.mapper.object_map import ObjectMap, ObjectMapConfig
from services.mapper.objects.config import ObjectLayerConfig
from services.mapper.objects.layer import camera_from_gaze
from services.sim.housegen import generate_house
from services.sim.render import Renderer
from services.vlm_scorer.detector.oracle import OracleDetector, OracleDetectorParams

TASK = Task(kind="pick_place", text="Move the chair from the table to the sofa", scene="gen-5", object="chair",
            start_receptacle="table", goal_receptacle="sofa")
CONFIG = ObjectMapConfig(layer=ObjectLayerConfig(render_scale=1.0))


@pytest.fixture(scope="module")
def fused():
    scene = generate_house(5)
    renderer = Renderer(scene)
    vs = ring_views(scene, renderer, 25, 160, 120)  # the kitchen chair
    det = OracleDetector(OracleDetectorParams(recall=1.0, background_fp=0.0, confusion=0.0))
    om = ObjectMap.for_task(TASK, CONFIG)
    for step, v in enumerate(vs[:2]):
        f = frame_of(v, renderer, "ep-phase", step)
        req = om.detect_request(f, seed=3)
        om.integrate(f, DetectResult(request_id=req.request_id, episode_id="ep-phase", step=step,
                                     detections=det.detect(req), backend="oracle"))
    free, ox, oy = scene.navigable_grid(0.1)
    grid = GridSpec(origin_x=ox, origin_y=oy, resolution=0.1, rows=free.shape[0], cols=free.shape[1])
    return scene, renderer, vs, det, om, grid, ~free


def test_frontiers_take_the_goal_receptacles_values_once_the_object_is_held() -> None:
    assert object_shell.frontier_class(TASK, holding=False) == "table"
    assert object_shell.frontier_class(TASK, holding=True) == "sofa"
    find = Task(kind="find_object", text="Find a mug", scene="gen-1", object="mug")
    assert object_shell.frontier_class(find, holding=False) == "mug"
    assert omod.phase_classes(TASK, False) == ["chair", "table"] and omod.phase_classes(TASK, True) == ["sofa"]


def test_gaze_points_go_to_the_phases_class_only(fused) -> None:
    _scene, _r, _vs, _det, om, grid, occ = fused
    before = om.summaries(grid, occ, targets=omod.phase_classes(TASK, False))
    chair = next(o for o in before if o.cls == "chair")
    assert chair.gaze
    after = om.summaries(grid, occ, targets=omod.phase_classes(TASK, True))  # holding: only sofas are looked at
    assert all(not o.gaze and o.ig == 0.0 for o in after if o.cls != "sofa")


def test_ig_is_that_of_the_whole_pose_set(fused, monkeypatch: pytest.MonkeyPatch) -> None:
    from eqa import robot as body

    _scene, _r, _vs, _det, om, grid, occ = fused
    # Eq. 12 over a pose set needs several gaze points: the chair stands next to furniture, and with the map
    # margin all but one of its gaze points are closer than the mapped clearance to an occupied cell
    monkeypatch.setattr(body, "MAP_MARGIN_M", 0.0)
    chair = next(o for o in om.summaries(grid, occ) if o.cls == "chair")
    assert len(chair.gaze) >= 2
    poses = [camera_from_gaze(g.x, g.y, g.yaw, g.pitch, 1.5) for g in chair.gaze]
    ci = om.layer.class_index("chair")
    assert chair.ig == pytest.approx(float(om.layer.optimistic(chair.instance_id, ci, poses).ig), rel=1e-5)
    assert chair.ig > max(g.ig for g in chair.gaze)  # P sees more of it than its best single gaze point


def test_a_miss_beyond_the_detectors_range_is_no_evidence(fused) -> None:
    _scene, renderer, vs, _det, om, _grid, _occ = fused
    f = frame_of(vs[0], renderer, "ep-phase", 5)
    nothing = DetectResult(request_id="r", episode_id="ep-phase", step=5, detections=[], backend="oracle")
    # the same layer, one with a miss range shorter than the view's depth: the empty frame changes nothing
    near = ObjectMap.restore(om.snapshot(), CONFIG)
    near.layer.config = ObjectLayerConfig(render_scale=1.0, other_max_depth_m=0.5)
    plain = ObjectMap.restore(om.snapshot(), CONFIG)
    plain.layer.config = ObjectLayerConfig(render_scale=1.0)
    g0 = near.layer.store.gamma.clone()
    near.integrate(f, nothing)
    plain.integrate(f, nothing)
    assert torch.allclose(near.layer.store.gamma, g0)
    other = plain.layer.other
    assert float(plain.layer.store.gamma[:, other].sum()) > float(g0[:, other].sum()) + 1.0
    # a task layer keeps its miss range through a restart
    assert om.layer.config.other_max_depth_m == CONFIG.miss_range_m == 4.5
    assert ObjectMap.restore(om.snapshot(), CONFIG).layer.config.other_max_depth_m == 4.5


def test_the_trusting_agents_layer_holds_one_frame(fused) -> None:
    _scene, renderer, vs, det, _om, grid, occ = fused
    om = ObjectMap.for_task(TASK, CONFIG, single_frame=True)
    f = frame_of(vs[0], renderer, "ep-trust", 0)
    req = om.detect_request(f, seed=3)
    om.integrate(f, DetectResult(request_id="a", episode_id="ep-trust", step=0, detections=det.detect(req),
                                 backend="oracle"))
    first = om.summaries(grid, occ)
    assert any(o.cls == "chair" for o in first) and all(not o.gaze for o in first)  # no gaze points either
    om.integrate(frame_of(vs[1], renderer, "ep-trust", 1),
                 DetectResult(request_id="b", episode_id="ep-trust", step=1, detections=[], backend="oracle"))
    assert om.summaries(grid, occ) == []  # nothing detected in this frame: nothing known
    back = ObjectMap.restore(om.snapshot(), CONFIG)
    assert back.single_frame


def test_gaze_points_keep_the_robots_clearance_from_obstacles() -> None:
    g = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.05, rows=80, cols=80)
    occ = np.zeros((80, 80), bool)
    # the object at (2, 2), a point footprint; contour radius 0.9 m, 4 points: (2.9, 2), (2, 2.9), (1.1, 2), (2, 1.1)
    occ[40, 60] = True  # (row, col): a post at x 3.00 .. 3.05, y 2.00 .. 2.05, 0.1 .. 0.15 m from (2.9, 2)
    pts = gz.gaze_points(occ, None, g, (2.0, 2.0, 0.5), (0.0, 0.0, 0.5), 0.9, 4, 1.0)
    assert len(pts) == 4
    kept = gz.gaze_points(occ, None, g, (2.0, 2.0, 0.5), (0.0, 0.0, 0.5), 0.9, 4, 1.0, clearance_m=0.2)
    assert sorted((round(p.x, 2), round(p.y, 2)) for p in kept) == [(1.1, 2.0), (2.0, 1.1), (2.0, 2.9)]
    assert len(gz.gaze_points(occ, None, g, (2.0, 2.0, 0.5), (0.0, 0.0, 0.5), 0.9, 4, 1.0, clearance_m=0.05)) == 4


def test_values_are_fused_by_field_of_view_confidence() -> None:
    from eqa.messages import Pose2D
    from services.mapper import fov_values
    from services.sim.camera import camera_pose, intrinsics

    K = intrinsics(64, 48)
    cam = camera_pose(Pose2D(x=0.0, y=0.0, yaw=0.0), height=1.0, tilt_deg=0.0)  # looking along +x, level
    depth = np.full((48, 64), 2.0)  # a wall 2 m ahead
    rows, cols, conf = fov_values.fov_cells(depth, K, cam, (-5.0, -5.0), 0.1, (100, 100))
    at = {(int(r), int(c)): float(w) for r, c, w in zip(rows, cols, conf, strict=True)}
    ahead = (50, 60)  # (x, y) = (1.05, 0.05): on the optical axis
    assert at[ahead] == pytest.approx(1.0, abs=0.01)
    assert (50, 75) not in at  # (2.55, 0.05): behind the wall, not seen
    assert (50, 40) not in at  # behind the camera
    # a cell seen at half the half field of view (cos^2(pi / 4) = 0.5)
    half = np.arctan(32 / K[0][0])
    x, y = 1.5, -1.5 * np.tan(half / 2)  # right of the axis (image x grows to the right = -y)
    cell = (int(np.floor((y + 5.0) / 0.1)), int(np.floor((x + 5.0) / 0.1)))
    assert at[cell] == pytest.approx(0.5, abs=0.08)
    values, confidence = np.zeros((100, 100), np.float32), np.zeros((100, 100), np.float32)
    r, c = np.array([50, 51]), np.array([60, 60])
    fov_values.fuse(values, confidence, r, c, np.array([0.5, 0.0]), 0.2)  # the second cell not seen
    fov_values.fuse(values, confidence, r, c, np.array([1.0, 0.0]), 0.8)
    # v = (0.5 * 0.2 + 1 * 0.8) / 1.5 = 0.6, c = (0.25 + 1) / 1.5 = 0.8333; not max-fused (0.8)
    assert values[50, 60] == pytest.approx(0.6) and confidence[50, 60] == pytest.approx(1.25 / 1.5)
    assert values[51, 60] == 0.0 and confidence[51, 60] == 0.0


def test_the_mapper_values_frontiers_with_the_goal_layer_after_a_successful_pick(fused) -> None:
    from eqa.messages import EpisodeStart, Question, SkillReport, ValueRequest, ValueResult
    from eqa.settings import Settings
    from services.mapper.episode_map import EpisodeMap
    from services.mapper.extension import MapperContext, StepOutputs
    from services.mapper.object_shell import ObjectLayerExtension

    _scene, renderer, vs, det, _om, _grid, _occ = fused

    def detect(req):  # the simulated detector, as the scorer pool answers
        return DetectResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                            detections=det.detect(req), backend="oracle")

    def values(req: ValueRequest) -> ValueResult:  # a constant score per target (0.2, 0.5, 0.9)
        return ValueResult(request_id=req.request_id, episode_id=req.episode_id, step=req.step,
                           values=[0.2, 0.5, 0.9][: len(req.targets)], backend="constant")

    errors: list = []
    ext = ObjectLayerExtension(MapperContext(Settings(), None, lambda *a: errors.append(a), detector=detect,
                                             values=values))
    try:
        start = EpisodeStart(episode_id="ep-shell", robot="r", question=Question(
            id="q", scene="gen-5", text=TASK.text, max_steps=10), max_steps=10, task=TASK)
        em = EpisodeMap(start, layers=["question"])
        ext.begin(em, None, restored=False)
        frames = [frame_of(vs[0], renderer, "ep-shell", 0),
                  frame_of(vs[1], renderer, "ep-shell", 1).model_copy(
                      update={"skill": SkillReport(skill="pick", success=True, target=25)})]
        got = []
        for f in frames:
            em.integrate(f)
            out = StepOutputs()
            ext.apply("r", em, f, ext.submit("r", em, f), out, {})
            got.append(out.frontier_layer)
        assert got == ["helios:table", "helios:sofa"] and not errors
        sofa = em.layer("helios:sofa")
        assert sofa.max() == pytest.approx(0.9, abs=1e-6) and 0 < (sofa > 0).mean() < 1  # the cone, not everywhere
    finally:
        ext.close()
