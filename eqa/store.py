"""State store: one interface, a Redis backend and an embedded (SQLite file) backend.

Used for episode records, their event streams (append-only, resumable by id, like Redis Streams),
calibration tables and map snapshots. The embedded backend is a SQLite file under ``data_dir`` so that
separate service processes on one machine share it without any server; with ``EQA_REDIS_URL`` set every
process uses Redis instead. Values are bytes; :meth:`Store.get_json`/:meth:`Store.set_json` wrap JSON.

Stream ids have the Redis form ``<ms>-<seq>`` and increase strictly within a stream on both backends.
"""

from __future__ import annotations

import json
import logging
import re
import sqlite3
import threading
import time
from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, Any

from eqa import metrics
from eqa.settings import SettingsGroup

if TYPE_CHECKING:
    from eqa.messages import EpisodeEnd

log = logging.getLogger(__name__)

EPISODE_STATE_TTL_S = 2 * 24 * 3600.0
"""How long a service keeps the stored state of an episode nobody ends (services resume from it)."""


def episode_end_key(episode_id: str) -> str:
    """Where the stopper stores the ``EpisodeEnd`` of an episode before publishing it: the gateway reconciles
    from it after a restart, a restarted sim does not take up an episode that has one."""
    return f"eqa:stopper:end:{episode_id}"


def stored_end(store: Store, episode_id: str) -> EpisodeEnd | None:
    """The ``EpisodeEnd`` the stopper stored for ``episode_id`` (None when there is none, or it is unreadable:
    logged)."""
    from eqa.messages import EpisodeEnd

    raw = store.get(episode_end_key(episode_id))
    if raw is None:
        return None
    try:
        return EpisodeEnd.model_validate_json(raw)
    except ValueError as exc:
        log.warning("stored end of %s is unreadable: %s", episode_id, exc)
        return None


def task_metrics_key(episode_id: str) -> str:
    """Where the sim keeps a task episode's phase metrics (FindObj ... SR, collisions, pick attempts),
    rewritten after every step: the stopper puts them in the episode's ``EpisodeEnd.metrics``."""
    return f"eqa:sim:task:{episode_id}"


def episode_state_key(service: str, episode_id: str) -> str:
    """Where ``service`` keeps its state of a running episode (:class:`eqa.episode_service.EpisodeService`:
    one :mod:`eqa.codec` msgpack envelope), e.g. ``eqa:planner:episode:ep-1``."""
    return f"eqa:{service}:episode:{episode_id}"


def episode_part_key(service: str, episode_id: str, part: str) -> str:
    """Where a part of ``service``'s state of an episode lives when the state spans several keys
    (:class:`eqa.episode_service.StateParts`, e.g. the mapper's incremental snapshots), e.g.
    ``eqa:mapper:part:ep-1:d3``. Not under :func:`episode_state_key`'s prefix, which lists episodes."""
    return f"eqa:{service}:part:{episode_id}:{part}"


def episode_trace_key(episode_id: str) -> str:
    """Where the stopper keeps the per-step scores (trace) of an episode, rewritten after each step."""
    return f"eqa:trace:episode:{episode_id}"


def task_trace_key(episode_id: str) -> str:
    """Where the sim keeps the per-step trace of a task episode (phase, decision numbers, pose, collisions,
    skills, phase flags; :class:`services.sim.task_episode.TaskEpisode`), rewritten after each step."""
    return f"eqa:trace:task:{episode_id}"


def episode_journal_key(service: str, episode_id: str) -> str:
    """The stream where ``service`` journals a summary of every message it publishes for an episode, before
    publishing it (:mod:`eqa.event_log`): the gateway backfills its event log from these after a restart."""
    return f"eqa:journal:{service}:{episode_id}"


LABEL_PREFIX = "eqa:label:"


def episode_label_key(episode_id: str) -> str:
    """Where the gateway stores the ground truth a user gave for a finished episode (``EpisodeLabel``):
    ``eqa calibrate --from-store`` / ``--check --from-store`` read them with the episode's trace."""
    return f"{LABEL_PREFIX}{episode_id}"


class StoreError(RuntimeError):
    pass


class StoreUnavailable(StoreError):  # noqa: N818 (public API name)
    """The store cannot be reached right now (Redis down or frozen, SQLite locked): retry later."""


MAX_STREAM_PART = 2**63 - 1
"""Largest part of a stream id ``<ms>-<seq>`` both backends take (SQLite integers are signed 64-bit;
Redis takes up to 2**64-1)."""
_STREAM_ID = re.compile(r"([0-9]{1,19})-([0-9]{1,19})")  # ASCII digits only (\\d takes other scripts)


def parse_stream_id(entry_id: str) -> tuple[int, int]:
    """``(ms, seq)`` of a stream id ``<ms>-<seq>``: two decimal integers of at most 19 digits, each at most
    :data:`MAX_STREAM_PART`. Anything else raises ``ValueError`` saying what a valid id looks like (a
    Last-Event-ID of 20-digit parts would otherwise pass a loose pattern and fail the stream in the backend)."""
    m = _STREAM_ID.fullmatch(entry_id) if isinstance(entry_id, str) else None
    if m is None:
        raise ValueError(f"event id {str(entry_id)[:40]!r} must look like <ms>-<seq> (two integers), e.g. 0-0")
    ms, seq = int(m.group(1)), int(m.group(2))
    if ms > MAX_STREAM_PART or seq > MAX_STREAM_PART:
        raise ValueError(f"event id {entry_id!r} is out of range: each part is at most {MAX_STREAM_PART}")
    return ms, seq


def _id_tuple(entry_id: str) -> tuple[int, int]:
    try:
        return parse_stream_id(entry_id)
    except ValueError as exc:
        raise StoreError(str(exc)) from exc


class Store(ABC):
    """Key/value bytes with optional expiry, plus append-only streams."""

    @abstractmethod
    def get(self, key: str) -> bytes | None: ...

    @abstractmethod
    def set(self, key: str, value: bytes, ttl_s: float | None = None) -> None: ...

    @abstractmethod
    def delete(self, key: str) -> None: ...

    @abstractmethod
    def keys(self, prefix: str) -> list[str]: ...

    @abstractmethod
    def set_if_absent(self, key: str, value: bytes, ttl_s: float | None = None) -> bool:
        """Atomically set ``key`` if it does not exist; True when set (a lock)."""

    @abstractmethod
    def delete_if_equal(self, key: str, value: bytes) -> bool:
        """Atomically delete ``key`` if it holds ``value``; True when deleted (a lock released by its holder only:
        one whose lock expired and was taken by another deletes nothing)."""

    @abstractmethod
    def set_many_if(self, guard: str, expected: bytes | None, items: list[tuple[str, bytes]],
                    ttl_s: float | None = None, then_delete: list[str] | None = None) -> bool:
        """Compare-and-set over several keys: atomically, if ``guard`` holds ``expected`` (None: absent), set
        ``items`` and then delete ``then_delete``, and return True; otherwise change nothing and return False.
        ``items`` may set ``guard`` itself (a versioned index written with what it describes)."""

    @abstractmethod
    def append(self, stream: str, value: bytes, ttl_s: float | None = None) -> str:
        """Append to a stream; return the new entry id. ``ttl_s``: the stream expires that long after its last
        append (Redis; the embedded store keeps streams until they are deleted)."""

    @abstractmethod
    def read(self, stream: str, after: str = "0-0", count: int = 1000) -> list[tuple[str, bytes]]:
        """Entries with id strictly greater than ``after``, oldest first."""

    @abstractmethod
    def stream_len(self, stream: str) -> int: ...

    @abstractmethod
    def close(self) -> None: ...

    def ping(self) -> bool:
        return True

    # ---- many keys at once (one round trip on Redis) ---------------------------------------------------
    def get_many(self, keys: list[str]) -> list[bytes | None]:
        return [self.get(k) for k in keys]

    def delete_many(self, keys: list[str]) -> None:
        for k in keys:
            self.delete(k)

    def set_many(self, items: list[tuple[str, bytes]], ttl_s: float | None = None,
                 then_delete: list[str] | None = None) -> None:
        """Set ``items`` in their order, then delete ``then_delete``: what one write of several keys needs (a
        state whose parts must be stored before the envelope naming them, and the old parts removed after it).
        Redis sends it all in one pipeline: one round trip, executed in this order (not atomic: a failure part
        way leaves the earlier keys written, as the calls one by one would)."""
        for key, value in items:
            self.set(key, value, ttl_s)
        if then_delete:
            self.delete_many(then_delete)

    # ---- sorted indexes (Redis sorted sets): list and prune without scanning every key ------------------
    @abstractmethod
    def index_add(self, index: str, member: str, score: float) -> None:
        """Put ``member`` into ``index`` with ``score`` (replacing its score if present)."""

    @abstractmethod
    def index_remove(self, index: str, members: list[str]) -> None: ...

    @abstractmethod
    def index_page(self, index: str, limit: int, offset: int = 0, newest_first: bool = True) -> list[str]:
        """Up to ``limit`` members by score (highest first with ``newest_first``), skipping ``offset``."""

    @abstractmethod
    def index_below(self, index: str, score: float, limit: int) -> list[str]:
        """Up to ``limit`` members with a score below ``score``, lowest first."""

    @abstractmethod
    def index_len(self, index: str) -> int: ...

    # ---- JSON helpers -----------------------------------------------------------------------------------
    def get_json(self, key: str) -> Any:
        raw = self.get(key)
        return None if raw is None else json.loads(raw)

    def set_json(self, key: str, value: Any, ttl_s: float | None = None) -> None:
        self.set(key, json.dumps(value).encode(), ttl_s)

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@metrics.timed_store("redis")
class RedisStore(Store):
    def __init__(self, url: str, timeout_s: float = 10.0) -> None:
        """``timeout_s``: how long one call waits for a frozen server before it raises (a connection error
        :func:`unavailable_errors` lists)."""
        import redis

        self.url = url
        self._r = redis.Redis.from_url(url, socket_timeout=timeout_s, socket_connect_timeout=min(5.0, timeout_s))
        try:
            self._r.ping()
        except redis.RedisError as exc:
            raise StoreError(f"cannot reach Redis at {url}: {exc} (check EQA_REDIS_URL or unset it)") from exc

    def get(self, key: str) -> bytes | None:
        return self._r.get(key)

    def set(self, key: str, value: bytes, ttl_s: float | None = None) -> None:
        self._r.set(key, value, px=int(ttl_s * 1000) if ttl_s else None)

    def delete(self, key: str) -> None:
        self._r.delete(key)

    def keys(self, prefix: str) -> list[str]:
        return sorted(k.decode() for k in self._r.scan_iter(match=prefix.replace("*", r"\*") + "*", count=500))

    def set_if_absent(self, key: str, value: bytes, ttl_s: float | None = None) -> bool:
        return bool(self._r.set(key, value, nx=True, px=int(ttl_s * 1000) if ttl_s else None))

    # the holder's check and the delete in one step on the server (between a GET and a DEL of the client the
    # lock could expire and be taken by another)
    _DELETE_IF_EQUAL = "if redis.call('GET', KEYS[1]) == ARGV[1] then return redis.call('DEL', KEYS[1]) end return 0"

    def delete_if_equal(self, key: str, value: bytes) -> bool:
        return bool(self._r.eval(self._DELETE_IF_EQUAL, 1, key, value))

    def set_many_if(self, guard: str, expected: bytes | None, items: list[tuple[str, bytes]],
                    ttl_s: float | None = None, then_delete: list[str] | None = None) -> bool:
        import redis

        px = int(ttl_s * 1000) if ttl_s else None
        # WATCH / MULTI: the transaction is discarded when another client changed the guard after WATCH
        with self._r.pipeline(transaction=True) as pipe:
            try:
                pipe.watch(guard)
                if pipe.get(guard) != expected:
                    pipe.unwatch()
                    return False
                pipe.multi()
                for key, value in items:
                    pipe.set(key, value, px=px)
                if then_delete:
                    pipe.delete(*then_delete)
                pipe.execute()
                return True
            except redis.WatchError:
                return False

    def append(self, stream: str, value: bytes, ttl_s: float | None = None) -> str:
        if not ttl_s:
            return self._r.xadd(stream, {"v": value}).decode()
        pipe = self._r.pipeline(transaction=False)
        pipe.xadd(stream, {"v": value})
        pipe.pexpire(stream, int(ttl_s * 1000))
        entry, _ = pipe.execute()
        return entry.decode()

    def read(self, stream: str, after: str = "0-0", count: int = 1000) -> list[tuple[str, bytes]]:
        _id_tuple(after)
        rows = self._r.xrange(stream, min=f"({after}", max="+", count=count)
        return [(rid.decode(), fields[b"v"]) for rid, fields in rows]

    def stream_len(self, stream: str) -> int:
        return int(self._r.xlen(stream))

    def get_many(self, keys: list[str]) -> list[bytes | None]:
        return list(self._r.mget(keys)) if keys else []

    def delete_many(self, keys: list[str]) -> None:
        if keys:
            self._r.delete(*keys)

    def set_many(self, items: list[tuple[str, bytes]], ttl_s: float | None = None,
                 then_delete: list[str] | None = None) -> None:
        pipe = self._r.pipeline(transaction=False)
        px = int(ttl_s * 1000) if ttl_s else None
        for key, value in items:
            pipe.set(key, value, px=px)
        if then_delete:
            pipe.delete(*then_delete)
        pipe.execute()

    def index_add(self, index: str, member: str, score: float) -> None:
        self._r.zadd(index, {member: score})

    def index_remove(self, index: str, members: list[str]) -> None:
        if members:
            self._r.zrem(index, *members)

    def index_page(self, index: str, limit: int, offset: int = 0, newest_first: bool = True) -> list[str]:
        if limit <= 0:
            return []
        rows = self._r.zrange(index, offset, offset + limit - 1, desc=newest_first)
        return [m.decode() for m in rows]

    def index_below(self, index: str, score: float, limit: int) -> list[str]:
        rows = self._r.zrangebyscore(index, "-inf", f"({score!r}", start=0, num=limit)
        return [m.decode() for m in rows]

    def index_len(self, index: str) -> int:
        return int(self._r.zcard(index))

    def ping(self) -> bool:
        try:
            return bool(self._r.ping())
        except Exception:
            return False

    def close(self) -> None:
        self._r.close()


@metrics.timed_store("sqlite")
class EmbeddedStore(Store):
    """SQLite file store (WAL mode), safe across processes and threads of one machine."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        with self._conn() as c:
            c.execute("PRAGMA journal_mode=WAL")
            c.execute("CREATE TABLE IF NOT EXISTS kv (k TEXT PRIMARY KEY, v BLOB NOT NULL, exp REAL)")
            c.execute(
                "CREATE TABLE IF NOT EXISTS streams (s TEXT NOT NULL, ms INTEGER NOT NULL, seq INTEGER NOT NULL,"
                " v BLOB NOT NULL, PRIMARY KEY (s, ms, seq))"
            )
            c.execute(
                "CREATE TABLE IF NOT EXISTS idx (i TEXT NOT NULL, m TEXT NOT NULL, score REAL NOT NULL,"
                " PRIMARY KEY (i, m))"
            )
            c.execute("CREATE INDEX IF NOT EXISTS idx_by_score ON idx (i, score)")

    def _conn(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(self.path, timeout=30, isolation_level=None, check_same_thread=False)
            conn.execute("PRAGMA busy_timeout=30000")
            conn.execute("PRAGMA synchronous=NORMAL")
            self._local.conn = conn
        return conn

    def get(self, key: str) -> bytes | None:
        row = self._conn().execute("SELECT v, exp FROM kv WHERE k=?", (key,)).fetchone()
        if row is None or (row[1] is not None and row[1] < time.time()):
            return None
        return bytes(row[0])

    def set(self, key: str, value: bytes, ttl_s: float | None = None) -> None:
        exp = time.time() + ttl_s if ttl_s else None
        self._conn().execute("INSERT OR REPLACE INTO kv (k, v, exp) VALUES (?, ?, ?)", (key, value, exp))

    def keys(self, prefix: str) -> list[str]:
        """Keys of values, streams and indexes under ``prefix`` (as Redis lists every kind of key)."""
        now = time.time()
        n = len(prefix)
        rows = self._conn().execute(
            "SELECT k FROM kv WHERE substr(k, 1, ?) = ? AND (exp IS NULL OR exp >= ?)"
            " UNION SELECT DISTINCT s FROM streams WHERE substr(s, 1, ?) = ?"
            " UNION SELECT DISTINCT i FROM idx WHERE substr(i, 1, ?) = ? ORDER BY 1",
            (n, prefix, now, n, prefix, n, prefix),
        )
        return [r[0] for r in rows]

    def set_if_absent(self, key: str, value: bytes, ttl_s: float | None = None) -> bool:
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")
        try:
            if self.get(key) is not None:
                conn.execute("COMMIT")
                return False
            self.set(key, value, ttl_s)
            conn.execute("COMMIT")
            return True
        except Exception:
            conn.execute("ROLLBACK")
            raise

    def delete_if_equal(self, key: str, value: bytes) -> bool:
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")  # the write lock of the file: no other process between check and delete
        try:
            held = self.get(key) == value
            if held:
                conn.execute("DELETE FROM kv WHERE k=?", (key,))
            conn.execute("COMMIT")
            return held
        except Exception:
            conn.execute("ROLLBACK")
            raise

    def set_many_if(self, guard: str, expected: bytes | None, items: list[tuple[str, bytes]],
                    ttl_s: float | None = None, then_delete: list[str] | None = None) -> bool:
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")
        try:
            if self.get(guard) != expected:
                conn.execute("COMMIT")
                return False
            for key, value in items:
                self.set(key, value, ttl_s)
            for key in then_delete or []:
                self.delete(key)
            conn.execute("COMMIT")
            return True
        except Exception:
            conn.execute("ROLLBACK")
            raise

    def append(self, stream: str, value: bytes, ttl_s: float | None = None) -> str:
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")
        try:
            ms = int(time.time() * 1000)
            last = conn.execute(
                "SELECT ms, seq FROM streams WHERE s=? ORDER BY ms DESC, seq DESC LIMIT 1", (stream,)
            ).fetchone()
            seq = 0
            if last is not None and last[0] >= ms:
                ms, seq = last[0], last[1] + 1
            conn.execute("INSERT INTO streams (s, ms, seq, v) VALUES (?, ?, ?, ?)", (stream, ms, seq, value))
            conn.execute("COMMIT")
        except Exception:
            conn.execute("ROLLBACK")
            raise
        return f"{ms}-{seq}"

    def read(self, stream: str, after: str = "0-0", count: int = 1000) -> list[tuple[str, bytes]]:
        ms, seq = _id_tuple(after)
        rows = self._conn().execute(
            "SELECT ms, seq, v FROM streams WHERE s=? AND (ms > ? OR (ms = ? AND seq > ?))"
            " ORDER BY ms, seq LIMIT ?",
            (stream, ms, ms, seq, count),
        )
        return [(f"{r[0]}-{r[1]}", bytes(r[2])) for r in rows]

    def stream_len(self, stream: str) -> int:
        return int(self._conn().execute("SELECT COUNT(*) FROM streams WHERE s=?", (stream,)).fetchone()[0])

    def delete(self, key: str) -> None:
        conn = self._conn()
        conn.execute("DELETE FROM kv WHERE k=?", (key,))
        conn.execute("DELETE FROM streams WHERE s=?", (key,))  # streams and indexes are keys too (as on Redis)
        conn.execute("DELETE FROM idx WHERE i=?", (key,))

    def get_many(self, keys: list[str]) -> list[bytes | None]:
        found: dict[str, bytes] = {}
        now = time.time()
        for i in range(0, len(keys), 500):
            chunk = keys[i : i + 500]
            rows = self._conn().execute(
                f"SELECT k, v, exp FROM kv WHERE k IN ({','.join('?' * len(chunk))})", chunk
            )
            found.update({r[0]: bytes(r[1]) for r in rows if r[2] is None or r[2] >= now})
        return [found.get(k) for k in keys]

    def index_add(self, index: str, member: str, score: float) -> None:
        self._conn().execute("INSERT OR REPLACE INTO idx (i, m, score) VALUES (?, ?, ?)", (index, member, score))

    def index_remove(self, index: str, members: list[str]) -> None:
        conn = self._conn()
        for m in members:
            conn.execute("DELETE FROM idx WHERE i=? AND m=?", (index, m))

    def index_page(self, index: str, limit: int, offset: int = 0, newest_first: bool = True) -> list[str]:
        order = "DESC" if newest_first else "ASC"
        rows = self._conn().execute(
            f"SELECT m FROM idx WHERE i=? ORDER BY score {order}, m {order} LIMIT ? OFFSET ?",
            (index, max(0, limit), max(0, offset)),
        )
        return [r[0] for r in rows]

    def index_below(self, index: str, score: float, limit: int) -> list[str]:
        rows = self._conn().execute(
            "SELECT m FROM idx WHERE i=? AND score < ? ORDER BY score, m LIMIT ?", (index, score, limit)
        )
        return [r[0] for r in rows]

    def index_len(self, index: str) -> int:
        return int(self._conn().execute("SELECT COUNT(*) FROM idx WHERE i=?", (index,)).fetchone()[0])

    def close(self) -> None:
        conn = getattr(self._local, "conn", None)
        if conn is not None:
            conn.close()
            self._local.conn = None


def unavailable_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean "the store cannot be reached now, retry later" (what a server answers with 503):
    :class:`StoreUnavailable`, Redis connection and timeout errors, a locked or unreadable SQLite file."""
    found: list[type[BaseException]] = [StoreUnavailable, sqlite3.OperationalError]
    try:
        import redis

        found += [redis.exceptions.ConnectionError, redis.exceptions.TimeoutError, redis.exceptions.BusyLoadingError]
    except ImportError:  # pragma: no cover - redis is a dependency
        pass
    return tuple(found)


def open_store(settings: SettingsGroup, timeout_s: float = 10.0) -> Store:
    """Redis when ``EQA_REDIS_URL`` is set, else the embedded store under ``data_dir``; ``timeout_s`` bounds
    one Redis call (a server that answers HTTP requests uses less, to answer 503 soon when Redis freezes)."""
    if settings.redis_url:
        return RedisStore(settings.redis_url, timeout_s=timeout_s)
    return EmbeddedStore(settings.data_dir / "store.sqlite")
