"""A demo episode on the real fleet (sim, mapper, vlm_scorer, planner, stopper as processes) through the
gateway: the merged .rrd is served over HTTP, verifies with the rerun tool and holds every entity the design
lists. One fleet and one episode (160x120 images, 4 steps) for the module.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fleet_support import GatewayThread, fleet_settings, sse_events, wait_for

from eqa.launcher import Fleet
from eqa.recording import ENTITIES, REQUIRED_ENTITIES
from gateway import recordings

SCENE = "gen-00001"
TASK_SCENE = "gen-115001"  # a tuning-seed task house with potted plants


@dataclass
class Episode:
    episode_id: str
    status: dict[str, Any]
    events: list[tuple[str, dict[str, Any]]]
    rrd: httpx.Response
    missing: httpx.Response
    out: Path
    task: tuple[dict[str, Any], Path] | None = None  # a task episode on the same fleet: final status, merged .rrd


@pytest.fixture(scope="module")
def episode(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[Episode]:
    from services.sim.library import load_or_generate

    s = fleet_settings(tmp_path_factory.mktemp("rec-fleet"), redis_url, record=True, episode_timeout_s=120.0)
    load_or_generate(SCENE, s.scenes_path)
    load_or_generate(TASK_SCENE, s.scenes_path)
    with (
        Fleet(s, scorers=1) as fleet,
        GatewayThread(fleet.client_settings()) as gw,
        httpx.Client(base_url=gw.url, timeout=60) as c,
    ):
        assert wait_for(lambda: c.get("/v1/ready").status_code == 200, 60), c.get("/v1/ready").text
        r = c.post(
            "/v1/questions",
            json={
                "question": "Which room is the sofa in?",
                "choices": ["kitchen", "living room", "bedroom", "bath"],
                "scene": SCENE,
                "max_steps": 4,
                "seed": 1,
                "stop_rule": "max_steps",
            },
        )
        assert r.status_code == 202, r.text
        eid = r.json()["episode_id"]
        events = list(sse_events(c, f"/v1/episodes/{eid}/events", timeout=300))
        st = c.get(f"/v1/episodes/{eid}").json()
        time.sleep(1.0)  # each service closes (flushes) its recorder when it sees the episode end
        rrd = c.get(f"/v1/episodes/{eid}/recording")
        missing = c.get("/v1/episodes/ep-none/recording")
        t = c.post("/v1/tasks", json={"instruction": "Find a potted plant", "scene": TASK_SCENE, "max_steps": 6,
                                      "seed": 1})
        assert t.status_code == 202, t.text
        tid = t.json()["episode_id"]
        list(sse_events(c, f"/v1/episodes/{tid}/events", timeout=300))
        tst = c.get(f"/v1/episodes/{tid}").json()
        time.sleep(1.0)
        trrd = c.get(f"/v1/episodes/{tid}/recording")
        assert trrd.status_code == 200, trrd.text
    out = s.data_dir / f"{eid}.rrd"
    out.write_bytes(rrd.content)
    tout = s.data_dir / f"{tid}.rrd"
    tout.write_bytes(trrd.content)
    yield Episode(eid, st, events, rrd, missing, out, (tst, tout))


def test_recording_served_over_http(episode: Episode) -> None:
    st = episode.status
    assert episode.events[-1][1]["kind"] == "episode_end"
    assert st["state"] == "stopped" and st["steps"] == 4, st
    assert st["recording"] == f"/v1/episodes/{episode.episode_id}/recording"
    assert episode.rrd.status_code == 200 and episode.rrd.headers["content-type"] == "application/octet-stream"
    ok, msg = recordings.verify(episode.out)
    assert ok, msg
    assert episode.missing.status_code == 404


def test_demo_episode_recording_has_every_entity(episode: Episode) -> None:
    paths = recordings.entity_paths(episode.out)
    missing = [
        k
        for k in REQUIRED_ENTITIES
        if not any(p == "/" + ENTITIES[k] or p.startswith("/" + ENTITIES[k] + "/") for p in paths)
    ]
    assert not missing, f"missing entities {missing}; recording has {sorted(paths)}"


def test_task_episode_recording_shows_phase_and_outcome(episode: Episode) -> None:
    """A task's recording holds its phase per step and its outcome (eqa.recording ENTITIES task_*)."""
    assert episode.task is not None
    st, path = episode.task
    assert st["state"] in ("stopped", "failed") and st["outcome"] is not None, st
    assert st["outcome"]["success"] == bool(st["metrics"].get("SR")), st
    assert "answering" not in (st["stop_reason"] or "")
    paths = recordings.entity_paths(path)
    for k in ("task_phase", "task_outcome"):
        assert "/" + ENTITIES[k] in paths, f"{ENTITIES[k]} missing; recording has {sorted(paths)}"
    assert any(p.startswith("/" + ENTITIES["task_flags"] + "/") for p in paths), sorted(paths)
