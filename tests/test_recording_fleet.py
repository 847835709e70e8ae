"""A demo episode on the real fleet (sim, mapper, vlm_scorer, planner, stopper as processes) through the
gateway: the merged .rrd verifies with the rerun tool and holds every entity the design lists.

Needs the full fleet; it takes longer than the unit tests, so it runs only with RUN_FLEET_TESTS=1.
"""

from __future__ import annotations

import os
import time

import httpx
import pytest

from eqa.recording import ENTITIES, REQUIRED_ENTITIES
from eqa.settings import Settings
from gateway import recordings
from gateway.harness import GatewayThread, sse_events

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(os.environ.get("RUN_FLEET_TESTS") != "1", reason="full-fleet test: set RUN_FLEET_TESTS=1"),
]


def test_demo_episode_recording_has_every_entity(settings: Settings, redis_url: str) -> None:
    from eqa.launcher import Fleet

    # zenoh_listen empty: the launcher's router picks a free port itself and hands it to the children.
    s = settings.model_copy(
        update={
            "record": True,
            "redis_url": redis_url,
            "episode_timeout_s": 120.0,
            "zenoh_listen": [],
            "zenoh_connect": [],
        }
    )
    with (
        Fleet(s, scorers=1) as fleet,
        GatewayThread(fleet.client_settings()) as gw,
        httpx.Client(base_url=gw.url, timeout=60) as c,
    ):
        deadline = time.monotonic() + 60
        while c.get("/v1/ready").status_code != 200:
            assert time.monotonic() < deadline, c.get("/v1/ready").text
            time.sleep(0.2)
        r = c.post(
            "/v1/questions",
            json={
                "question": "Which room is the sofa in?",
                "choices": ["kitchen", "living room", "bedroom", "bath"],
                "scene": "gen-00001",
                "max_steps": 6,
                "seed": 1,
                "stop_rule": "max_steps",
            },
        )
        assert r.status_code == 202, r.text
        eid = r.json()["episode_id"]
        events = list(sse_events(c, f"/v1/episodes/{eid}/events", timeout=300))
        assert events[-1][1]["kind"] == "episode_end"
        st = c.get(f"/v1/episodes/{eid}").json()
        assert st["state"] == "stopped", st
        time.sleep(1.0)  # the services close their recorders on EpisodeEnd
        rrd = c.get(f"/v1/episodes/{eid}/recording")
        assert rrd.status_code == 200
    out = s.data_dir / f"{eid}.rrd"
    out.write_bytes(rrd.content)
    ok, msg = recordings.verify(out)
    assert ok, msg
    paths = recordings.entity_paths(out)
    missing = [
        k
        for k in REQUIRED_ENTITIES
        if not any(p == "/" + ENTITIES[k] or p.startswith("/" + ENTITIES[k] + "/") for p in paths)
    ]
    assert not missing, f"missing entities {missing}; recording has {sorted(paths)}"
