"""The homes API over real HTTP (uvicorn on loopback) with a real Redis: ``home`` on questions and tasks, the
list, one home's summary, reset, tenant isolation, the per-tenant bound under a hostile client, 409 while an
episode of the home runs, retention.

The gateway runs in this process with a private Zenoh port and no services: an episode it starts stays
"running" (nothing answers), which is what the 409 case needs. The home's memory is written here through the
contract the mapper writes it with (:func:`eqa.homes.write_summary` and keys under :func:`eqa.homes.prefix`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from support.fleet import GatewayThread, clear_gateway_state, lone_gateway_settings, wait_for
from support.gateway import ADMIN, READER, SCENE, TOKENS, A, B, Q

from eqa import homes, keys
from eqa.bus import Bus
from eqa.messages import EpisodeStart
from eqa.settings import Settings
from eqa.store import open_store

CAP = 5


def _settings(tmp: Path, redis_url: str, **update: object) -> Settings:
    base = {"redis_url": redis_url, "episode_timeout_s": 3600.0, "robots": ["robot0", "robot1"],
            "queue_max_per_robot": 50, "queue_max_per_token": 50, "homes_max_per_tenant": CAP}
    return lone_gateway_settings(tmp / "var", TOKENS, **{**base, **update})


def _clear(s: Settings) -> None:
    clear_gateway_state(s)
    with open_store(s) as store:
        store.delete_many(store.keys(homes.PREFIX))


@pytest.fixture
def gw(tmp_path: Path, redis_url: str) -> Iterator[tuple[GatewayThread, httpx.Client]]:
    s = _settings(tmp_path, redis_url)
    _clear(s)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
        yield g, c
        for h in (A, B, ADMIN):
            for ep in c.get("/v1/episodes", headers=h).json()["episodes"]:
                if ep["state"] in ("queued", "running"):
                    c.delete(f"/v1/episodes/{ep['episode_id']}", headers=h)
    _clear(s)


def _tenant(token: str) -> str:
    from gateway.auth import tenant_of

    return tenant_of(token)


def _starts(s: Settings) -> tuple[list[EpisodeStart], Bus]:
    """EpisodeStarts the gateway publishes, as the services receive them."""
    got: list[EpisodeStart] = []
    lock = threading.Lock()
    bus = Bus(s.model_copy(update={"zenoh_listen": [], "zenoh_connect": s.zenoh_listen}), "sim", "test")
    bus.__enter__()

    def on(_k: str, m: EpisodeStart) -> None:
        with lock:
            got.append(m)

    bus.subscribe(keys.any_robot(keys.EPISODE_START), EpisodeStart, on)
    return got, bus




def test_home_round_trip_question_task_list_get_delete(gw) -> None:
    g, c = gw
    starts, bus = _starts(g.settings)
    try:
        time.sleep(1.0)  # the subscriber's link to the gateway's session
        r = c.post("/v1/questions", json={**Q, "home": "flat-1"}, headers=A)
        assert r.status_code == 202, r.text
        eid = r.json()["episode_id"]
        hid = homes.home_id(_tenant("tok-a"), "flat-1")
        assert wait_for(lambda: any(s.episode_id == eid for s in starts), 15.0)
        start = next(s for s in starts if s.episode_id == eid)
        assert start.home == hid and hid != "flat-1"  # the services see the internal id only
        plain = c.post("/v1/questions", json=Q, headers=A).json()["episode_id"]
        assert wait_for(lambda: any(s.episode_id == plain for s in starts), 15.0)
        assert next(s for s in starts if s.episode_id == plain).home is None  # no home: no memory
    finally:
        bus.__exit__(None, None, None)

    info = c.get("/v1/homes/flat-1", headers=A).json()
    assert info["name"] == "flat-1" and info["episodes_submitted"] == 1 and info["memory"] is None
    assert info["active_episodes"] == [eid] and info["age_s"] >= 0
    # a task naming the same home: one home, two episodes
    t = c.post("/v1/tasks", json={"instruction": "Find a mug", "scene": SCENE, "home": "flat-1", "record": False},
               headers=A)
    assert t.status_code == 202, t.text
    info = c.get("/v1/homes/flat-1", headers=A).json()
    assert info["episodes_submitted"] == 2 and set(info["active_episodes"]) == {eid, t.json()["episode_id"]}

    # what the mapper stores of the home shows in the summary
    with open_store(g.settings) as store:
        homes.write_summary(store, homes.HomeSummary(home=hid, episodes=1, views=12, bytes=34567, scenes=[SCENE]))
        store.set(homes.prefix(hid) + "views", b"x" * 100)
    mem = c.get("/v1/homes/flat-1", headers=A).json()["memory"]
    assert (mem["views"], mem["bytes"], mem["episodes"], mem["scenes"]) == (12, 34567, 1, [SCENE])

    # the list: newest first, paged, with the summaries
    c.post("/v1/questions", json={**Q, "home": "flat-2"}, headers=A)
    listed = c.get("/v1/homes", headers=A).json()
    assert [h["name"] for h in listed["homes"]] == ["flat-2", "flat-1"] and listed["total"] == 2
    assert listed["homes"][1]["memory"]["views"] == 12
    page = c.get("/v1/homes", params={"limit": 1, "offset": 1}, headers=A).json()
    assert [h["name"] for h in page["homes"]] == ["flat-1"] and (page["limit"], page["offset"]) == (1, 1)

    # reset: refused while its episodes run, then the memory and the name go
    r = c.delete("/v1/homes/flat-1", headers=A)
    assert r.status_code == 409 and eid in r.json()["detail"], r.text
    assert c.get("/v1/homes/flat-1", headers=A).json()["memory"]["views"] == 12  # nothing lost by the refusal
    for e in info["active_episodes"]:
        assert c.delete(f"/v1/episodes/{e}", headers=A).json()["state"] == "cancelled"
    r = c.delete("/v1/homes/flat-1", headers=A)
    assert r.status_code == 200 and r.json() == {"name": "flat-1", "deleted_keys": 2}
    with open_store(g.settings) as store:
        assert store.keys(homes.prefix(hid)) == []
    assert c.get("/v1/homes/flat-1", headers=A).status_code == 404
    assert c.delete("/v1/homes/flat-1", headers=A).status_code == 404
    assert [h["name"] for h in c.get("/v1/homes", headers=A).json()["homes"]] == ["flat-2"]
    # naming it again makes a new, empty home
    c.post("/v1/questions", json={**Q, "home": "flat-1"}, headers=A)
    again = c.get("/v1/homes/flat-1", headers=A).json()
    assert again["episodes_submitted"] == 1 and again["memory"] is None


def test_a_reset_while_a_mapper_writes_the_home_back_is_refused_and_loses_nothing(gw) -> None:
    g, c = gw
    eid = c.post("/v1/questions", json={**Q, "home": "flat-w"}, headers=A).json()["episode_id"]
    assert c.delete(f"/v1/episodes/{eid}", headers=A).json()["state"] == "cancelled"
    hid = homes.home_id(_tenant("tok-a"), "flat-w")
    with open_store(g.settings) as store:
        homes.write_summary(store, homes.HomeSummary(home=hid, episodes=1, views=3, bytes=99))
        assert homes.take_lock(store, hid, "mapper-1", 0.0)  # the mapper writes the ended episode back
        r = c.delete("/v1/homes/flat-w", headers=A)
        assert r.status_code == 409 and "try again" in r.json()["detail"] and r.headers["retry-after"], r.text
        assert c.get("/v1/homes/flat-w", headers=A).json()["memory"]["views"] == 3  # nothing lost
        assert "flat-w" in [h["name"] for h in c.get("/v1/homes", headers=A).json()["homes"]]
        store.delete(homes.lock_key(hid))
    r = c.delete("/v1/homes/flat-w", headers=A)
    assert r.status_code == 200 and r.json()["deleted_keys"] == 1, r.text
    assert c.get("/v1/homes/flat-w", headers=A).status_code == 404


def test_a_reset_waiting_for_a_write_back_holds_up_no_other_request(gw) -> None:
    """The reset waits (up to 2 s) for a mapper's write-back without the manager's lock: other requests answer
    meanwhile, a question naming the home being reset gets 409 with Retry-After (it would read a memory being
    deleted), and the reset goes through once the write-back ends."""
    g, c = gw
    eid = c.post("/v1/questions", json={**Q, "home": "flat-v"}, headers=A).json()["episode_id"]
    c.delete(f"/v1/episodes/{eid}", headers=A)
    hid = homes.home_id(_tenant("tok-a"), "flat-v")
    manager = g.server.config.app.state.manager
    manager.homes.reset_wait_s = 30.0  # the probes below take what they take on a loaded machine
    with open_store(g.settings) as store:
        homes.write_summary(store, homes.HomeSummary(home=hid, episodes=1, views=3, bytes=99))
        assert homes.take_lock(store, hid, "mapper-1", 0.0)
        result: dict[str, httpx.Response] = {}
        with httpx.Client(base_url=g.url, timeout=30) as c2:
            reset = threading.Thread(target=lambda: result.update(r=c2.delete("/v1/homes/flat-v", headers=A)))
            reset.start()
            try:
                assert wait_for(lambda: hid in manager._resetting, 10.0)  # the reset waits for the write-back
                other = c.post("/v1/questions", json={**Q, "home": "flat-u"}, headers=B)
                listed = c.get("/v1/homes", headers=A)
                assert other.status_code == 202 and listed.status_code == 200, (other.text, listed.text)
                assert reset.is_alive()  # answered while the reset still waits (it held the lock for all: 2 s)
                r = c.post("/v1/questions", json={**Q, "home": "flat-v"}, headers=A)
                assert r.status_code == 409 and "being reset" in r.json()["detail"] and r.headers["retry-after"]
            finally:
                store.delete(homes.lock_key(hid))  # the write-back ends
                reset.join(10)
    assert result["r"].status_code == 200, result["r"].text
    assert c.get("/v1/homes/flat-v", headers=A).status_code == 404 and hid not in manager._resetting


def test_a_home_is_one_house(gw) -> None:
    """A home's memory is of one house: the same home in another scene is a 409 (nothing written); the house
    after changes (gen-<seed>-c<k>) is the same house."""
    _g, c = gw
    assert c.post("/v1/questions", json={**Q, "home": "flat"}, headers=A).status_code == 202
    n = len(c.get("/v1/episodes", headers=A).json()["episodes"])
    for path, body in (("/v1/questions", {**Q, "scene": "gen-00002", "home": "flat"}),
                       ("/v1/tasks", {"instruction": "Find a mug", "scene": "gen-00002", "home": "flat"})):
        r = c.post(path, json=body, headers=A)
        assert r.status_code == 409 and "is the house gen-00001" in r.json()["detail"], r.text
    assert len(c.get("/v1/episodes", headers=A).json()["episodes"]) == n
    info = c.get("/v1/homes/flat", headers=A).json()
    assert info["house"] == SCENE and info["episodes_submitted"] == 1
    r = c.post("/v1/questions", json={**Q, "scene": "gen-00001-c2", "home": "flat"}, headers=A)
    assert r.status_code == 202, r.text
    assert c.get("/v1/homes/flat", headers=A).json()["episodes_submitted"] == 2
    # a real robot's world (no scene) is a house of its own
    r = c.post("/v1/questions", json={"question": "Where is it?", "robot": "robot1", "home": "flat"}, headers=A)
    assert r.status_code == 409 and "no scene" in r.json()["detail"]


def test_homes_belong_to_their_tenant(gw) -> None:
    g, c = gw
    r = c.post("/v1/questions", json={**Q, "home": "shared-name"}, headers=A)
    assert r.status_code == 202
    eid = r.json()["episode_id"]
    a_home = homes.home_id(_tenant("tok-a"), "shared-name")
    with open_store(g.settings) as store:
        homes.write_summary(store, homes.HomeSummary(home=a_home, views=3))
    # B cannot read, list or delete A's home; the same name under B is B's own (new) home
    for method in ("GET", "DELETE"):
        r = c.request(method, "/v1/homes/shared-name", headers=B)
        assert r.status_code == 404 and "no home" in r.text, (method, r.text)
    assert c.get("/v1/homes", headers=B).json() == {"homes": [], "total": 0, "offset": 0, "limit": 50}
    assert c.get("/v1/homes/shared-name", headers=READER).status_code == 404
    assert c.delete("/v1/homes/shared-name", headers=READER).status_code == 403  # reset needs submit
    rb = c.post("/v1/questions", json={**Q, "home": "shared-name"}, headers=B)
    assert rb.status_code == 202
    b_info = c.get("/v1/homes/shared-name", headers=B).json()
    assert b_info["memory"] is None and b_info["active_episodes"] == [rb.json()["episode_id"]]
    assert c.get("/v1/homes/shared-name", headers=A).json()["memory"]["views"] == 3  # A's untouched
    assert c.get("/v1/homes/shared-name", headers=A).json()["active_episodes"] == [eid]
    # admin: homes are per tenant, so its own names only
    assert c.get("/v1/homes/shared-name", headers=ADMIN).status_code == 404
    c.delete(f"/v1/episodes/{rb.json()['episode_id']}", headers=B)
    assert c.delete("/v1/homes/shared-name", headers=B).status_code == 200
    assert c.get("/v1/homes/shared-name", headers=A).json()["memory"]["views"] == 3


BAD_HOMES = [
    ("huge name", "h" * 100_000),
    ("65 characters", "h" * 65),
    ("trailing newline", "flat\n"),
    ("path", "../eqa:home:x"),
    ("key pattern", "flat*"),
    ("colon", "a:b"),
    ("empty", ""),
    ("unicode", "wohnung-ü"),
]


@pytest.mark.parametrize(("case", "name"), BAD_HOMES, ids=[c for c, _ in BAD_HOMES])
def test_bad_home_names_get_a_422_and_change_nothing(gw, case: str, name: str) -> None:
    _g, c = gw
    for path, body in (("/v1/questions", {**Q, "home": name}),
                       ("/v1/tasks", {"instruction": "Find a mug", "scene": SCENE, "home": name})):
        r = c.post(path, json=body, headers=A)
        assert r.status_code in (413, 422), (case, path, r.status_code, r.text[:200])
        if r.status_code == 422:
            assert any("home" in [str(p) for p in d["loc"]] for d in r.json()["detail"]), r.text[:300]
    for body in ({**Q, "home": 7}, {**Q, "home": ["a"]}, {**Q, "home": None, "extra": 1}):
        assert c.post("/v1/questions", json=body, headers=A).status_code == 422
    assert c.get("/v1/episodes", headers=A).json()["episodes"] == []
    assert c.get("/v1/homes", headers=A).json()["total"] == 0


@pytest.mark.parametrize("path", ["/v1/homes/a%0A", "/v1/homes/" + "x" * 65, "/v1/homes/a*", "/v1/homes/%00"])
def test_bad_home_paths_are_refused(gw, path: str) -> None:
    _g, c = gw
    for method in ("GET", "DELETE"):
        r = c.request(method, path, headers=A)
        assert r.status_code in (404, 422), (method, path, r.status_code)
    for params in ({"limit": 0}, {"limit": 1001}, {"offset": -1}, {"offset": 100_001}, {"limit": "x"}, {"limt": 5},
                   {"": "null"}):
        assert c.get("/v1/homes", params=params, headers=A).status_code == 422, params


def test_many_homes_hit_the_tenant_bound_and_nothing_else_is_lost(gw) -> None:
    """A hostile client names new homes until the bound: each past it gets a 429 naming the setting, stores no
    episode and no home; its homes, the old names and the other tenants' homes go on working."""
    g, c = gw
    ids = []
    for k in range(CAP):
        r = c.post("/v1/questions", json={**Q, "home": f"h{k}"}, headers=A)
        assert r.status_code == 202, r.text
        ids.append(r.json()["episode_id"])
    n_episodes = len(c.get("/v1/episodes", headers=A).json()["episodes"])
    for k in range(CAP, CAP + 30):
        r = c.post("/v1/questions", json={**Q, "home": f"h{k}"}, headers=A)
        assert r.status_code == 429 and "EQA_HOMES_MAX_PER_TENANT=5" in r.json()["detail"], r.text
        t = c.post("/v1/tasks", json={"instruction": "Find a mug", "scene": SCENE, "home": f"h{k}"}, headers=A)
        assert t.status_code == 429
    assert len(c.get("/v1/episodes", headers=A).json()["episodes"]) == n_episodes
    listed = c.get("/v1/homes", params={"limit": 1000}, headers=A).json()
    assert listed["total"] == CAP and sorted(h["name"] for h in listed["homes"]) == [f"h{k}" for k in range(CAP)]
    with open_store(g.settings) as store:
        assert len(store.keys("gw:home:")) == CAP
    # an existing home is still usable, no home at all too, and another tenant has its own bound
    assert c.post("/v1/questions", json={**Q, "home": "h0"}, headers=A).status_code == 202
    assert c.post("/v1/questions", json=Q, headers=A).status_code == 202
    assert c.post("/v1/questions", json={**Q, "home": "h9"}, headers=B).status_code == 202
    # a delete frees a slot
    for e in ids[1:2]:
        c.delete(f"/v1/episodes/{e}", headers=A)
    assert c.delete("/v1/homes/h1", headers=A).status_code == 200
    assert c.post("/v1/questions", json={**Q, "home": "fresh"}, headers=A).status_code == 202
    assert c.post("/v1/questions", json={**Q, "home": "fresh2"}, headers=A).status_code == 429


def test_concurrent_new_homes_never_pass_the_bound(gw) -> None:
    """40 submissions naming 40 new homes at once (a hostile client in parallel): exactly the bound succeed."""
    from concurrent.futures import ThreadPoolExecutor

    g, c = gw

    def post(k: int) -> int:
        with httpx.Client(base_url=g.url, timeout=30) as own:
            return own.post("/v1/questions", json={**Q, "home": f"p{k}"}, headers=A).status_code

    with ThreadPoolExecutor(max_workers=16) as pool:
        codes = list(pool.map(post, range(40)))
    assert sorted(codes) == [202] * CAP + [429] * (40 - CAP), codes
    assert c.get("/v1/homes", headers=A).json()["total"] == CAP
    assert len(c.get("/v1/episodes", headers=A).json()["episodes"]) == CAP
    with open_store(g.settings) as store:
        assert len(store.keys("gw:home:")) == CAP


def test_unused_homes_are_deleted_after_retention(gw) -> None:
    g, c = gw
    r = c.post("/v1/questions", json={**Q, "home": "old"}, headers=A)
    c.post("/v1/questions", json={**Q, "home": "busy"}, headers=A)
    c.delete(f"/v1/episodes/{r.json()['episode_id']}", headers=A)
    hid = homes.home_id(_tenant("tok-a"), "old")
    with open_store(g.settings) as store:
        homes.write_summary(store, homes.HomeSummary(home=hid, views=1))
    from gateway.manager import EpisodeManager

    manager: EpisodeManager = g.server.config.app.state.manager  # the running gateway's own manager
    later = time.time() + g.settings.homes_retention_days * 86400.0 + 60
    assert manager.prune_homes(now=time.time()) == 0
    assert manager.prune_homes(now=later) == 1  # "busy" has a running episode: kept
    assert c.get("/v1/homes/old", headers=A).status_code == 404
    assert c.get("/v1/homes/busy", headers=A).status_code == 200
    with open_store(g.settings) as store:
        assert store.keys(homes.prefix(hid)) == []


def test_a_restarted_gateway_keeps_homes_and_their_running_episodes(tmp_path: Path, redis_url: str) -> None:
    """Home records and the episodes that hold a home are in the store: a gateway restarted on the same Redis
    lists the home, shows its running episode and still refuses its reset."""
    s = _settings(tmp_path, redis_url)
    _clear(s)
    try:
        with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
            eid = c.post("/v1/questions", json={**Q, "home": "kept"}, headers=A).json()["episode_id"]
            for k in range(CAP - 1):
                assert c.post("/v1/questions", json={**Q, "home": f"k{k}"}, headers=A).status_code == 202
        with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
            info = c.get("/v1/homes/kept", headers=A).json()
            assert info["active_episodes"] == [eid] and info["episodes_submitted"] == 1
            assert c.delete("/v1/homes/kept", headers=A).status_code == 409
            assert c.get("/v1/homes", headers=A).json()["total"] == CAP
            assert c.post("/v1/questions", json={**Q, "home": "one-more"}, headers=A).status_code == 429
            assert c.delete(f"/v1/episodes/{eid}", headers=A).json()["state"] == "cancelled"
            assert c.delete("/v1/homes/kept", headers=A).status_code == 200
    finally:
        _clear(s)


def test_openapi_documents_the_homes_routes(gw) -> None:
    _g, c = gw
    spec = c.get("/openapi.json", headers=A).json()
    want = {
        ("/v1/homes", "get"): {"200", "401", "403", "422", "429", "503"},
        ("/v1/homes/{name}", "get"): {"200", "401", "403", "404", "422", "429", "503"},
        ("/v1/homes/{name}", "delete"): {"200", "400", "401", "403", "404", "408", "409", "413", "422", "429",
                                         "503"},
    }
    for (path, method), codes in want.items():
        assert set(spec["paths"][path][method]["responses"]) == codes, (path, method)
    for model in ("QuestionRequest", "TaskRequest"):
        assert "home" in spec["components"]["schemas"][model]["properties"]


def test_eqa_ask_sends_the_home(tmp_path: Path) -> None:
    import argparse

    from eqa_app import ask

    parser = argparse.ArgumentParser()
    ask.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["ask", "Where is it?", "--choice", "a", "--choice", "b", "--scene", SCENE,
                              "--home", "flat-1"])
    body, _ = ask._body(args, tmp_path)
    assert body["home"] == "flat-1" and body["scene"] == SCENE
    assert "home" not in ask._body(parser.parse_args(["ask", "Where is it?", "--scene", SCENE]), tmp_path)[0]


def test_eqa_ask_says_when_a_warm_question_stopped_on_a_table_not_calibrated_for_warm_starts(gw, capsys) -> None:
    """The stopper's decisions of a warm start on the cold table carry ``warm_calibrated`` False (the services'
    part: tests/stopper/test_warm_calibration.py); `eqa ask` follows the gateway's event stream and says so under
    the answer. Here the stopper's messages come from the test's own Zenoh peer, over the real gateway."""
    from eqa.messages import Decision, EpisodeEnd
    from eqa_app import ask
    from services.stopper.state import WARM_NOT_CALIBRATED

    g, _c = gw
    starts, bus = _starts(g.settings)
    note = f"{WARM_NOT_CALIBRATED}: no warm table is named (EQA_HOME_CALIBRATION_NAME is empty)"
    out: dict[str, ask.Outcome] = {}
    t = threading.Thread(target=lambda: out.setdefault("o", ask.follow(
        g.url, {**Q, "home": "flat-ask"}, "tok-a", 30.0, quiet=False)))
    t.start()
    try:
        assert wait_for(lambda: bool(starts), timeout=15.0)
        s = starts[0]
        time.sleep(0.5)  # the client's event stream is open before the episode's messages come
        reason = (f"one answer left in the prediction set: A (CP eps=0.2, q_hat=1.2, N=40; {note}; stopping on the "
                  "cold table)")
        bus.publish(keys.stream(s.robot, keys.STOPPER_DECISION), Decision(
            episode_id=s.episode_id, step=0, rule="cp", stop=True, reason=reason, prediction_set=["A"], answer="A",
            q_hat=1.2, warm_calibrated=False))
        bus.publish(keys.stream(s.robot, keys.EPISODE_END), EpisodeEnd(
            episode_id=s.episode_id, robot=s.robot, state="stopped", reason=reason, answer="A", steps=1,
            max_steps=3, prediction_set=["A"]))
        t.join(30.0)
    finally:
        bus.__exit__(None, None, None)
    outcome = out["o"]
    assert outcome.warm_uncalibrated is not None and outcome.status["state"] == "stopped"
    ask._report(outcome, g.settings, None, False)
    printed = capsys.readouterr().out
    assert "warning: this question started from its home's memory and its " + WARM_NOT_CALIBRATED in printed
    assert "EQA_HOME_CALIBRATION_NAME is empty" in printed.split("warning:")[1]


def test_a_tenants_homes_are_bounded_in_bytes(tmp_path: Path, redis_url: str) -> None:
    """EQA_HOMES_MAX_BYTES_PER_TENANT: an episode naming a home is admitted only while the tenant's other homes
    (stored bytes, or EQA_HOME_MAX_BYTES while an episode of theirs runs) and this one's bound fit; past it a 429
    naming the setting and nothing stored; another tenant has its own bound; a bound below one home's is refused."""
    one = 1_000_000
    s = _settings(tmp_path, redis_url, home_max_bytes=one, homes_max_bytes_per_tenant=2_500_000)
    _clear(s)
    with GatewayThread(s) as g, httpx.Client(base_url=g.url, timeout=30) as c:
        first = c.post("/v1/questions", json={**Q, "home": "b1"}, headers=A)
        second = c.post("/v1/questions", json={**Q, "home": "b2"}, headers=A)
        assert first.status_code == 202 and second.status_code == 202, second.text
        # b1 and b2 have running episodes: 2 x 1 MB counted, one more home would need 3 MB
        r = c.post("/v1/questions", json={**Q, "home": "b3"}, headers=A)
        assert r.status_code == 429 and "EQA_HOMES_MAX_BYTES_PER_TENANT=2500000" in r.json()["detail"], r.text
        assert c.post("/v1/tasks", json={"instruction": "Find a mug", "scene": SCENE, "home": "b3"},
                      headers=A).status_code == 429
        assert c.get("/v1/homes/b3", headers=A).status_code == 404  # nothing stored
        assert c.post("/v1/questions", json={**Q, "home": "b1"}, headers=A).status_code == 202  # its own bound
        assert c.post("/v1/questions", json={**Q, "home": "b3"}, headers=B).status_code == 202  # another tenant
        assert c.post("/v1/questions", json=Q, headers=A).status_code == 202  # no home: no bound
        # b2's episode ends and the mapper wrote 0.2 MB: 1 MB (b1 runs) + 0.2 MB + 1 MB fit
        assert c.delete(f"/v1/episodes/{second.json()['episode_id']}", headers=A).json()["state"] == "cancelled"
        with open_store(s) as store:
            homes.write_summary(store, homes.HomeSummary(home=homes.home_id(_tenant("tok-a"), "b2"), bytes=200_000))
        assert c.post("/v1/questions", json={**Q, "home": "b3"}, headers=A).status_code == 202
        for h in (A, B):
            for ep in c.get("/v1/episodes", headers=h).json()["episodes"]:
                if ep["state"] in ("queued", "running"):
                    c.delete(f"/v1/episodes/{ep['episode_id']}", headers=h)
    _clear(s)
    with pytest.raises(ValueError, match="EQA_HOMES_MAX_BYTES_PER_TENANT=1000000 is below EQA_HOME_MAX_BYTES"):
        Settings(home_max_bytes=2_000_000, homes_max_bytes_per_tenant=1_000_000)
