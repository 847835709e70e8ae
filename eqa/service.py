"""The shell every service shares: a bus, a store, a liveliness token and one ordered worker.

A service subclasses :class:`Service`, names itself, and in :meth:`Service.setup` declares handlers with
:meth:`Service.on` for the streams it consumes (over all robots). Zenoh delivers on its own threads; the
shell decodes there (malformed payloads are logged and dropped) and queues the message, and one worker
thread runs the handlers in arrival order, so service code needs no locks. A handler that raises is logged
and the service goes on.

``python -m services.<name>`` calls :func:`main` with the service class.
"""

from __future__ import annotations

import argparse
import logging
import os
import queue
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, ClassVar

from eqa import keys, logs, metrics, standby
from eqa.bus import Bus
from eqa.event_log import encode_event, summarize
from eqa.messages import STREAM_TYPES, Message
from eqa.settings import (
    BusSettings,
    Groups,
    MonitoringSettings,
    ProcessSettings,
    Settings,
    SettingsGroup,
    SettingsView,
    StoreSettings,
    view,
)
from eqa.store import EPISODE_STATE_TTL_S, Store, episode_journal_key, open_store

log = logging.getLogger(__name__)

_STOP = object()

# what the shell itself reads: its process, bus and store, and its recordings and metrics
SHELL_GROUPS: Groups = (ProcessSettings, BusSettings, StoreSettings, MonitoringSettings)


def setup_logging(level: str = "INFO", service: str = "eqa", fmt: str = "text", instance: str | None = None) -> None:
    """Log to stderr at ``level``; ``fmt`` ``json``: one JSON object per line with the episode context
    (:mod:`eqa.logs`, ``EQA_LOG_FORMAT``)."""
    logs.set_process(service=service, instance=instance)
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        handlers=[logs.handler(sys.stderr, service, fmt)],
        force=True,
    )


class Service:
    """Base of the service shells. Subclasses set ``name`` and implement :meth:`setup`."""

    name: str = "service"
    description: str = ""
    # the settings groups this service reads (the shell's and its own): it keeps only those (eqa.settings.view)
    settings_groups: ClassVar[Groups] = SHELL_GROUPS

    def __init__(self, settings: SettingsGroup, bus: Bus | None = None, store: Store | None = None) -> None:
        self.settings: SettingsView = view(settings, self.settings_groups)
        self.bus = bus or Bus(self.settings, self.name)
        self._store = store
        self._queue: queue.Queue[Any] = queue.Queue()
        self._stopped = threading.Event()
        self._worker: threading.Thread | None = None

    @property
    def store(self) -> Store:
        if self._store is None:
            self._store = open_store(self.settings)
        return self._store

    # ---- for subclasses ---------------------------------------------------------------------------------
    @classmethod
    def warm_up(cls) -> None:
        """Work a warm standby (:mod:`eqa.standby`) does before it is needed, off the bus: imports or compiled
        code a first step would otherwise load. Runs without settings, store or bus."""

    def setup(self) -> None:
        """Declare subscriptions / queryables. Called once the bus is open."""

    def teardown(self) -> None:
        """Release resources. Called once after the worker stopped."""

    def on(self, pair: tuple[str, str], handler: Callable[[str, Any], None],
           on_invalid: Callable[[str, bytes, str], None] | None = None, prefilter: bool = False) -> None:
        """Run ``handler(robot, message)`` on the worker for every message of stream ``pair`` of any robot;
        ``on_invalid(robot, payload, reason)`` on the worker for each payload that does not validate.
        ``prefilter``: messages of robots :meth:`wants` refuses are dropped before they are decoded."""
        expected = STREAM_TYPES[pair]

        def enqueue(key: str, msg: Message) -> None:
            self._queue.put((handler, keys.robot_of(key), msg))

        def enqueue_invalid(key: str, payload: bytes, reason: str) -> None:
            if on_invalid is not None:
                self._queue.put((on_invalid, keys.robot_of(key), payload, reason))

        accept = (lambda key: self.wants(keys.robot_of(key))) if prefilter else None
        self.bus.subscribe(keys.any_robot(pair), expected, enqueue, enqueue_invalid if on_invalid else None,
                           accept=accept)

    def wants(self, robot: str) -> bool:
        """Whether messages of ``robot`` are worth decoding here (sharded services: their robots). Runs on Zenoh
        threads."""
        return True

    def submit(self, fn: Callable[..., None], *args: Any) -> None:
        """Run ``fn(*args)`` on the worker (after what is already queued)."""
        self._queue.put((fn, *args))

    def every(self, period_s: float, fn: Callable[[], None]) -> None:
        """Run ``fn()`` on the worker every ``period_s`` seconds until the service stops."""

        def tick() -> None:
            while not self._stopped.wait(period_s):
                self.submit(fn)

        threading.Thread(target=tick, name=f"{self.name}-every-{period_s:g}s", daemon=True).start()

    journal: bool = True  # journal what is published for an episode (eqa.event_log), before publishing it

    def publish(self, robot: str, pair: tuple[str, str], msg: Message) -> None:
        """Journal the message's summary in the store (the episode's event log holds it whatever process dies
        next: :mod:`eqa.event_log`), then publish it. A store that fails is logged; the message goes out."""
        episode_id = getattr(msg, "episode_id", None)
        if self.journal and isinstance(episode_id, str):
            try:
                self.store.append(episode_journal_key(self.name, episode_id), encode_event(summarize(msg)),
                                  ttl_s=EPISODE_STATE_TTL_S)
            except Exception as exc:
                log.warning("%s: journal of episode %s not written (%s: %s); publishing anyway", self.name,
                            episode_id, type(exc).__name__, exc)
        self.bus.publish(keys.stream(robot, pair), msg)

    # ---- lifecycle --------------------------------------------------------------------------------------
    def start(self) -> None:
        """Open the bus, declare handlers and the liveliness token, start the worker (non-blocking)."""
        self.bus.open()
        self.setup()
        self._worker = threading.Thread(target=self._work, name=f"{self.name}-worker", daemon=True)
        self._worker.start()
        self.bus.declare_alive()
        log.info("%s %s up", self.name, self.bus.instance)

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            fn, *args = item
            token = logs.CONTEXT.set({"service": self.name, **logs.message_context(args)})
            try:
                fn(*args)
            except Exception:
                log.exception("%s: handler %s failed; going on", self.name, getattr(fn, "__name__", fn))
            finally:
                logs.CONTEXT.reset(token)

    @property
    def stopped(self) -> bool:
        """Whether :meth:`stop` has been called."""
        return self._stopped.is_set()

    def stop(self) -> None:
        if self._stopped.is_set():
            return
        self._stopped.set()
        self._queue.put(_STOP)
        if self._worker is not None:
            self._worker.join(timeout=10)
        try:
            self.teardown()
        finally:
            self.bus.close()
            if self._store is not None:
                self._store.close()
        log.info("%s stopped", self.name)

    def drain(self, timeout: float = 10.0) -> bool:
        """Wait until the worker has handled everything queued so far (tests)."""
        done = threading.Event()
        self.submit(done.set)
        return done.wait(timeout)

    def run_forever(self) -> None:
        """Start, then block until SIGINT/SIGTERM."""
        stop = threading.Event()

        def on_signal(signum: int, _frame: Any) -> None:
            log.info("%s: signal %d, stopping", self.name, signum)
            stop.set()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
        self.start()
        try:
            while not stop.wait(0.5):
                if self._worker is not None and not self._worker.is_alive():
                    raise RuntimeError(f"{self.name} worker died")
                if self.settings.parent_pid and os.getppid() != self.settings.parent_pid:
                    log.warning("%s: launcher (pid %d) is gone; stopping", self.name, self.settings.parent_pid)
                    break
        finally:
            self.stop()


def main(service_cls: type[Service], argv: list[str] | None = None) -> int:
    """Entry point of ``python -m services.<name>``: settings from ``EQA_*`` variables."""
    parser = argparse.ArgumentParser(
        prog=f"python -m services.{service_cls.name}",
        description=(service_cls.description or service_cls.__doc__ or "").strip()
        + "\n\nConfigured by EQA_* environment variables (see eqa/settings.py); runs until SIGTERM/SIGINT.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--log-level", default=None, help="override EQA_LOG_LEVEL")
    parser.add_argument("--standby", type=int, default=None, metavar="FD",
                        help="start as a warm standby (eqa.standby): warm up, write 'ready' to the pipe FD, then "
                        "wait off the bus for the launcher's promotion on standard input")
    args = parser.parse_args(argv)
    try:
        settings = Settings()
    except Exception as exc:
        print(f"error: invalid EQA_* settings: {exc}", file=sys.stderr)
        return 2
    if args.standby is not None:
        setup_logging(args.log_level or settings.log_level, service_cls.name, settings.log_format, "standby")
        if standby.await_promotion(args.standby, service_cls.name, service_cls.warm_up) is None:
            return 0
        try:
            settings = Settings()  # the environment of the instance this process now is
        except Exception as exc:
            print(f"error: invalid EQA_* settings: {exc}", file=sys.stderr)
            return 2
    setup_logging(args.log_level or settings.log_level, service_cls.name, settings.log_format, settings.instance)
    try:
        metrics.serve(settings, service_cls.name)
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    service_cls(settings).run_forever()
    return 0
