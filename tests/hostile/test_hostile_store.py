"""Unbounded growth: stored episode records have a retention (count and age), the episode list
reads one page of an index instead of scanning every record, and stream ids are parsed into bounded
integers. Both store backends (embedded SQLite and a private Redis)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from eqa.bus import Bus
from eqa.messages import EpisodeEnd
from eqa.settings import Settings
from eqa.store import MAX_STREAM_PART, Store, StoreError, parse_stream_id
from gateway.auth import Caller
from gateway.manager import EpisodeManager, ev_key
from gateway.schemas import QuestionRequest

ALICE = Caller(tenant="t-alice", scopes=frozenset({"submit", "read"}), key="a")
BOB = Caller(tenant="t-bob", scopes=frozenset({"submit", "read"}), key="b")
ADMIN = Caller(tenant="t-admin", scopes=frozenset({"admin"}), key="c")


def _run(manager: EpisodeManager, caller: Caller, n: int) -> list[str]:
    """``n`` episodes submitted by ``caller`` and ended by a stopper's EpisodeEnd, oldest first."""
    ids = []
    for _ in range(n):
        eid = manager.submit(QuestionRequest(question="Is the oven on?", robot="robot0", max_steps=3, record=False),
                             caller).episode_id
        manager.handle("robot0", EpisodeEnd(episode_id=eid, robot="robot0", state="stopped", reason="done",
                                            steps=1, max_steps=3))
        ids.append(eid)
    return ids


@pytest.fixture
def manager(store: Store, settings: Settings, hub_settings: Settings) -> EpisodeManager:
    s = settings.model_copy(update={"episode_retention_count": 10, "episode_retention_days": 7.0})
    bus = Bus(hub_settings, "gateway", f"t-{time.monotonic_ns()}").open()
    m = EpisodeManager(s, store, bus)
    m.reconcile()
    yield m
    bus.close()


def test_retention_by_count_then_age_deletes_records_events_and_index(manager: EpisodeManager, store: Store) -> None:
    old = _run(manager, ALICE, 15)
    new = _run(manager, BOB, 10)
    assert store.index_len("gw:idx:all") == 25
    assert manager.prune() == 15
    assert store.index_len("gw:idx:all") == 10
    assert all(manager.load(e) is None and store.read(ev_key(e)) == [] for e in old)
    assert all(manager.load(e) is not None and store.read(ev_key(e)) for e in new)
    assert manager.list(ALICE) == [] and manager.list(ALICE, state="stopped") == []
    assert [s.episode_id for s in manager.list(BOB, limit=3)] == new[::-1][:3]
    assert manager.prune() == 0
    # a queued or running episode is never pruned, ended ones past the age limit are
    running = manager.submit(QuestionRequest(question="q?", robot="robot0", max_steps=3, record=False), BOB)
    assert manager.prune(now=time.time() + 8 * 86400) == 10
    assert [s.episode_id for s in manager.list(ADMIN)] == [running.episode_id]


def test_list_reads_an_index_not_every_record(manager: EpisodeManager, store: Store, monkeypatch) -> None:
    a = _run(manager, ALICE, 6)
    b = _run(manager, BOB, 3)

    def no_scan(prefix: str) -> list[str]:
        raise AssertionError(f"the list scanned keys {prefix!r}")

    monkeypatch.setattr(store, "keys", no_scan)  # a tripwire: listing must not walk the key space
    assert [s.episode_id for s in manager.list(ALICE, limit=4)] == a[::-1][:4]
    assert [s.episode_id for s in manager.list(BOB, state="stopped")] == b[::-1]
    assert [s.episode_id for s in manager.list(ADMIN, limit=2)] == b[::-1][:2]
    assert manager.list(BOB, state="failed") == [] and manager.list(BOB, state="running") == []


@pytest.mark.parametrize("bad", ["99999999999999999999-0", "0-99999999999999999999", f"{MAX_STREAM_PART + 1}-0",
                                 "1-", "-1", "1-2\n", "+1-2", " 1-2", "١-٢"])
def test_stream_ids_are_bounded_integers(bad: str, store: Store) -> None:
    with pytest.raises(ValueError):
        parse_stream_id(bad)
    with pytest.raises(StoreError):
        store.read("s", after=bad)
    assert parse_stream_id(f"{MAX_STREAM_PART}-{MAX_STREAM_PART}") == (MAX_STREAM_PART, MAX_STREAM_PART)
    store.append("s", b"x")
    assert store.read("s", after=f"{MAX_STREAM_PART}-0") == []


def test_old_records_without_tenant_are_indexed_once_and_admin_only(store: Store, settings: Settings,
                                                                    hub_settings: Settings, tmp_path: Path) -> None:
    from gateway.state import finished

    bus = Bus(hub_settings, "gateway", f"t-{time.monotonic_ns()}").open()
    try:
        m = EpisodeManager(settings, store, bus)
        m.reconcile()
        eid = _run(m, ALICE, 1)[0]
        raw = store.get_json(f"gw:ep:{eid}")
        raw.pop("owner")  # a record written before tenants existed
        raw["status"] = finished(m.load(eid).status, "stopped", "done", time.time()).model_dump(mode="json")
        store.set_json(f"gw:ep:{eid}", raw)
        for k in store.keys("gw:idx:"):
            store.delete(k)
        m2 = EpisodeManager(settings, store, bus)
        m2.reconcile()
        assert [s.episode_id for s in m2.list(ADMIN)] == [eid] and m2.list(ALICE) == []
    finally:
        bus.close()


def test_events_of_one_episode_are_bounded(manager: EpisodeManager, store: Store) -> None:
    """A bus peer that floods a running episode with messages cannot grow its event stream without end."""
    import numpy as np

    from eqa.messages import ErrorReply, Frame, Pose2D
    from gateway.manager import EVENTS_PER_STEP

    eid = manager.submit(QuestionRequest(question="q?", robot="robot0", max_steps=3, record=False), ALICE).episode_id
    frame = Frame(episode_id=eid, step=0, pose=Pose2D(x=0, y=0), camera_pose=np.eye(4), intrinsics=np.eye(3),
                  rgb=np.zeros((2, 2, 3), np.uint8), depth=np.zeros((2, 2), np.float32))
    for _ in range(400):
        manager.handle("robot0", frame)
    manager.handle("robot0", ErrorReply(source="mapper", episode_id=eid, step=0, reason="still told"))
    events = store.read(ev_key(eid), count=10_000)
    assert len(events) <= EVENTS_PER_STEP * 3 + 100 + 3, len(events)
    assert b"still told" in events[-1][1]  # errors are always kept
    manager.cancel(eid, ALICE)
    assert b'"kind":"episode_end"' in store.read(ev_key(eid), count=10_000)[-1][1]
