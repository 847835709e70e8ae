"""Ground truth through the real gateway (``POST /v1/episodes/{id}/label``) and recalibration from it
(``eqa calibrate --from-store`` / ``--check --from-store``), end to end: real services over Zenoh, real Redis,
the gateway over real HTTP."""

from __future__ import annotations

import httpx
import pytest
from support.fleet import GatewayThread, wait_for
from support.gateway import AUTH, EPISODE_S, SCENE, TOKEN

from eqa.settings import Settings
from eqa.store import open_store
from eqa_app.calibrate import main as calibrate_main
from services.stopper.calibration import TraceStore, load_table

CHOICES = ["bedroom", "hallway", "storage room", "living room"]
Q = {"question": "Where is the black suitcase?", "choices": CHOICES, "scene": SCENE, "max_steps": 4,
     "stop_rule": "max_steps", "record": False}
OTHER = "other-tenant-token"


@pytest.fixture
def gateway(gw_settings: Settings):
    s = gw_settings.model_copy(update={"api_tokens": [TOKEN, OTHER]})
    with GatewayThread(s) as gw, httpx.Client(base_url=gw.url, headers=AUTH, timeout=30) as c:
        assert wait_for(lambda: c.get("/v1/ready").status_code == 200, 60)
        yield s, c


def _run(c: httpx.Client, body: dict) -> str:
    r = c.post("/v1/questions", json=body)
    assert r.status_code in (200, 201, 202), r.text
    return r.json()["episode_id"]


def _state(c: httpx.Client, eid: str) -> str:
    return c.get(f"/v1/episodes/{eid}").json()["state"]


def test_label_then_recalibrate_and_check_from_the_store(gateway, monkeypatch: pytest.MonkeyPatch) -> None:
    settings, c = gateway
    eids = [_run(c, {**Q, "question_id": f"label-test-{i}"}) for i in range(5)]
    assert wait_for(lambda: all(_state(c, e) == "stopped" for e in eids), EPISODE_S * 2), [_state(c, e) for e in eids]

    # validation at the edge: letters / indices within the episode's choices, the caller's own finished episodes
    e0 = eids[0]
    assert c.post(f"/v1/episodes/{e0}/label", json={"answer": "E"}).status_code == 422
    assert c.post(f"/v1/episodes/{e0}/label", json={"answer": 4}).status_code == 422
    assert c.post(f"/v1/episodes/{e0}/label", json={"answer": "B", "extra": 1}).status_code == 422
    assert c.post("/v1/episodes/ep-doesnotexist/label", json={"answer": "B"}).status_code == 404
    other = c.post(f"/v1/episodes/{e0}/label", json={"answer": "B"}, headers={"Authorization": f"Bearer {OTHER}"})
    assert other.status_code == 404  # another tenant's episode does not exist for it
    running = _run(c, {**Q, "max_steps": 400})
    assert wait_for(lambda: _state(c, running) == "running", 30)
    assert c.post(f"/v1/episodes/{running}/label", json={"answer": "B"}).status_code == 409
    assert c.delete(f"/v1/episodes/{running}").status_code == 200

    for i, e in enumerate(eids):  # ground truth, as letters and as indices; a correction replaces a label
        r = c.post(f"/v1/episodes/{e}/label", json={"answer": ["A", 1, "c", 3, "A"][i]})
        assert r.status_code == 200, r.text
        assert r.json()["answer"] == ["A", "B", "C", "D", "A"][i] and r.json()["episode_id"] == e
    r = c.post(f"/v1/episodes/{eids[4]}/label", json={"answer": "B"})
    assert r.json()["answer"] == "B" and r.json()["answer_text"] == "hallway"

    for k, v in settings.env().items():
        monkeypatch.setenv(k, v)
    assert calibrate_main(["calibrate", "--from-store", "--eps", "0.2,0.5", "--name", "labelled",
                           "--no-progress"]) == 0
    with open_store(settings) as store:
        table, _ = load_table(store, "labelled")
        assert table is not None and table.n == 5
        assert sorted(table.question_ids) == sorted(f"episode:{e}" for e in eids)
        assert table.provenance["source"] == "labelled episodes"
        traces, _ = TraceStore(store).labelled()
        by_id = {t.question_id: t for t in traces}
        assert by_id[f"episode:{eids[4]}"].answer == "B"  # the correction
        assert sorted(table.kappas) == sorted(t.kappa() for t in traces)
    # the same episodes against their own table: nothing stale
    assert calibrate_main(["calibrate", "--check", "--from-store", "--name", "labelled", "--no-progress"]) == 0
