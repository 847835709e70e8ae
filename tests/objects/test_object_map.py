"""The mapper's object map (services/mapper/object_map.py): task vocabulary and thresholds, fusion of
DetectResults from rendered frames, ObjectInstance summaries with gaze points scored by Psi' and IG, and the
snapshot a restarted mapper restores."""

from __future__ import annotations

import numpy as np
import pytest
from support.objects import frame_of, ring_views

from eqa.messages import DetectResult, GridSpec, MapUpdate, Pose2D, Task, decode, encode
from services.mapper.object_map import ObjectMap, ObjectMapConfig, task_classes
from services.mapper.objects.config import ObjectLayerConfig
from services.sim.housegen import generate_house
from services.sim.render import Renderer
from services.vlm_scorer.detector.oracle import OracleDetector, OracleDetectorParams

TASK = Task(kind="pick_place", text="Move the chair from the table to the sofa", scene="gen-5", object="chair",
            start_receptacle="table", goal_receptacle="sofa")


@pytest.fixture(scope="module")
def views():
    scene = generate_house(5)
    renderer = Renderer(scene)
    return scene, renderer, ring_views(scene, renderer, 25, 160, 120)  # the kitchen chair


def test_task_classes_and_thresholds() -> None:
    assert task_classes(TASK, ObjectMapConfig()) == (["chair", "table", "sofa"], [0.25, 0.35, 0.45])
    find = Task(kind="find_object", text="Find a mug", scene="gen-1", object="mug")
    assert task_classes(find, ObjectMapConfig()) == (["mug"], [0.25])


def test_fusion_summaries_gaze_and_restore(views) -> None:
    scene, renderer, vs = views
    objects = ObjectMap.for_task(TASK, ObjectMapConfig(layer=ObjectLayerConfig(render_scale=1.0)))
    det = OracleDetector(OracleDetectorParams(recall=1.0, background_fp=0.0, confusion=0.0))
    for step, v in enumerate(vs[:2]):
        f = frame_of(v, renderer, "ep-om", step)
        req = objects.detect_request(f, seed=3)
        assert req.classes == ["chair", "table", "sofa"] and req.thresholds == [0.25, 0.35, 0.45]
        res = DetectResult(request_id=req.request_id, episode_id="ep-om", step=step, detections=det.detect(req),
                           backend="oracle")
        stats = objects.integrate(f, res)
        assert stats.gaussians > 0
    free, ox, oy = scene.navigable_grid(0.1)
    grid = GridSpec(origin_x=ox, origin_y=oy, resolution=0.1, rows=free.shape[0], cols=free.shape[1])
    objs = objects.summaries(grid, ~free)
    chair = next(o for o in objs if o.cls == "chair")
    pos = scene.instances[25].position
    assert abs(chair.centre[0] - pos[0]) < 0.4 and abs(chair.centre[1] - pos[1]) < 0.4
    assert set(chair.scores) == {"chair", "table", "sofa"} and chair.scores["chair"][2] == pytest.approx(chair.psi)
    assert chair.gaze and all(g.psi_prime >= chair.psi - 1e-6 for g in chair.gaze)
    assert chair.ig == pytest.approx(max(g.ig for g in chair.gaze)) and chair.ig > 0
    assert objects.history[chair.instance_id][-1][0] == 1
    # on the bus
    up = MapUpdate(episode_id="ep-om", step=1, grid=grid, occupied=~free, free=free, explored=free,
                   pose=Pose2D(x=0, y=0), objects=objs)
    assert decode(encode(up)).objects == objs
    # restore: the same layer, the same next update
    back = ObjectMap.restore(objects.snapshot(), objects.config)
    assert back.thresholds == objects.thresholds and back.history == objects.history
    assert [o.model_dump() for o in back.summaries()] == [o.model_dump() for o in objects.summaries()]
    f = frame_of(vs[2], renderer, "ep-om", 2)
    req = objects.detect_request(f, seed=3)
    res = DetectResult(request_id="r", episode_id="ep-om", step=2, detections=det.detect(req), backend="oracle")
    a, b = objects.integrate(f, res), back.integrate(f, res)
    assert a.gaussians == b.gaussians
    assert np.allclose(objects.layer.store.gamma.numpy(), back.layer.store.gamma.numpy())


def test_rerun_shows_gaussians_instances_and_psi(views, tmp_path) -> None:
    from eqa.recording import EpisodeRecorder
    from eqa.settings import Settings
    from gateway import recordings
    from services.mapper.object_map import GAUSSIANS_ENTITY, INSTANCES_ENTITY, PSI_ENTITY, log_rerun

    _scene, renderer, vs = views
    objects = ObjectMap.for_task(TASK, ObjectMapConfig(layer=ObjectLayerConfig(render_scale=1.0)))
    det = OracleDetector(OracleDetectorParams(recall=1.0, background_fp=0.0))
    rec = EpisodeRecorder(Settings(data_dir=tmp_path), "ep-om", "mapper")
    for step, v in enumerate(vs[:2]):
        f = frame_of(v, renderer, "ep-om", step)
        req = objects.detect_request(f)
        objects.integrate(f, DetectResult(request_id="r", episode_id="ep-om", step=step, detections=det.detect(req),
                                     backend="oracle"))
        rec.set_step(step)
        objs = objects.summaries()
        log_rerun(rec, objects, objs)
    rec.close()
    paths = recordings.entity_paths(rec.path)
    assert {"/" + GAUSSIANS_ENTITY, "/" + INSTANCES_ENTITY} <= paths
    assert any(p.startswith("/" + PSI_ENTITY + "/") for p in paths)


def test_obstacle_heights_follow_the_occupancy_map(views) -> None:
    from eqa.messages import EpisodeStart, Question
    from services.mapper.episode_map import EpisodeMap
    from services.mapper.object_shell import obstacle_heights

    _scene, renderer, vs = views
    episode_map = EpisodeMap(EpisodeStart(episode_id="ep-h", robot="r0", question=Question(text="q?", scene="gen-5"),
                                 max_steps=3))
    assert obstacle_heights(episode_map) is None  # nothing integrated yet
    episode_map.integrate(frame_of(vs[0], renderer, "ep-om", 0))
    h = obstacle_heights(episode_map)
    assert h is not None and h.shape == episode_map.maps.occupied.shape
    assert bool((h[episode_map.maps.occupied] > 0).all()) and bool((h[~episode_map.maps.occupied] == 0).all())
    assert float(h.max()) <= 1.5 + 0.1 and float(h[episode_map.maps.occupied].min()) >= 0.1
