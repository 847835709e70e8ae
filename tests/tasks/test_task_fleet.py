"""A task through the product: POST /v1/tasks on the real gateway in front of the real services (sim,
mapper, scorer, planner, stopper as processes): the same lifecycle as questions, task phases in the SSE events,
the per-phase metrics in the final status."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from support.fleet import GatewayThread, sse_events, stored_end, wait_for
from support.gateway import AUTH, EPISODE_S

from eqa.settings import Settings
from services.sim.housegen import generate_house
from services.sim.tasks import generate_tasks

HOUSE = 115000  # a tuning-seed task house (eqa.seeds.TUNING_SEED 11)


@pytest.fixture
def client(gw_settings: Settings) -> Iterator[httpx.Client]:
    with GatewayThread(gw_settings) as gw, httpx.Client(base_url=gw.url, headers=AUTH, timeout=30) as c:
        assert wait_for(lambda: c.get("/v1/ready").status_code == 200)
        yield c


def test_a_pick_and_place_task_through_the_services(client: httpx.Client, gw_settings: Settings) -> None:
    c = client
    bad = c.post("/v1/tasks", json={"instruction": "dance a little", "scene": f"gen-{HOUSE}"})
    assert bad.status_code == 422 and "Move the <object>" in bad.text
    task = next(t for t in generate_tasks(generate_house(HOUSE), np.random.default_rng(HOUSE))
                if t.kind == "pick_place")
    body = {"instruction": task.text, "scene": f"gen-{HOUSE}", "start_pose": task.start_pose.model_dump(),
            "max_steps": 5, "record": False, "pick_limit": 5, "ablation": "helios"}
    r = c.post("/v1/tasks", json=body)
    assert r.status_code == 202, r.text
    eid = r.json()["episode_id"]
    events = [e for _, e in sse_events(c, f"/v1/episodes/{eid}/events", timeout=EPISODE_S)]
    kinds = [e["kind"] for e in events]
    assert kinds[0] == "episode_start" and kinds[-1] == "episode_end"
    goals = [e for e in events if e["kind"] == "goal"]
    assert goals and all(g["phase"] in ("searching", "local_search", "looking", "picking", "placing", "finished")
                         for g in goals)
    st = c.get(f"/v1/episodes/{eid}").json()
    assert st["state"] == "stopped", st
    assert st["task"]["kind"] == "pick_place" and st["task"]["object"] == task.object
    assert set(st["metrics"]) >= {"FindObj", "Pick", "FindRec", "Place", "SR", "collisions", "pick_attempts"}
    assert st["answer"] is None
    end = stored_end(gw_settings, eid)
    assert end is not None and end.metrics == st["metrics"]
    assert events[-1]["metrics"] == {k: round(v, 4) if isinstance(v, float) else v for k, v in st["metrics"].items()}
    # what it means: 5 steps do not achieve a pick-and-place; the status and the end event say which phase failed
    assert st["outcome"]["success"] is False and st["outcome"]["cause"] != "success", st
    assert st["outcome"]["phase"] is not None and st["outcome"]["step"] is not None, st  # from the sim's trace
    assert events[-1]["outcome"]["cause"] == st["outcome"]["cause"]
    assert (st["ablation"], st["pick_limit"]) == ("helios", 5)
    assert "answering" not in st["stop_reason"]


def test_a_task_without_a_budget_gets_the_task_budget(client: httpx.Client) -> None:
    """A task's default budget is the task benchmark's 6 sqrt(floor area), not a question's 3 sqrt(area) (a
    pick-and-place needs the search, the pick and the search for the goal); cancelled at once."""
    c = client
    area = generate_house(HOUSE).floor_area_m2
    r = c.post("/v1/tasks", json={"instruction": "Find a box", "scene": f"gen-{HOUSE}", "record": False})
    assert r.status_code == 202, r.text
    eid = r.json()["episode_id"]
    assert c.get(f"/v1/episodes/{eid}").json()["max_steps"] == int(6 * area**0.5)
    c.post(f"/v1/episodes/{eid}/cancel")
    assert wait_for(lambda: c.get(f"/v1/episodes/{eid}").json()["state"] in ("cancelled", "stopped"), EPISODE_S)


def test_a_task_the_house_lacks_reaches_the_terminal_as_an_error_with_exit_2(client: httpx.Client,
                                                                              gw_settings: Settings) -> None:
    """``eqa task --url`` (a running gateway: the CLI cannot check the server's scenes): the simulator refuses
    the task, the episode fails at once, the terminal shows the simulator's line saying what the house has."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from support.gateway import TOKEN

    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "EQA_DATA_DIR": str(gw_settings.data_dir), "PYTHONPATH": str(repo), "COLUMNS": "300"}
    out = subprocess.run([sys.executable, "-m", "eqa_app", "task", "Find a piano", "--scene", f"gen-{HOUSE}",
                          "--url", str(client.base_url), "--token", TOKEN, "--no-record"],
                         capture_output=True, text=True, timeout=EPISODE_S, env=env, cwd=repo)
    assert out.returncode == 2, out
    assert f"error from sim: task refused: gen-{HOUSE} has no piano (its small objects: " in out.stdout, out.stdout
    assert "failed after 0 of" in out.stdout and "sim refused the episode" in out.stdout, out.stdout
