"""Warm standby processes: a service process that has done its imports and waits, off the bus, to replace a
dead instance of its service.

With one process per service, a killed process's robots have no other owner, and a freshly started Python
process spends seconds on its imports (torch, open3d, numba) before it holds its liveliness token. The launcher
(:mod:`eqa.launcher`, ``EQA_STANDBY``) therefore keeps one standby per service: ``python -m services.<name>
--standby FD``. The standby imports the service's modules (``python -m`` does that before :func:`await_promotion`
runs), runs the service class's :meth:`eqa.service.Service.warm_up`, writes :data:`READY` to the pipe ``FD``
and blocks on its standard input. It opens no Zenoh session and no store, declares no liveliness token and
subscribes to nothing, so it cannot take or compute any step.

Once the active process is dead (the launcher has reaped its pid and seen its liveliness token go), the
launcher writes one JSON line (:class:`Promotion`) to the standby's standard input: the environment of the
instance it replaces (``EQA_INSTANCE``, its metrics port, ...) and that instance's log file. The standby takes
them and goes on as that instance would after a restart: it opens the bus and the store, restores its episodes
from the store and declares its token (the re-drive of :mod:`eqa.sharding` sends the waiting step again). An
end of file instead (the launcher is gone) ends the standby.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path
from typing import IO

from pydantic import BaseModel, ConfigDict, Field, field_validator

log = logging.getLogger(__name__)

READY = b"ready\n"
MAX_LINE = 256 * 1024  # the promotion line: an environment of a few hundred variables
MAX_VARS = 1000


class Promotion(BaseModel):
    """What the launcher hands a standby that takes a dead instance's place."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    env: dict[str, str] = Field(description="environment variables of the instance replaced (set over the standby's)")
    unset: list[str] = Field(default_factory=list, max_length=MAX_VARS,
                             description="variables the standby has and the instance replaced had not")
    log_path: Path | None = Field(default=None, description="the replaced instance's log file (appended to)")

    @field_validator("env")
    @classmethod
    def _bounded(cls, v: dict[str, str]) -> dict[str, str]:
        if len(v) > MAX_VARS:
            raise ValueError(f"at most {MAX_VARS} variables")
        bad = [k for k in v if not k or "=" in k or "\0" in k or "\0" in v[k]]
        if bad:
            raise ValueError(f"invalid variable names or values: {bad[:3]}")
        return v

    def encode(self) -> bytes:
        return self.model_dump_json().encode() + b"\n"


def await_promotion(ready_fd: int, service: str, warm_up: object = None,
                    stdin: IO[bytes] | None = None) -> Promotion | None:
    """Run ``warm_up()`` (when callable), tell the launcher through ``ready_fd`` that this standby is ready,
    then wait for the promotion on standard input and apply it (environment, log file). None: the launcher
    closed the pipe without promoting this process (it stopped); the caller exits."""
    t0 = time.monotonic()
    if callable(warm_up):
        warm_up()
    try:
        os.write(ready_fd, READY)
    finally:
        os.close(ready_fd)
    log.info("standby for %s (pid %d): ready (warm-up %.2f s), waiting off the bus for a promotion", service,
             os.getpid(), time.monotonic() - t0)
    line = (stdin or sys.stdin.buffer).readline(MAX_LINE)
    if not line:
        log.info("standby for %s (pid %d): the launcher closed the pipe; exiting", service, os.getpid())
        return None
    try:
        promotion = Promotion.model_validate_json(line)
    except ValueError as exc:
        log.error("standby for %s: invalid promotion (%s); exiting", service, exc)
        return None
    apply(promotion)
    log.info("standby for %s (pid %d): promoted to instance %s", service, os.getpid(),
             promotion.env.get("EQA_INSTANCE", "?"))
    return promotion


def apply(promotion: Promotion) -> None:
    """Take the replaced instance's environment and append this process's output to its log file."""
    for name in promotion.unset:
        os.environ.pop(name, None)
    os.environ.update(promotion.env)
    if promotion.log_path is not None:
        sys.stdout.flush()
        sys.stderr.flush()
        fd = os.open(promotion.log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.dup2(fd, 1)
            os.dup2(fd, 2)
        finally:
            os.close(fd)
