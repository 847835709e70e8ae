"""Per-episode Rerun recordings: each service writes its own .rrd with the shared recording id; the gateway
merges them with the pinned rerun CLI and the merged file verifies. Serving it over HTTP after a real episode
is in ``test_recording_fleet.py``."""

from __future__ import annotations

import time

import numpy as np
import rerun as rr

from eqa.recording import ENTITIES, EpisodeRecorder, recording_dir
from eqa.settings import Settings
from gateway import recordings


def test_recorders_merge_into_one_verified_recording(settings: Settings) -> None:
    s = settings.model_copy(update={"record": True})
    sim = EpisodeRecorder(s, "ep-rec1", "sim")
    mapper = EpisodeRecorder(s, "ep-rec1", "mapper")
    off = EpisodeRecorder(s, "ep-rec1", "planner", enabled=False)
    assert sim.path == recording_dir(s, "ep-rec1") / "sim.rrd" and off.path is None
    for t in range(3):
        for r in (sim, mapper, off):
            r.set_step(t)
        sim.log(ENTITIES["rgb"], rr.Image(np.zeros((12, 16, 3), np.uint8)))
        sim.log(ENTITIES["depth"], rr.DepthImage(np.ones((12, 16), np.float32), meter=1.0))
        mapper.log(ENTITIES["frontiers"], rr.Points2D([[1.0, 2.0]], radii=[0.3]))
        off.log(ENTITIES["goal"], rr.Points2D([[0.0, 0.0]]))
    sim.log("bad/entity", object())  # a bad archetype is logged, never raised
    for r in (sim, mapper, off):
        r.close()
    merged = recordings.merge(s, "ep-rec1")
    ok, msg = recordings.verify(merged)
    assert ok, msg
    assert recordings.entity_paths(merged) >= {"/" + ENTITIES[k] for k in ("rgb", "depth", "frontiers")}
    assert "/" + ENTITIES["goal"] not in recordings.entity_paths(merged)
    assert recordings.merge(s, "ep-rec1") == merged  # cached until a part changes
    # Plain concatenation would not be a valid file in rerun 0.41 (why the gateway merges).
    cat = merged.with_name("cat.rrd")
    cat.write_bytes((recording_dir(s, "ep-rec1") / "sim.rrd").read_bytes() * 2)
    assert not recordings.verify(cat)[0]


def test_live_stream_to_a_viewer_and_file_at_once(settings: Settings, tmp_path) -> None:
    """With EQA_RERUN_URL set the recorder streams to the viewer's gRPC proxy and still writes its file."""
    import os
    import subprocess

    from eqa.launcher import free_port

    port = free_port()
    log_path = tmp_path / "viewer.log"
    with open(log_path, "wb") as out:
        viewer = subprocess.Popen(
            [recordings.rerun_cli(), "--test-receive", "--bind", "127.0.0.1", "--port", str(port)],
            stdout=out,
            stderr=out,
            env={**os.environ, "RERUN_TELEMETRY_ENABLED": "false"},
        )
    try:
        deadline = time.monotonic() + 20
        while "Listening for gRPC" not in log_path.read_text(errors="replace"):
            assert time.monotonic() < deadline and viewer.poll() is None, log_path.read_text()
            time.sleep(0.05)
        s = settings.model_copy(update={"record": True, "rerun_url": f"rerun+http://127.0.0.1:{port}/proxy"})
        with EpisodeRecorder(s, "ep-live", "sim") as rec:
            assert rec.live
            rec.set_step(0)
            rec.log(ENTITIES["rgb"], rr.Image(np.zeros((8, 8, 3), np.uint8)))
        deadline = time.monotonic() + 20
        while "Received first message" not in log_path.read_text(errors="replace"):
            assert time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.05)
        assert rec.path is not None and recordings.verify(rec.path)[0]
    finally:
        viewer.kill()
        viewer.wait(timeout=10)


def test_an_unreachable_viewer_leaves_the_file_recording_alone(settings: Settings, caplog) -> None:
    """EQA_RERUN_URL pointing at no viewer: the episode is recorded to its file only, with one warning (a gRPC
    sink to a dead viewer held every flush and disconnect for seconds, 17-22 s per episode)."""
    from eqa.launcher import free_port

    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    s = settings.model_copy(update={"record": True, "rerun_url": url})
    with caplog.at_level("WARNING", logger="eqa.recording"):
        for ep in ("ep-dead-1", "ep-dead-2"):
            with EpisodeRecorder(s, ep, "sim") as rec:
                assert not rec.live
                rec.set_step(0)
                rec.log(ENTITIES["rgb"], rr.Image(np.zeros((8, 8, 3), np.uint8)))
            assert rec.path is not None and recordings.verify(rec.path)[0]
    assert sum("not reachable" in r.getMessage() for r in caplog.records) == 1  # said once, not per episode
