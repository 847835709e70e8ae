"""HELIOS closed loop in a generated house (open3d renders, the simulated detector, the object layer):
a false positive's Psi falls below tau_g after two more views, chosen by Psi' (Eq. 11), while a true
object's rises above it."""

from __future__ import annotations

import pytest
from support.objects import best_gaze, detect, fuse, instances_near, ring_views

from services.mapper.objects.config import ObjectLayerConfig
from services.mapper.objects.layer import ObjectLayer
from services.sim.housegen import generate_house
from services.sim.render import Renderer
from services.vlm_scorer.detector.oracle import OracleDetector, OracleDetectorParams

TAU_G = 0.5  # Table 3
W, H = 160, 120
HOUSE = 5
CHAIR, ARMCHAIR = 25, 44  # a kitchen chair (true "chair") and a living-room armchair (the false positive)
CLASSES, THRESHOLDS = ["chair", "table"], [0.25, 0.35]  # od_g for the object, od_a for the receptacle


@pytest.fixture(scope="module")
def house():
    scene = generate_house(HOUSE)
    assert scene.instances[CHAIR].category == "chair" and scene.instances[ARMCHAIR].category == "armchair"
    return scene, Renderer(scene)


def psi_chair(layer: ObjectLayer, xyz) -> list[float]:
    return [i.psi[0] for i in instances_near(layer, xyz)]


def test_false_positive_falls_and_true_object_rises(house) -> None:
    scene, renderer = house
    # a detector fooled by similar categories (the armchair is "a chair"), and one that is not
    fooled = OracleDetector(OracleDetectorParams(recall=1.0, similar_fp=1.0, confusion=0.0, background_fp=0.0))
    honest = OracleDetector(OracleDetectorParams(recall=1.0, similar_fp=0.0, confusion=0.0, background_fp=0.0))
    layer = ObjectLayer(CLASSES, ObjectLayerConfig(render_scale=1.0))
    fp_views = ring_views(scene, renderer, ARMCHAIR, W, H)
    true_views = ring_views(scene, renderer, CHAIR, W, H)
    assert len(fp_views) >= 5 and len(true_views) >= 3
    fp_xyz, true_xyz = scene.instances[ARMCHAIR].position, scene.instances[CHAIR].position
    step = 0
    for v in fp_views[:3]:  # fooled three times: the layer believes the armchair is a chair
        fuse(layer, v, detect(fooled, renderer, v, CLASSES, THRESHOLDS, step), step)
        step += 1
    fp = instances_near(layer, fp_xyz)
    assert fp and max(psi_chair(layer, fp_xyz)) >= TAU_G
    fuse(layer, true_views[0], detect(honest, renderer, true_views[0], CLASSES, THRESHOLDS, step), step)
    step += 1
    first = psi_chair(layer, true_xyz)
    assert first and max(first) < TAU_G  # one view is not enough to be confident
    # local search: two more views of each candidate, the best by Psi' (Eq. 11) as the believed class
    for xyz, views in ((fp_xyz, fp_views[3:]), (true_xyz, true_views[1:])):
        candidate = max(instances_near(layer, xyz), key=lambda i: i.psi[0])
        ranked = best_gaze(layer, candidate.instance_id, 0, views)
        assert ranked[0][0] >= candidate.psi[0]  # optimistic: seeing it as a chair again would raise Psi
        for _, v in ranked[:2]:
            fuse(layer, v, detect(honest, renderer, v, CLASSES, THRESHOLDS, step), step)
            step += 1
    assert max(psi_chair(layer, fp_xyz)) < TAU_G  # the false positive is no longer pickable
    assert max(psi_chair(layer, true_xyz)) >= TAU_G  # the true chair is
