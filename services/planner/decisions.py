"""HELIOS decisions about a detected object (paper appendix 6.1, Eq. 7 and 11; Table 3 thresholds) and the
pick-attempt limits (section 4.1).

For a candidate target ``g`` (class score ``S_g >= cs_g``) with uncertainty-weighted score ``Psi_g`` (Eq. 7)
and, for its best gaze point, the optimistic score ``Psi'_g`` (Eq. 11: the score if the views from there all
detected it as ``g``):

* ``Psi_g >= tau_g`` -> **act** (pick it; for a goal receptacle ``b`` with ``tau_b``: place on it);
* else ``Psi'_g >= min(tau_g, Psi_g + tau_inc)`` -> **look** (go to that gaze point for another view);
* else -> **global** (back to the global search).

Among several candidates: act on the one with the highest ``Psi`` that passes ``tau``; else look at the one
with the highest ``Psi'`` that passes the look rule; else global search. The ``trusting`` ablation (Table 1)
has no object layer: it acts on the first detection of the class (any candidate, whatever its score).

Pick attempts (section 4.1): 1, 5 or unlimited; with a limit, an episode that would exceed it ends and all its
metrics count 0 (the paper's scoring). A failed oracle pick reveals "not in frame / not within reach", so the
planner marks that candidate and looks elsewhere.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

Action = Literal["act", "look", "global"]
PICK_LIMITS: dict[str, int | None] = {"1": 1, "5": 5, "unlimited": None}


@dataclass(frozen=True)
class Scored:
    """One candidate: instance id, class score ``S``, ``Psi`` (Eq. 7) and ``Psi'`` of its best gaze point
    (Eq. 11; None when it has no usable gaze point)."""

    instance_id: int
    S: float
    psi: float
    psi_prime: float | None = None


@dataclass(frozen=True)
class TaskChoice:
    """What a task episode does about one object class (not the stopper's bus ``Decision``): the action, the
    candidate it is about, and why."""

    action: Action
    instance_id: int | None = None
    reason: str = ""


def decide_one(psi: float, psi_prime: float | None, tau: float, tau_inc: float) -> Action:
    """Eq. 11's rule for one candidate (module doc)."""
    if psi >= tau:
        return "act"
    if psi_prime is not None and math.isfinite(psi_prime) and psi_prime >= min(tau, psi + tau_inc):
        return "look"
    return "global"


def decide(candidates: Iterable[Scored], tau: float, tau_inc: float, cs: float,
           trusting: bool = False, exclude: set[int] | frozenset[int] = frozenset()) -> TaskChoice:
    """The decision over every candidate of one class (module doc). ``cs`` = cs_g or cs_b (Table 3);
    ``exclude``: candidates ruled out (a failed pick there, a place that failed)."""
    pool = [c for c in candidates if c.instance_id not in exclude and math.isfinite(c.psi)]
    if trusting:
        if not pool:
            return TaskChoice("global", None, "trusting: no detection yet")
        first = max(pool, key=lambda c: (c.S, -c.instance_id))
        return TaskChoice("act", first.instance_id, "trusting: acts on a detection")
    pool = [c for c in pool if cs <= c.S]
    acts = [c for c in pool if decide_one(c.psi, c.psi_prime, tau, tau_inc) == "act"]
    if acts:
        best = max(acts, key=lambda c: (c.psi, -c.instance_id))
        return TaskChoice("act", best.instance_id, f"Psi {best.psi:.3f} >= tau {tau:.3f}")
    looks = [c for c in pool if decide_one(c.psi, c.psi_prime, tau, tau_inc) == "look"]
    if looks:
        best = max(looks, key=lambda c: (c.psi_prime or -math.inf, -c.instance_id))
        return TaskChoice("look", best.instance_id,
                        f"Psi' {best.psi_prime:.3f} >= min(tau {tau:.3f}, Psi {best.psi:.3f} + tau_inc {tau_inc:.3f})")
    return TaskChoice("global", None, "no candidate confident enough or worth another look" if pool else "no candidate")


@dataclass
class PickBudget:
    """Pick attempts under a limit (None = unlimited)."""

    limit: int | None = None
    attempts: int = 0
    successes: int = 0

    def __post_init__(self) -> None:
        if self.limit is not None and self.limit < 1:
            raise ValueError(f"a pick limit is >= 1 (or None for unlimited), got {self.limit}")

    @property
    def exhausted(self) -> bool:
        """No attempt left."""
        return self.limit is not None and self.attempts >= self.limit

    def attempt(self, success: bool) -> None:
        """Count one attempt; raises ``RuntimeError`` when none was left (the caller must check first)."""
        if self.exhausted:
            raise RuntimeError(f"pick limit {self.limit} already used")
        self.attempts += 1
        self.successes += int(bool(success))


def pick_limit(name: str | int | None) -> int | None:
    """``"1"``/``1`` -> 1, ``"5"`` -> 5, ``"unlimited"``/``0``/None -> None; else ``ValueError``."""
    if name is None or name == 0 or name == "0":
        return None
    if isinstance(name, int):
        if name < 0:
            raise ValueError(f"pick limit must be >= 0 (0 = unlimited), got {name}")
        return name
    if name in PICK_LIMITS:
        return PICK_LIMITS[name]
    try:
        return pick_limit(int(name))
    except ValueError:
        raise ValueError(f"pick limit must be 1, 5, unlimited or a positive number, got {name!r}") from None
