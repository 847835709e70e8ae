"""A thin, typed wrapper over one real Zenoh session.

* ``publish`` / ``subscribe`` carry :class:`eqa.messages.Message` objects; a payload that does not decode
  into the expected type is logged and dropped, a handler that raises is logged, and the subscriber keeps
  running either way.
* ``declare_queryable`` / ``query`` carry request/reply messages (the scorer pool).
* ``declare_alive`` holds the liveliness token ``eqa/v1/alive/{service}/{instance}/{session}``; ``alive``
  lists the instances present; ``watch_alive`` reports each process that appears under an instance name and
  the instance's disappearance when its last process is gone.

Callbacks run on Zenoh threads. Services hand work to their own worker (``eqa.service``); the gateway hands
it to asyncio with ``loop.call_soon_threadsafe``.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from eqa import keys, metrics, security
from eqa.codec import CodecError
from eqa.messages import ErrorReply, M, Message, decode, encode
from eqa.settings import BusSettings, SettingsGroup

log = logging.getLogger(__name__)

Handler = Callable[[str, Any], None]


class BusError(RuntimeError):
    """The session could not be opened (nothing listens there, or it refused this node's credentials)."""


def zenoh_config(settings: BusSettings) -> zenoh.Config:
    """Zenoh configuration from settings: mode, listen/connect endpoints, multicast scouting, and the bus
    security of :mod:`eqa.security` when configured."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.zenoh_mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(settings.zenoh_multicast)))
    if settings.zenoh_listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(settings.zenoh_listen)))
    if settings.zenoh_connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(settings.zenoh_connect)))
    security.apply(conf, settings)  # TLS, user/password, ACL: nothing unless EQA_ZENOH_TLS_*/USER/ACL are set
    return conf


class _SerialQueryable:
    """A queryable whose queries one worker thread answers in order (``Bus.declare_queryable(serial=True)``).

    With ``batch_max > 1`` the worker answers them in batches: it takes the first waiting query, then every
    query already queued, then (``window_s > 0``) waits up to ``window_s`` after the first for more while the
    batch holds fewer than were in flight when the previous batch was answered (see :meth:`_batch`), up to
    ``batch_max`` in all, and hands the batch to ``answer`` as one list. With ``window_s = 0`` a batch holds what
    queued while the previous one was served, so a lone request never waits for batch mates."""

    _STOP = object()

    def __init__(self, key: str, answer: Callable[[Any], None], batch_max: int = 1, window_s: float = 0.0,
                 service: str = "") -> None:
        self.jobs: queue.Queue[Any] = queue.Queue()
        self.service = service
        self.queryable: Any = None
        self._answer = answer
        self.batch_max = max(1, int(batch_max))
        self.window_s = max(0.0, float(window_s))
        self.in_flight = 1  # queries in flight when the last batch was answered (see _batch)
        self._thread = threading.Thread(target=self._serve, name=f"queryable {key}", daemon=True)
        self._thread.start()

    def _batch(self, first: Any) -> tuple[list[Any], bool]:
        """``first`` and the queries that join it; True when the stop marker was met. Every query already queued
        joins (up to ``batch_max``); with a window the batch waits for more only while it holds fewer than were
        in flight when the previous batch was answered (that batch and the queries queued behind it): robots
        that each wait for their reply before sending again come back one by one as their replies go out, and
        without the wait the first back would be served alone, the rest queue behind it, and the batches split
        into small ones that share little; a lone robot's request waits for no one."""
        batch = [first]
        deadline = time.monotonic() + self.window_s
        while len(batch) < self.batch_max:
            try:
                query = self.jobs.get_nowait()
            except queue.Empty:
                wait = deadline - time.monotonic()
                if wait <= 0 or len(batch) >= self.in_flight:
                    break
                try:
                    query = self.jobs.get(timeout=wait)
                except queue.Empty:
                    break
            if query is self._STOP:
                return batch, True
            batch.append(query)
        return batch, False

    def _serve(self) -> None:
        while True:
            query = self.jobs.get()
            if query is self._STOP:
                return
            if self.batch_max == 1:
                batch, stop = [query], False
            else:
                batch, stop = self._batch(query)
            metrics.gauge_add(metrics.QUEUE_DEPTH, self.service, amount=-len(batch))
            try:
                self._answer(batch if self.batch_max > 1 else query)
            except Exception:
                log.exception("could not answer a query; going on")
            finally:
                # finalise now (sends the end-of-replies marker) rather than whenever the object is collected: a
                # logged exception's traceback may keep it alive, and the client would wait for its timeout
                for q in batch:
                    q.drop()
                self.in_flight = len(batch) + self.jobs.qsize()
            if stop:
                return

    def put(self, query: Any) -> None:
        """Queue a query (the Zenoh callback)."""
        metrics.gauge_add(metrics.QUEUE_DEPTH, self.service)
        self.jobs.put(query)

    def undeclare(self) -> None:
        if self.queryable is not None:
            queryable, self.queryable = self.queryable, None
            try:
                queryable.undeclare()
            finally:
                self.jobs.put(self._STOP)
                self._thread.join(timeout=30)


class Bus:
    """One Zenoh session of one service instance. Use as a context manager."""

    def __init__(self, settings: SettingsGroup, service: str, instance: str | None = None) -> None:
        self.settings = settings
        self.service = keys.check_id(service, "service")
        self.instance = keys.check_id(instance or settings.instance, "instance")
        self._session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self._lock = threading.Lock()

    # ---- lifecycle ------------------------------------------------------------------------------------
    def open(self) -> Bus:
        if self._session is None:
            conf = zenoh_config(self.settings)
            try:
                self._session = zenoh.open(conf)
            except zenoh.ZError as exc:
                s = self.settings
                hint = (" (a secured fleet also needs this node's EQA_ZENOH_TLS_CA/CERT/KEY and "
                        "EQA_ZENOH_USER/PASSWORD: docs/deployment.md, Scaling out)")
                raise BusError(
                    f"could not open a Zenoh {s.zenoh_mode} session connecting to "
                    f"{', '.join(s.zenoh_connect) or 'nothing'}: {exc}; check EQA_ZENOH_CONNECT{hint}"
                ) from exc
            if self.settings.zenoh_connect and self.settings.bus_link_wait_s > 0:
                self.wait_linked(self.settings.bus_link_wait_s)
        return self

    def linked(self) -> bool:
        """Whether the session has a link to at least one router or peer."""
        info = self.session.info
        return bool(list(info.routers_zid()) or list(info.peers_zid()))

    def wait_linked(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the first link. A peer session returns from ``zenoh.open`` before its
        connect endpoints have finished their handshake; until then a liveliness query answers "nobody" at
        once (a sharded instance would take every robot) and publications reach no one. Without a link after
        ``timeout`` the session goes on (Zenoh keeps retrying) and a warning says so."""
        deadline = time.monotonic() + timeout
        while not self.linked():
            if time.monotonic() >= deadline:
                log.warning("%s/%s: no link to %s after %g s; going on (Zenoh keeps trying)", self.service,
                            self.instance, ", ".join(self.settings.zenoh_connect), timeout)
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        with self._lock:
            entities, self._entities = self._entities, []
        for ent in reversed(entities):
            try:
                ent.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> Bus:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("bus is not open")
        return self._session

    def _keep(self, entity: Any) -> Any:
        with self._lock:
            self._entities.append(entity)
        return entity

    # ---- pub/sub --------------------------------------------------------------------------------------
    def publish(self, key: str, msg: Message) -> None:
        """Publish reliably: the pipeline is a choreography in which a lost message stalls an episode, so
        puts block on congestion instead of being dropped (Zenoh's default for data is to drop)."""
        self.session.put(key, encode(msg), congestion_control=zenoh.CongestionControl.BLOCK)

    def publish_raw(self, key: str, payload: bytes) -> None:
        """Publish bytes as they are (tests use it to send garbage)."""
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def subscribe(self, key: str, expected: type[M] | tuple[type[M], ...], handler: Handler,
                  on_invalid: Callable[[str, bytes, str], None] | None = None,
                  accept: Callable[[str], bool] | None = None) -> Any:
        """Call ``handler(key, message)`` for each well-formed message on ``key``; log and drop the rest
        (after ``on_invalid(key, payload, reason)`` when given: a service answers the episode at once).
        ``accept(key)``, when given, is asked first: a sample it refuses is dropped without being decoded (an
        instance skips the frames of robots another instance owns)."""

        def on_sample(sample: zenoh.Sample) -> None:
            skey = str(sample.key_expr)
            if accept is not None and not accept(skey):
                return
            payload = sample.payload.to_bytes()
            try:
                msg = decode(payload, expected)
            except CodecError as exc:
                log.warning("dropped malformed message on %s: %s", skey, exc)
                metrics.inc(metrics.BUS_DROPPED, self.service, "malformed")
                if on_invalid is not None:
                    try:
                        on_invalid(skey, payload, str(exc))
                    except Exception:
                        log.exception("invalid-message callback for %s failed", skey)
                return
            try:
                handler(skey, msg)
            except Exception:
                log.exception("handler for %s failed; going on", skey)
                metrics.inc(metrics.BUS_DROPPED, self.service, "handler_error")

        return self._keep(self.session.declare_subscriber(key, on_sample))

    # ---- queries --------------------------------------------------------------------------------------
    def declare_queryable(
        self, key: str, expected: type[M] | tuple[type[M], ...], handler: Callable[[M], Message],
        serial: bool = False, *, batch_handler: Callable[[list[M]], list[Message]] | None = None,
        batch_max: int = 1, batch_window_s: float = 0.0,
    ) -> Any:
        """Answer each query on ``key`` with ``handler(request)``; malformed requests and handler errors are
        answered with :class:`ErrorReply` carrying the reason, and the queryable keeps serving.

        ``serial``: the Zenoh callback only queues the query and one worker thread of this queryable answers
        them in arrival order (a slow handler, e.g. a VLM, never holds a Zenoh thread). The returned object's
        ``undeclare()`` stops serving (the query in hand is answered first); :meth:`close` does it too.

        ``batch_handler`` with ``batch_max > 1`` (serial only): the worker hands the well-formed requests of a
        batch (see :class:`_SerialQueryable`) to ``batch_handler``, which answers each, in order; a malformed
        query of the batch is answered with its error alone, and a ``batch_handler`` that raises answers
        every request of the batch with the error."""

        def source() -> str:
            return f"{self.service}/{self.instance}"

        def decoded(query: zenoh.Query) -> tuple[Any, Message | None]:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                return decode(payload, expected), None
            except CodecError as exc:
                log.warning("malformed query on %s: %s", query.key_expr, exc)
                metrics.inc(metrics.BUS_DROPPED, self.service, "malformed_query")
                return None, ErrorReply(source=source(), reason=str(exc))

        def failed(request: Any, exc: Exception) -> ErrorReply:
            return ErrorReply(source=source(), reason=f"{type(exc).__name__}: {exc}",
                              request_id=getattr(request, "request_id", None))

        def send(query: zenoh.Query, reply: Message) -> None:
            try:
                query.reply(key, encode(reply))
            except Exception:
                log.exception("could not reply on %s", query.key_expr)

        def on_query(query: zenoh.Query) -> None:
            request, reply = decoded(query)
            if reply is None:
                try:
                    reply = handler(request)
                except Exception as exc:
                    log.exception("query handler on %s failed", query.key_expr)
                    reply = failed(request, exc)
            send(query, reply)

        def on_batch(queries: list[zenoh.Query]) -> None:
            good: list[tuple[zenoh.Query, Any]] = []
            for query in queries:
                request, error = decoded(query)
                if error is not None:
                    send(query, error)
                else:
                    good.append((query, request))
            if not good:
                return
            assert batch_handler is not None
            try:
                replies = batch_handler([r for _, r in good])
                if len(replies) != len(good):
                    raise RuntimeError(f"batch handler answered {len(replies)} of {len(good)} requests")
            except Exception as exc:
                log.exception("batch handler on %s failed", key)
                replies = [failed(r, exc) for _, r in good]
            for (query, _), reply in zip(good, replies, strict=True):
                send(query, reply)

        if not serial:
            return self._keep(self.session.declare_queryable(key, on_query))
        if batch_handler is not None and batch_max > 1:
            server = _SerialQueryable(key, on_batch, batch_max=batch_max, window_s=batch_window_s,
                                      service=self.service)
        else:
            server = _SerialQueryable(key, on_query, service=self.service)
        server.queryable = self.session.declare_queryable(key, server.put)
        return self._keep(server)

    def query(self, key: str, msg: Message, timeout: float, expected: type[M] | tuple[type[M], ...] | None = None
              ) -> list[tuple[str, Message]]:
        """Send ``msg`` to every queryable matching ``key``; return ``(replier key, reply)`` pairs.
        Malformed replies are logged and skipped; an :class:`ErrorReply` is returned as it is."""
        out: list[tuple[str, Message]] = []
        replies = self.session.get(key, payload=encode(msg), timeout=timeout)
        for reply in replies:
            if reply.ok is None:
                log.warning("query %s: error reply %s", key, reply.err.payload.to_bytes()[:200] if reply.err else "")
                continue
            try:
                allowed = ((expected,) if not isinstance(expected, tuple) else expected) if expected else None
                decoded = decode(reply.ok.payload.to_bytes(), None)
                if allowed is not None and not isinstance(decoded, (*allowed, ErrorReply)):
                    raise CodecError(f"unexpected reply kind {decoded.kind}")
            except CodecError as exc:
                log.warning("malformed reply on %s: %s", reply.ok.key_expr, exc)
                metrics.inc(metrics.BUS_DROPPED, self.service, "malformed_reply")
                continue
            out.append((str(reply.ok.key_expr), decoded))
        return out

    # ---- liveliness -----------------------------------------------------------------------------------
    def declare_alive(self) -> Any:
        session = str(self.session.zid())
        return self._keep(self.session.liveliness().declare_token(keys.alive(self.service, self.instance, session)))

    def alive(self, selector: str = keys.ALIVE_ANY, timeout: float = 1.0) -> list[tuple[str, str]]:
        """``(service, instance)`` of every liveliness token matching ``selector`` (one row per instance, however
        many processes hold a token under its name)."""
        found = []
        for reply in self.session.liveliness().get(selector, timeout=timeout):
            if reply.ok is not None:
                try:
                    found.append(keys.parse_alive(str(reply.ok.key_expr))[:2])
                except ValueError:
                    continue
        return sorted(set(found))

    def watch_alive(self, selector: str, callback: Callable[[str, str, bool], None]) -> Any:
        """``callback(service, instance, alive)`` for tokens already present and for each change.

        ``alive`` is True for every process that appears, so an instance restarted while its predecessor's
        token is still routed is reported up a second time (its state is new: whatever was in flight to the old
        process is lost), and False only once no process holds a token under that name. Calls are made one at
        a time, in the order of the changes."""
        sessions: dict[tuple[str, str], set[str]] = {}
        lock = threading.Lock()

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                service, instance, session = keys.parse_alive(str(sample.key_expr))
            except ValueError:
                log.warning("ignoring liveliness key %s", sample.key_expr)
                return
            up = sample.kind == zenoh.SampleKind.PUT
            with lock:  # held across the callback so that a later change is never reported before this one
                if up:
                    held = sessions.setdefault((service, instance), set())
                    if session in held:
                        return
                    held.add(session)
                else:
                    held = sessions.get((service, instance), set())
                    if session not in held:
                        return
                    held.discard(session)
                    if held:
                        return
                    del sessions[(service, instance)]
                try:
                    callback(service, instance, up)
                except Exception:
                    log.exception("liveliness callback failed")

        return self._keep(self.session.liveliness().declare_subscriber(selector, on_sample, history=True))
