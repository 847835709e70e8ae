"""Mapper service over real Zenoh: map updates, scores, errors, and a restart from the store snapshot."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from support.fleet import wait_for
from support.mapper import ROBOT, Collector, H, frame, start_msg
from support.services import serving

from eqa import keys
from eqa.bus import Bus
from eqa.messages import (
    ScoreRequest,
    ScoreResult,
)
from eqa.settings import Settings
from services.mapper.episode_map import EpisodeMap
from services.mapper.service import MapperService
from services.sim.library import load_or_generate
from services.sim.render import Renderer

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def renderer(tmp_path_factory: pytest.TempPathFactory) -> Renderer:
    return Renderer(load_or_generate("gen-00007", Path(tmp_path_factory.mktemp("scenes"))))


def preferring_left_scorer(calls: list[ScoreRequest]):
    """A deterministic scorer for the test: LSV favours the leftmost prompt point in the image."""

    def score(req: ScoreRequest) -> ScoreResult:
        calls.append(req)
        n = len(req.prompt_points)
        order = np.argsort([p.u for p in req.prompt_points])
        lsv = [0.0] * n
        if n:
            lsv[int(order[0])] = 1.0
        return ScoreResult(
            request_id=req.request_id,
            episode_id=req.episode_id,
            step=req.step,
            answer_probs=[0.7, 0.3],
            relevance=0.4,
            lsv=lsv,
            gsv=0.9,
            backend="test",
        )

    return score


def test_service_publishes_maps_scores_and_rejects_bad_frames(
    hub_settings: Settings, settings: Settings, renderer: Renderer
) -> None:
    calls: list[ScoreRequest] = []
    with Bus(hub_settings, "gateway") as bus:
        got = Collector(bus)
        svc = MapperService(settings, scorer=preferring_left_scorer(calls))
        svc.start()
        try:
            time.sleep(0.5)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_msg("ep-svc"))
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-svc", 0))
            m0 = got.maps.get(timeout=15)
            s0 = got.scores.get(timeout=5)
            assert (
                m0.step == 0
                and s0.step == 0
                and s0.answer_probs == [0.7, 0.3]
                and s0.choices == ["yes", "no"]
            )
            assert m0.free.shape == (m0.grid.rows, m0.grid.cols) and m0.free.dtype == bool
            assert m0.explored_area_m2 > 1.0 and m0.prompt_points and m0.frontiers
            assert m0.values["question"].max() == pytest.approx(math.exp(1.0 + 0.9), rel=1e-5)
            assert calls[0].prompt_points == m0.prompt_points and calls[0].instances is not None
            # the scorer is never sent the ground truth
            assert calls[0].question.answer is None and calls[0].question.evidence_ids == []

            # a non-rigid pose and a depth image of the wrong size: errors, map unchanged
            bad = frame(renderer, "ep-svc", 1)
            bad.camera_pose = bad.camera_pose * 2.0
            bad.camera_pose[3, 3] = 1.0
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), bad)
            err = got.errors.get(timeout=10)
            assert err.step == 1 and "not rigid" in err.reason and err.source == "mapper"
            bad = frame(renderer, "ep-svc", 1)
            bad.depth = np.ascontiguousarray(bad.depth[: H // 2])
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), bad)
            err = got.errors.get(timeout=10)
            assert "depth image is" in err.reason
            assert got.maps.empty()

            # the good frame 1 then integrates on top of frame 0 only
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-svc", 1))
            m1 = got.maps.get(timeout=15)
            ref = EpisodeMap(start_msg("ep-svc"))
            for k in (0, 1):
                ref.integrate(frame(renderer, "ep-svc", k))
            assert m1.step == 1 and m1.explored_area_m2 == pytest.approx(ref.explored_area_m2())
            s1 = got.scores.get(timeout=5)

            # frame 1 sent again (the sim got no goal back): map update and scores published again, the frame is
            # not integrated twice and the semantic values are not written twice; an older frame is ignored
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-svc", 1))
            again = got.maps.get(timeout=15)
            assert again.step == 1 and again.explored_area_m2 == m1.explored_area_m2
            assert np.array_equal(again.free, m1.free) and np.array_equal(again.occupied, m1.occupied)
            assert np.array_equal(again.values["question"], m1.values["question"])
            assert again.frontiers == m1.frontiers
            s1_again = got.scores.get(timeout=5)
            assert s1_again.step == 1 and s1_again.answer_probs == s1.answer_probs
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-svc", 0))
            assert svc.drain()
            assert got.maps.empty() and got.scores.empty()

            # unknown episode: the first frame is held (it may have overtaken its start), a second one is refused
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-nobody", 0))
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-nobody", 0))
            err = got.errors.get(timeout=10)
            assert err.episode_id == "ep-nobody" and "unknown episode" in err.reason

            # a frame that overtook its EpisodeStart is mapped once the start arrives
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-late", 0))
            assert svc.drain()
            assert got.maps.empty()
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_msg("ep-late"))
            late = got.maps.get(timeout=15)
            assert late.episode_id == "ep-late" and late.step == 0
        finally:
            svc.stop()


def test_scorer_failure_is_reported_and_map_still_published(
    hub_settings: Settings, settings: Settings, renderer: Renderer
) -> None:
    def broken(req: ScoreRequest) -> ScoreResult:
        raise TimeoutError("no scorer replica answered within 1.0 s")

    with Bus(hub_settings, "gateway") as bus:
        got = Collector(bus)
        with serving(MapperService(settings, scorer=broken)):
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_msg("ep-noscore"))
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-noscore", 0))
            err = got.errors.get(timeout=15)
            assert "scorer failed" in err.reason and "no scorer replica" in err.reason and err.step == 0
            m = got.maps.get(timeout=10)
            assert m.step == 0 and m.explored_area_m2 > 0
            assert got.scores.empty()


def _spawn(settings: Settings, log: Path) -> subprocess.Popen:
    env = {**os.environ, **settings.env(), "EQA_SCORER_TIMEOUT_S": "1", "EQA_RECORD": "false"}
    env["PYTHONPATH"] = str(REPO)
    return subprocess.Popen(
        [sys.executable, "-m", "services.mapper"],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=log.open("ab"),
    )


def _wait_alive(bus: Bus, timeout: float = 30.0) -> None:
    if not wait_for(lambda: bool(bus.alive(keys.alive_service("mapper"), timeout=0.5)), timeout, every=0.2):
        raise TimeoutError("mapper did not come up")


def test_killed_mapper_resumes_from_snapshot(
    hub_settings: Settings, settings: Settings, renderer: Renderer, tmp_path: Path
) -> None:
    log = tmp_path / "mapper.log"
    with Bus(hub_settings, "gateway") as bus:
        got = Collector(bus)
        proc = _spawn(settings, log)
        try:
            _wait_alive(bus)
            time.sleep(0.3)
            bus.publish(keys.stream(ROBOT, keys.EPISODE_START), start_msg("ep-crash"))
            for k in range(3):
                bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-crash", k))
                m = got.maps.get(timeout=30)
                assert m.step == k
            before = m
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
            # wait until the dead process' liveliness token is gone, then start a fresh one
            deadline = time.monotonic() + 15
            while bus.alive(keys.alive_service("mapper"), timeout=0.5) and time.monotonic() < deadline:
                time.sleep(0.2)
            proc = _spawn(settings, log)
            _wait_alive(bus)
            time.sleep(0.3)
            bus.publish(keys.stream(ROBOT, keys.SIM_FRAME), frame(renderer, "ep-crash", 3))
            after = got.maps.get(timeout=30)
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
    assert after.step == 3
    ref = EpisodeMap(start_msg("ep-crash"))
    for k in range(4):
        ref.integrate(frame(renderer, "ep-crash", k))
    assert after.explored_area_m2 == pytest.approx(ref.explored_area_m2()), log.read_text()[-2000:]
    assert np.array_equal(after.explored, ref.maps.explored)
    # everything explored before the crash is still explored
    r0 = round((before.grid.origin_y - after.grid.origin_y) / after.grid.resolution)
    c0 = round((before.grid.origin_x - after.grid.origin_x) / after.grid.resolution)
    sub = after.explored[r0 : r0 + before.grid.rows, c0 : c0 + before.grid.cols]
    assert not (before.explored & ~sub).any()
    assert "restored from snapshot at step 2" in log.read_text()
