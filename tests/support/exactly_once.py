"""What the services publish, read back to tell whether a step was computed once.

Every message carries ``sent_at``, the time it was made. A step *integrated* by the mapper is a ``MapUpdate``
with its stage timings (a resent frame is answered from the stored map with an empty ``timing_ms``); a step
*decided* by the stopper is a ``Decision`` (a resent step gets the stored decision again, same ``sent_at``); a
step *planned* by the planner is a ``Goal`` (the stored goal again for a resent step; a goal the simulator
refused with a ``sim/error`` is replanned once more by design, so each such error allows one more goal).
Two instances computing one step leave two different ``sent_at``; a skipped step leaves none.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from typing import Any

from eqa import keys
from eqa.messages import STREAM_TYPES, EpisodeEnd

PAIRS = (keys.MAPPER_MAP, keys.STOPPER_DECISION, keys.PLANNER_GOAL, keys.SIM_ERROR)


def wait_on(cond: threading.Condition, pred: Any, timeout: float) -> bool:
    """Wait on ``cond`` (notified when what ``pred`` reads changes) until ``pred()`` holds; False on timeout."""
    deadline = time.monotonic() + timeout
    with cond:
        while not pred():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            cond.wait(min(left, 0.2))
    return True


class Ends:
    """The first ``EpisodeEnd`` of each episode (subscribe it to ``keys.any_robot(keys.EPISODE_END)``)."""

    def __init__(self) -> None:
        self.ends: dict[str, EpisodeEnd] = {}
        self.lock = threading.Lock()

    def __call__(self, _key: str, msg: EpisodeEnd) -> None:
        with self.lock:
            self.ends.setdefault(msg.episode_id, msg)


class StepLedger:
    def __init__(self) -> None:
        self.made: dict[tuple[str, str, int], set[float]] = defaultdict(set)
        self.lock = threading.Lock()

    def subscribe(self, bus: Any) -> None:
        for pair in PAIRS:
            bus.subscribe(keys.any_robot(pair), STREAM_TYPES[pair], self._on(pair))

    def _on(self, pair: tuple[str, str]):
        name = "/".join(pair)

        def on(_key: str, msg: Any) -> None:
            step = getattr(msg, "step", None)
            if msg.episode_id is None or step is None:
                return
            if pair == keys.MAPPER_MAP and not msg.timing_ms:
                return  # answered again from the stored map, not integrated
            with self.lock:
                self.made[(name, msg.episode_id, int(step))].add(float(msg.sent_at))

        return on

    def problems(self, episodes: dict[str, int]) -> list[str]:
        """Every step computed more than once or not at all, for ``episode -> steps run``.

        An output this ledger did not see counts as not made only when nothing downstream shows it was made:
        a peer writes one message to each peer's link in turn, so a kill -9 between two writes can leave the
        consumer with it and this observer without it. A goal of step t is shown made by any output of a later
        step (the sim renders step t+1 only after it), a map or a decision of step t also by the goal of step t
        (the planner plans on both). The last step has nothing downstream: its outputs must be seen."""
        out = []
        with self.lock:
            made = {k: set(v) for k, v in self.made.items()}
        for eid, steps in episodes.items():
            seen_steps = {t for (_, e, t) in made if e == eid}

            def later(t: int, eid: str = eid, seen: set[int] = seen_steps) -> bool:
                return any(u > t for u in seen)

            for t in range(steps):
                goal = len(made.get(("planner/goal", eid, t), ()))
                for stream in ("mapper/map", "stopper/decision"):
                    n = len(made.get((stream, eid, t), ()))
                    if n > 1 or (n == 0 and not (goal or later(t))):
                        out.append(f"{stream} step {t} of {eid}: made {n} times")
                if t < steps - 1:
                    allowed = 1 + len(made.get(("sim/error", eid, t), ()))
                    if goal > allowed or (goal == 0 and not later(t)):
                        out.append(f"planner/goal step {t} of {eid}: made {goal} times ({allowed - 1} refused)")
        return out

    def settled_problems(self, episodes: dict[str, int], timeout: float = 10.0) -> list[str]:
        """:meth:`problems` once they are gone or ``timeout`` s passed: the subscriptions run on their own
        threads, so the last decision, published right before the end, may be counted a moment later (a
        missing one stays missing)."""
        deadline = time.monotonic() + timeout
        while (out := self.problems(episodes)) and time.monotonic() < deadline:
            time.sleep(0.1)
        return out
