"""Scorer replicas over real Zenoh: failover when a replica process dies, error replies for bad input."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from support.scorer import frame_request, scorer_pool, start_replica

from eqa import keys
from eqa.bus import Bus
from eqa.codec import packb
from eqa.messages import ErrorReply, ScoreRequest, ScoreResult, decode
from eqa.scorer_client import ScorerClient, ScorerError, ScorerUnavailable
from services.vlm_scorer.service import ScorerService


def _raw_request(req: ScoreRequest, **changes: object) -> bytes:
    body = req.model_dump(mode="python")
    body["kind"] = req.kind
    for path, value in changes.items():
        target = body
        *parents, leaf = path.split("__")
        for p in parents:
            target = target[p]
        target[leaf] = value
    return packb(body)


def _ask_raw(bus: Bus, key: str, payload: bytes) -> list[object]:
    out = []
    for reply in bus.session.get(key, payload=payload, timeout=10):
        assert reply.ok is not None
        out.append(decode(reply.ok.payload.to_bytes()))
    return out


def test_kill_one_of_two_replicas_with_50_in_flight(hub_settings, settings):
    settings = settings.model_copy(update={"scorer_timeout_s": 15.0})
    with Bus(hub_settings, "gateway", "client") as bus:
        client = ScorerClient(bus, settings)
        procs = [start_replica(settings, f"rep{i}") for i in range(2)]
        try:
            assert client.wait_for_replicas(2, timeout=30), "replicas did not come up"
            requests = [frame_request(step=i, h=240, w=320) for i in range(50)]
            answered: list[str] = []

            def one(req: ScoreRequest) -> ScoreResult:
                res = client.score(req)
                answered.append(res.replica)
                return res

            with ThreadPoolExecutor(50) as pool:
                futures = [pool.submit(one, r) for r in requests]
                deadline = time.monotonic() + 20
                while len(answered) < 2 and time.monotonic() < deadline:
                    time.sleep(0.001)
                procs[0].kill()
                results = [f.result(timeout=60) for f in futures]
            assert len(results) == 50
            assert sorted(r.request_id for r in results) == sorted(r.request_id for r in requests)
            for res, req in zip(results, requests, strict=True):
                assert res.request_id == req.request_id and res.step == req.step
                assert abs(sum(res.answer_probs) - 1) < 1e-6
            assert client.stats["answers"] == 50
            assert set(answered) <= {"rep0", "rep1"}
            # the survivor now takes everything
            assert client.score(frame_request(step=99)).replica == "rep1"
        finally:
            for p in procs:
                p.kill()
                p.wait(timeout=10)


def test_bad_input_gets_error_replies_and_replica_keeps_serving(hub_settings, settings):
    settings = settings.model_copy(update={"scorer_replica": "solo"})
    with scorer_pool(hub_settings, settings) as (client, _):
        good = frame_request()
        bad_shape = frame_request()
        bad_shape.rgb = np.zeros((20, 30), np.uint8)
        bad_dtype = frame_request()
        bad_dtype.rgb = np.zeros((20, 30, 3), np.float32)
        for req, words in ((bad_shape, "HxWx3"), (bad_dtype, "uint8")):
            with pytest.raises(ScorerError, match=words) as info:
                client.score(req)
            assert info.value.reply.request_id == req.request_id
        key = keys.scorer_replica("solo")
        empty = _ask_raw(client.bus, key, _raw_request(good, question__text="   "))
        many = _ask_raw(client.bus, key, _raw_request(good, question__choices=[f"c{i}" for i in range(27)]))
        garbage = _ask_raw(client.bus, key, b"\x00not msgpack")
        assert isinstance(empty[0], ErrorReply) and "question text is empty" in empty[0].reason
        assert isinstance(many[0], ErrorReply) and "between 2 and 26 choices" in many[0].reason
        assert isinstance(garbage[0], ErrorReply) and "msgpack" in garbage[0].reason
        res = client.score(good)  # still serving
        assert res.replica == "solo" and res.backend == "oracle" and res.model == "simulated-perception"
        assert len(res.lsv) == 2 and abs(sum(res.lsv) - 1) < 1e-6


def test_missing_or_non_vlm_model_directory_is_an_error_reply(hub_settings, settings, tmp_path):
    not_vlm = tmp_path / "bert"
    not_vlm.mkdir()
    (not_vlm / "config.json").write_text('{"model_type": "bert", "hidden_size": 8}')
    with Bus(hub_settings, "gateway", "client") as bus:
        for i, path in enumerate((tmp_path / "nowhere", not_vlm)):
            s = settings.model_copy(
                update={"scorer_backend": "hf", "hf_model_path": path, "scorer_replica": f"hf{i}"}
            )
            svc = ScorerService(s)
            svc.start()
            try:
                client = ScorerClient(bus, s, timeout_s=10)
                assert client.wait_for_replicas(1, timeout=10)
                for _ in range(2):  # keeps answering
                    with pytest.raises(ScorerError) as info:
                        client.score(frame_request())
                    reason = info.value.reply.reason
                    assert (
                        ("does not exist" in reason)
                        if i == 0
                        else ("not a supported vision-language" in reason)
                    )
                    assert "EQA_HF_MODEL_PATH" in reason or "bert" in reason
            finally:
                svc.stop()
                time.sleep(0.2)


def test_no_replica_raises_unavailable(hub_settings, settings):
    with Bus(hub_settings, "gateway", "client") as bus:
        client = ScorerClient(bus, settings, timeout_s=0.5, retries=1)
        with pytest.raises(ScorerUnavailable, match="no live scorer replica"):
            client.score(frame_request())


def test_least_busy_replica_spreads_concurrent_requests(hub_settings, settings):
    replicas = [settings.model_copy(update={"scorer_replica": f"s{i}"}) for i in range(2)]
    with scorer_pool(hub_settings, *replicas) as (client, services):
        with ThreadPoolExecutor(8) as pool:
            results = list(pool.map(client.score, [frame_request(step=i, h=120, w=160) for i in range(24)]))
        counts = {r: sum(res.replica == r for res in results) for r in ("s0", "s1")}
        assert min(counts.values()) >= 4, counts
        assert sum(s.served for s in services) == 24


def test_annotated_image_goes_to_the_episode_recording(settings):
    s = settings.model_copy(update={"record": True, "scorer_replica": "rec"})
    svc = ScorerService(s)
    from services.vlm_scorer.backends.oracle import OracleBackend

    svc.backend = OracleBackend()
    res = svc.handle(frame_request(episode="ep-rec"))
    assert isinstance(res, ScoreResult)
    for rec in svc._recorders.values():
        rec.close()
    path = s.recordings_path / "ep-rec" / "vlm_scorer.rrd"
    assert path.is_file() and path.stat().st_size > 1000
