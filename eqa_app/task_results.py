"""One task benchmark run's identity and result, shared by the fleet runner (:mod:`eqa_app.task_bench`) and the
in-process runner (:mod:`eqa_app.task_cores`)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

from eqa.task_traces import Failure, failure_cause


def task_seed(task_id: str) -> int:
    return int.from_bytes(hashlib.sha256(task_id.encode()).digest()[:4], "little") & 0x7FFFFFFF


@dataclass
class TaskResult:
    task_id: str
    kind: str
    variant: str
    max_steps: int
    metrics: dict[str, float]
    state: str
    reason: str
    seconds: float
    pick_limit: int | None = None  # enforced during the run (None: unlimited)
    trace: dict[str, Any] | None = None  # the sim's task trace (exported apart from the results)

    def key(self) -> tuple[str, str, int, int | None]:
        return (self.task_id, self.variant, self.max_steps, self.pick_limit)

    def row(self) -> dict[str, Any]:
        """The results line (without the trace)."""
        return {k: v for k, v in self.__dict__.items() if k != "trace"}

    def failure(self) -> Failure:
        return failure_cause(self.kind, self.trace, self.metrics, self.state, self.reason, self.max_steps)
