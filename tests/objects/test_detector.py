"""The detector behind the scorer pool (services/vlm_scorer/detector): the simulated DETIC-class detector,
the transformers OWL-ViT backend on a tiny random model built here, the refused remote backend, and the
per-target value prompt."""

from __future__ import annotations

import json

import numpy as np
import pytest

from eqa.messages import DetectRequest, InstanceLabel, ValueRequest
from eqa.settings import Settings
from services.vlm_scorer.backends.base import BackendUnavailable, BadRequest
from services.vlm_scorer.backends.oracle import OracleBackend
from services.vlm_scorer.detector import REMOTE_REFUSAL, check_detector_settings, make_detector
from services.vlm_scorer.detector.oracle import OracleDetector, OracleDetectorParams, matches, similar
from services.vlm_scorer.target_values import target_values

H, W = 120, 160


def frame(mug_box=(40, 60, 80, 100), vase_box=None, depth_m: float = 2.0):
    inst = np.full((H, W), 1, np.int32)  # a wall everywhere
    inst[90:, :] = 2  # the floor
    labels = [
        InstanceLabel(id=1, category="wall", room_kind="kitchen", pixels=0),
        InstanceLabel(id=2, category="floor", room_kind="kitchen", pixels=0),
    ]
    if mug_box:
        y0, x0, y1, x1 = mug_box
        inst[y0:y1, x0:x1] = 10
        labels.append(InstanceLabel(id=10, category="mug", room_kind="kitchen"))
    if vase_box:
        y0, x0, y1, x1 = vase_box
        inst[y0:y1, x0:x1] = 11
        labels.append(InstanceLabel(id=11, category="vase", room_kind="kitchen"))
    for lab in labels:
        lab.pixels = int((inst == lab.id).sum())
    depth = np.full((H, W), depth_m, np.float32)
    rgb = np.zeros((H, W, 3), np.uint8)
    return rgb, inst, labels, depth


def request(step=0, classes=("mug", "table"), thresholds=(0.25, 0.35), seed=0, **kw) -> DetectRequest:
    rgb, inst, labels, depth = frame(**kw)
    return DetectRequest(
        episode_id="ep-1", step=step, rgb=rgb, classes=list(classes), thresholds=list(thresholds),
        instances=inst, labels=labels, depth=depth, seed=seed,
    )


def test_oracle_detects_the_visible_object_with_its_mask_and_is_seeded() -> None:
    det = OracleDetector(OracleDetectorParams(background_fp=0.0, confusion=0.0, bleed_frac=0.0))
    hits = [d for s in range(20) for d in det.detect(request(step=s)) if d.cls == "mug"]
    assert len(hits) >= 14  # recall 0.9 on a well-seen object
    d = hits[0]
    assert d.box == (60, 40, 100, 80) and d.mask.all()
    assert all(0.25 <= h.score <= 1.0 for h in hits)
    again = det.detect(request(step=0))
    assert [(x.cls, x.score, x.box) for x in again] == [(x.cls, x.score, x.box) for x in det.detect(request(step=0))]


def test_oracle_never_sees_what_is_not_in_the_frame() -> None:
    det = OracleDetector(OracleDetectorParams(background_fp=0.0))
    req = request(mug_box=None)
    req.labels.append(InstanceLabel(id=10, category="mug", pixels=500))  # a label without pixels in the image
    assert all(not d.mask.any() or d.cls != "mug" for d in det.detect(req))
    assert det.detect(req) == []


def test_oracle_misses_small_and_far_objects() -> None:
    det = OracleDetector(OracleDetectorParams(background_fp=0.0))
    tiny = sum(len(det.detect(request(step=s, mug_box=(50, 50, 52, 52)))) for s in range(30))
    far = sum(len(det.detect(request(step=s, depth_m=7.5))) for s in range(30))
    assert tiny == 0 and far == 0


def test_oracle_confuses_similar_categories_and_fires_on_background() -> None:
    det = OracleDetector(OracleDetectorParams(similar_fp=0.5, background_fp=0.0))
    fp = [d for s in range(40) for d in det.detect(request(step=s, mug_box=None, vase_box=(40, 60, 80, 100)))]
    assert fp and all(d.cls == "mug" for d in fp)  # a vase reported as a mug, sometimes
    assert 5 <= len(fp) <= 35
    assert similar("mug", "vase") and not similar("mug", "bed") and matches("table", "coffee_table")
    bg = OracleDetector(OracleDetectorParams(background_fp=1.0, recall=0.0, fp_score_lo=0.4, fp_score_hi=0.45))
    dets = bg.detect(request(classes=("mug",), thresholds=(0.25,)))
    assert len(dets) == 1 and 0.4 <= dets[0].score <= 0.45
    # thresholds are per class: the same background blob under a 0.5 threshold is dropped
    assert bg.detect(request(classes=("mug",), thresholds=(0.5,))) == []


def test_oracle_masks_bleed() -> None:
    det = OracleDetector(OracleDetectorParams(background_fp=0.0, confusion=0.0, bleed_frac=0.05))
    sizes = [int(d.mask.sum()) for s in range(20) for d in det.detect(request(step=s))]
    assert max(sizes) > 40 * 40  # dilated past the object's 40x40 pixels


def test_oracle_needs_instance_ids_and_valid_requests() -> None:
    det = OracleDetector()
    req = request()
    req.instances = None
    with pytest.raises(BadRequest, match="instance ids"):
        det.detect(req)
    with pytest.raises(BadRequest, match="distinct"):
        det.detect(request(classes=("mug", "Mug"), thresholds=(0.3, 0.3)))
    with pytest.raises(ValueError, match="one per class"):
        DetectRequest(episode_id="e", step=0, rgb=np.zeros((8, 8, 3), np.uint8), classes=["a"], thresholds=[0.1, 0.2])


def test_remote_detector_is_refused_with_the_reason(tmp_path) -> None:
    with pytest.raises(BackendUnavailable, match="no well-known HTTP protocol"):
        check_detector_settings(Settings(detector_backend="remote", data_dir=tmp_path))
    assert "EQA_DETECTOR_BACKEND=hf" in REMOTE_REFUSAL
    with pytest.raises(BackendUnavailable, match="EQA_DETECTOR_MODEL_PATH"):
        make_detector(Settings(detector_backend="hf", data_dir=tmp_path))


def test_hf_owlvit_detector_on_a_tiny_random_model(tmp_path) -> None:
    from services.vlm_scorer.detector.tiny import build_tiny_owlvit

    path = build_tiny_owlvit(tmp_path / "owl")
    det = make_detector(Settings(detector_backend="hf", detector_model_path=path, data_dir=tmp_path))
    assert det.name == "hf" and det.model_name.startswith("owlvit:")
    rgb = np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8)
    req = DetectRequest(episode_id="e", step=0, rgb=rgb, classes=["mug", "table"], thresholds=[0.0, 0.0])
    out = det.detect(req)
    assert out and {d.cls for d in out} <= {"mug", "table"}
    assert all(d.mask.all() and d.mask.shape == (d.box[3] - d.box[1], d.box[2] - d.box[0]) for d in out)
    assert [d.score for d in out] == sorted((d.score for d in out), reverse=True)
    strict = det.detect(req.model_copy(update={"thresholds": [1.0, 1.0]}))
    assert all(d.score >= 1.0 for d in strict)
    other = tmp_path / "bert"
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"model_type": "bert"}))
    with pytest.raises(BackendUnavailable, match="not a supported zero-shot detector"):
        make_detector(Settings(detector_backend="hf", detector_model_path=other, data_dir=tmp_path))


def test_value_prompt_oracle() -> None:
    rgb, inst, labels, depth = frame()
    seen = ValueRequest(episode_id="e", step=0, rgb=rgb, targets=["mug", "bed"], instances=inst, labels=labels,
                        depth=depth)
    v = target_values(OracleBackend(), seen)
    assert len(v) == 2 and v[0] > v[1] + 0.2  # a visible mug in a kitchen vs a bed in a kitchen
    rgb, inst, labels, depth = frame(mug_box=None)
    unseen = ValueRequest(episode_id="e", step=0, rgb=rgb, targets=["mug"], instances=inst, labels=labels, depth=depth)
    assert target_values(OracleBackend(), unseen)[0] < v[0]


def test_fleet_preflight_refuses_a_remote_detector(tmp_path) -> None:
    from services.vlm_scorer.backends import check_settings

    check_settings(Settings(data_dir=tmp_path))  # the default simulated detector passes
    with pytest.raises(BackendUnavailable, match="EQA_DETECTOR_BACKEND=hf"):
        check_settings(Settings(detector_backend="remote", data_dir=tmp_path))


def test_ground_truth_semantics_yardstick(tmp_path) -> None:
    det = make_detector(Settings(detector_ground_truth=True, data_dir=tmp_path))
    assert det.model_name == "ground-truth-semantics"
    for step in range(5):  # a tiny, far mug and a vase: the mug always, exactly, the vase never
        dets = det.detect(request(step=step, mug_box=(50, 50, 52, 52), vase_box=(10, 10, 40, 40), depth_m=7.5))
        assert [(d.cls, d.score, d.box, int(d.mask.sum())) for d in dets] == [("mug", 1.0, (50, 50, 52, 52), 4)]
    assert make_detector(Settings(data_dir=tmp_path)).model_name == "simulated-detector"
