"""Detection and per-target value requests through the scorer pool over real Zenoh (ScorerClient ->
ScorerService queryable): typed replies, error replies for bad input and a refused backend."""

from __future__ import annotations

import numpy as np
import pytest
from support.scorer import scorer_pool
from test_detector import frame

from eqa.messages import DetectRequest, ValueRequest
from eqa.scorer_client import ScorerError


def test_detect_and_values_through_the_pool(hub_settings, settings):
    settings = settings.model_copy(update={"scorer_replica": "det"})
    rgb, inst, labels, depth = frame()
    with scorer_pool(hub_settings, settings) as (client, [svc]):
        req = DetectRequest(episode_id="ep-1", step=3, rgb=rgb, classes=["mug"], thresholds=[0.25],
                            instances=inst, labels=labels, depth=depth, seed=7)
        res = client.detect(req)
        assert res.backend == "oracle" and res.model == "simulated-detector" and res.replica == "det"
        assert res.request_id == req.request_id
        direct = svc.handle_detect(req)
        assert [(d.cls, d.score, d.box) for d in res.detections] == [
            (d.cls, d.score, d.box) for d in direct.detections  # type: ignore[union-attr]
        ]
        assert all(d.mask.dtype == bool for d in res.detections)
        val = client.values(ValueRequest(episode_id="ep-1", step=3, rgb=rgb, targets=["mug", "bed"],
                                         instances=inst, labels=labels, depth=depth))
        assert len(val.values) == 2 and val.values[0] > val.values[1]
        no_ids = req.model_copy(update={"instances": None})
        with pytest.raises(ScorerError, match="instance ids"):
            client.detect(no_ids)
        bad = req.model_copy(update={"rgb": np.zeros((4, 4), np.uint8)})
        with pytest.raises(ScorerError, match="HxWx3"):
            client.detect(bad)
        assert client.detect(req).detections is not None  # still serving


def test_remote_detector_backend_is_an_error_reply(hub_settings, settings):
    settings = settings.model_copy(update={"scorer_replica": "rem", "detector_backend": "remote"})
    rgb, inst, labels, _depth = frame()
    with scorer_pool(hub_settings, settings) as (client, _):
        req = DetectRequest(episode_id="e", step=0, rgb=rgb, classes=["mug"], instances=inst, labels=labels)
        for _ in range(2):
            with pytest.raises(ScorerError, match="no well-known HTTP protocol"):
                client.detect(req)
