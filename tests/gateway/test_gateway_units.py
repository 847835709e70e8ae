"""Pure parts of the gateway: token bucket, token check, event summaries, request validation."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pydantic import ValidationError

from eqa.messages import Decision, Frontier, GridSpec, MapUpdate, Pose2D
from gateway.auth import RateLimiter, check_token
from gateway.events import MAX_FRONTIERS, summarize
from gateway.schemas import QuestionRequest


def test_rate_limiter_bucket_refills_per_key() -> None:
    rl = RateLimiter(rate=2.0, burst=3)
    assert [rl.allow("a", now=0.0)[0] for _ in range(4)] == [True, True, True, False]
    ok, wait = rl.allow("a", now=0.0)
    assert not ok and wait == pytest.approx(0.5)
    assert rl.allow("b", now=0.0)[0]  # another key has its own bucket
    assert rl.allow("a", now=0.5)[0] and not rl.allow("a", now=0.5)[0]
    assert [rl.allow("a", now=100.0)[0] for _ in range(4)] == [True, True, True, False]  # capped at burst


def test_check_token() -> None:
    assert check_token(["x1", "y2"], "y2") and not check_token(["x1"], "x2") and not check_token(["x1"], None)


def test_map_summary_is_compact_and_lists_best_frontiers() -> None:
    big = np.zeros((400, 400), bool)
    frontiers = [Frontier(x=i, y=0, nx=1, ny=0, size=3, weight=w) for i, w in enumerate(np.linspace(0, 1, 20))]
    msg = MapUpdate(
        episode_id="ep-1",
        step=3,
        grid=GridSpec(origin_x=0, origin_y=0, resolution=0.1, rows=400, cols=400),
        occupied=big,
        free=big,
        explored=big,
        values={"sofa": np.zeros((400, 400), np.float32)},
        frontiers=frontiers,
        pose=Pose2D(x=1, y=2, yaw=float("0.5")),
        explored_area_m2=12.345,
    )
    ev = summarize(msg)
    text = json.dumps(ev)
    assert len(text) < 2000 and ev["kind"] == "map_update" and ev["step"] == 3 and ev["layers"] == ["sofa"]
    assert ev["frontiers"] == 20 and len(ev["top_frontiers"]) == MAX_FRONTIERS
    assert ev["top_frontiers"][0]["weight"] == 1.0 and ev["explored_area_m2"] == 12.35
    d = summarize(
        Decision(
            episode_id="ep-1",
            step=4,
            rule="cp",
            stop=True,
            reason="one answer left",
            prediction_set=["B"],
            scores={"B": 0.91234567},
            answer="B",
        )
    )
    assert d["prediction_set"] == ["B"] and d["scores"] == {"B": 0.9123} and d["answer"] == "B"


def test_request_validation_messages() -> None:
    with pytest.raises(ValidationError, match="between 2 and 26 choices"):
        QuestionRequest(question="q", choices=["a"], scene="s")
    with pytest.raises(ValidationError, match="question text is empty"):
        QuestionRequest(question="   ", scene="s")
    with pytest.raises(ValidationError, match="not one of the choice letters"):
        QuestionRequest(question="q", choices=["a", "b"], scene="s", answer="C")
    with pytest.raises(ValidationError, match=r"give 2\.\.26 choices, or leave choices out"):
        QuestionRequest(question="q", choices=[], robot="r0")
    r = QuestionRequest(question="q", robot="r0")
    assert r.choices is None and r.stop_config().eps == 0.2


def test_rate_limiter_memory_is_bounded_by_many_clients() -> None:
    rl = RateLimiter(rate=1.0, burst=1, max_keys=100)
    for i in range(1000):  # 1000 addresses within a second: none idle
        rl.allow(f"addr-{i}", now=i / 1000)
    assert len(rl._buckets) <= 100
    assert not rl.allow("addr-999", now=0.9995)[0]  # the newest are remembered
