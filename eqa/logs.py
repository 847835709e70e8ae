"""Log records that can be joined across processes and hosts: JSON lines and the episode context.

``EQA_LOG_FORMAT=json`` makes :func:`eqa.service.setup_logging` write one JSON object per line::

    {"time": "2026-12-02T03:04:05.123Z", "level": "INFO", "logger": "services.mapper.service",
     "message": "...", "service": "mapper", "instance": "mapper-0-...", "episode": "ep-1", "robot": "robot0",
     "step": 3}

``service``, ``instance``, ``episode``, ``robot`` and ``step`` come from context variables (:data:`CONTEXT`):
the process sets ``service``/``instance`` once (:func:`set_process`), and the service shell sets the episode,
robot and step of the message its worker is handling (:func:`bind`, :func:`message_context`) for the time the
handler runs; a key is absent when it is not known. A record with an exception carries ``exc`` (the
traceback as text). The text format (the default) shows the same context as ``[episode robot step]``.
"""

from __future__ import annotations

import contextvars
import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

FIELDS = ("service", "instance", "episode", "robot", "step")
CONTEXT: contextvars.ContextVar[dict[str, Any]] = contextvars.ContextVar("eqa_log_context", default={})  # noqa: B039 - never mutated
_PROCESS: dict[str, Any] = {}


def set_process(**fields: Any) -> None:
    """Fields every record of this process carries unless a context overrides them (service, instance)."""
    _PROCESS.update({k: v for k, v in fields.items() if v is not None})


def current() -> dict[str, Any]:
    """The context of the calling thread/task, over the process fields."""
    ctx = CONTEXT.get()
    return {**_PROCESS, **ctx} if ctx else dict(_PROCESS)


@contextmanager
def bind(**fields: Any) -> Iterator[None]:
    """Add ``fields`` (None values skipped) to the log context for the ``with`` block."""
    new = {k: v for k, v in fields.items() if v is not None}
    if not new:
        yield
        return
    token = CONTEXT.set({**CONTEXT.get(), **new})
    try:
        yield
    finally:
        CONTEXT.reset(token)


def message_context(args: tuple[Any, ...]) -> dict[str, Any]:
    """Episode, robot and step of a worker item's arguments ``(robot, message, ...)``; empty when they are not
    a robot and a message."""
    if len(args) < 2 or not isinstance(args[0], str):
        return {}
    msg = args[1]
    episode = getattr(msg, "episode_id", None)
    if episode is None:
        return {}
    step = getattr(msg, "step", None)
    return {"robot": args[0], "episode": episode, "step": step if isinstance(step, int) else None}


class ContextFilter(logging.Filter):
    """Puts the context fields on every record (attributes ``service``, ``episode``, ...; None when unknown)."""

    def filter(self, record: logging.LogRecord) -> bool:
        ctx = current()
        for name in FIELDS:
            if not hasattr(record, name):
                setattr(record, name, ctx.get(name))
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per record: time (UTC, ISO 8601, ms), level, logger, message, the context fields that
    are known, ``exc`` when an exception is attached."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for name in FIELDS:
            value = getattr(record, name, None)
            if value is not None:
                out[name] = value
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exc"] = record.exc_text
        return json.dumps(out, ensure_ascii=False, default=str)


class TextFormatter(logging.Formatter):
    """The human format, with ``[episode robot step]`` after the logger when a message is being handled."""

    def __init__(self, service: str) -> None:
        super().__init__(f"%(asctime)s %(levelname)s {service} %(name)s%(where)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        episode = getattr(record, "episode", None)
        if episode is None:
            record.where = ""
        else:
            step = getattr(record, "step", None)
            record.where = f" [{episode} {getattr(record, 'robot', None) or '-'} {'-' if step is None else step}]"
        return super().format(record)


def handler(stream: Any, service: str, fmt: str = "text") -> logging.Handler:
    """A stream handler with the context filter and the formatter of ``fmt`` (``text`` or ``json``)."""
    if fmt not in ("text", "json"):
        raise ValueError(f"log format {fmt!r}: use text or json (EQA_LOG_FORMAT)")
    out = logging.StreamHandler(stream)
    out.addFilter(ContextFilter())
    out.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter(service))
    return out
