"""The same store contract on the embedded (SQLite) and Redis backends."""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

import pytest

from eqa.settings import Settings
from eqa.store import EmbeddedStore, RedisStore, StoreError, open_store


def test_kv_roundtrip_prefix_and_expiry(store):
    store.set("eqa:ep:1", b"one")
    store.set("eqa:ep:2", b"two")
    store.set("eqa:other", b"x")
    assert store.get("eqa:ep:1") == b"one"
    assert store.keys("eqa:ep:") == ["eqa:ep:1", "eqa:ep:2"]
    store.delete("eqa:ep:1")
    assert store.get("eqa:ep:1") is None
    store.set_json("eqa:j", {"a": [1, 2]})
    assert store.get_json("eqa:j") == {"a": [1, 2]}
    store.set("eqa:tmp", b"t", ttl_s=0.05)
    time.sleep(0.15)
    assert store.get("eqa:tmp") is None


def test_set_many_writes_in_order_with_expiry_then_deletes(store):
    store.set("eqa:part:old", b"old")
    store.set("eqa:part:keep", b"keep")
    # a key given twice ends with its last value (the items are written in order), the deletes come after
    store.set_many([("eqa:part:new", b"1"), ("eqa:env", b"first"), ("eqa:env", b"second")], ttl_s=0.3,
                   then_delete=["eqa:part:old", "eqa:part:new-never-written"])
    assert store.get("eqa:env") == b"second" and store.get("eqa:part:new") == b"1"
    assert store.get("eqa:part:old") is None and store.get("eqa:part:keep") == b"keep"
    store.set_many([("eqa:gone", b"x")], then_delete=["eqa:gone"])  # deleted after it was set
    assert store.get("eqa:gone") is None
    store.set_many([], then_delete=[])
    time.sleep(0.45)
    assert store.get("eqa:env") is None and store.get("eqa:part:new") is None  # ttl_s applies to every item
    assert store.get("eqa:part:keep") == b"keep"


def test_set_if_absent_is_a_lock(store):
    assert store.set_if_absent("eqa:lock", b"a")
    assert not store.set_if_absent("eqa:lock", b"b")
    assert store.get("eqa:lock") == b"a"


def test_delete_if_equal_releases_only_the_holders_value(store):
    assert store.set_if_absent("eqa:lock", b"token-a", ttl_s=0.2)
    time.sleep(0.3)  # a's lock expired; b takes it
    assert store.set_if_absent("eqa:lock", b"token-b", ttl_s=30)
    assert not store.delete_if_equal("eqa:lock", b"token-a")  # a's late release leaves b's lock
    assert store.get("eqa:lock") == b"token-b"
    assert store.delete_if_equal("eqa:lock", b"token-b") and store.get("eqa:lock") is None
    assert not store.delete_if_equal("eqa:lock", b"token-b")


def test_set_many_if_writes_only_over_the_expected_guard(store):
    assert store.set_many_if("eqa:idx", None, [("eqa:part", b"p1"), ("eqa:idx", b"v1")], then_delete=["eqa:old"])
    assert store.get("eqa:idx") == b"v1" and store.get("eqa:part") == b"p1"
    store.set("eqa:old", b"x")
    # a writer that read v1 and one that read nothing: only the first writes
    assert not store.set_many_if("eqa:idx", None, [("eqa:part", b"late"), ("eqa:idx", b"v1-late")])
    assert store.set_many_if("eqa:idx", b"v1", [("eqa:part", b"p2"), ("eqa:idx", b"v2")], ttl_s=30,
                             then_delete=["eqa:old"])
    assert not store.set_many_if("eqa:idx", b"v1", [("eqa:part", b"p3"), ("eqa:idx", b"v3")])
    assert (store.get("eqa:idx"), store.get("eqa:part"), store.get("eqa:old")) == (b"v2", b"p2", None)


def test_streams_are_ordered_and_resumable(store):
    ids = [store.append("eqa:events:1", f"e{i}".encode()) for i in range(50)]
    assert len(set(ids)) == 50
    assert [tuple(map(int, i.split("-"))) for i in ids] == sorted(tuple(map(int, i.split("-"))) for i in ids)
    first = store.read("eqa:events:1", count=20)
    assert [v for _, v in first] == [f"e{i}".encode() for i in range(20)]
    rest = store.read("eqa:events:1", after=first[-1][0])
    assert [v for _, v in rest] == [f"e{i}".encode() for i in range(20, 50)]
    assert store.read("eqa:events:1", after=ids[-1]) == []
    assert store.stream_len("eqa:events:1") == 50
    with pytest.raises(StoreError):
        store.read("eqa:events:1", after="not-an-id")


def _writer(path: str, n: int) -> None:
    s = EmbeddedStore(Path(path))
    for i in range(n):
        s.append("eqa:shared", str(i).encode())
    s.close()


def test_embedded_store_is_shared_between_processes(tmp_path):
    path = tmp_path / "s.sqlite"
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_writer, args=(str(path), 100)) for _ in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    s = EmbeddedStore(path)
    rows = s.read("eqa:shared", count=1000)
    assert len(rows) == 300 and len({r[0] for r in rows}) == 300


def test_open_store_picks_backend(tmp_path, redis_url):
    assert isinstance(open_store(Settings(data_dir=tmp_path)), EmbeddedStore)
    assert isinstance(open_store(Settings(data_dir=tmp_path, redis_url=redis_url)), RedisStore)
    with pytest.raises(StoreError, match="EQA_REDIS_URL"):
        RedisStore("redis://127.0.0.1:1/0")
