"""HELIOS global search objective (paper section 3.2, Eq. 8-10): where to go next, a frontier or a candidate
start receptacle.

Notation (paper): ``A`` = detected objects of the start receptacle's class with class score ``S >= cs_a``
(Table 3: 0.3) not yet locally searched; ``F`` = the current frontiers with their value-map score ``F(f)``;
``F'`` = the frontiers chosen earlier, each stored with its value-map score when chosen, ``F_0(f')``; for each
``a in A`` the first detection stores ``S_a0``, ``IG_a0`` and its centre then.

* Eq. 8: ``V_0(f') = max_{a in A} (S_a0(a) IG_a0(a) - alpha_d dist(a, f'))``, ``dist`` from the stored centre
  of ``a`` to ``f'``;
* Eq. 9: ``F_0 = 1/|F'| sum_{f' in F'_p} V_0(f') / F_0(f')``: the average ratio of the candidate score a
  previous frontier turned out to be associated with to its value-map score. ``F'_p`` is read as the previous
  frontiers with a positive stored score and a positive ``V_0`` (the ratio is undefined for a zero score, and a
  non-positive ``V_0`` -- no candidate worth more than its distance, e.g. every stored ``IG_a0 = 0`` -- would
  make ``F_0 <= 0``, which turns Eq. 10's frontier ranking upside down: the frontier of highest value would
  rank last); the others still count in ``|F'|``. With no term in ``F'_p`` no association is known and
  ``F_0 = 1``, as with no stored candidate;
* Eq. 10: ``V(r) = S_a(r) IG_a(r) - alpha_d dist(r)`` for ``r in A``, ``F(r) F_0 - alpha_d dist(r)`` for
  ``r in F``, ``dist`` from the robot to ``r``'s centre; the robot goes to the ``r`` of highest ``V``.

Where the paper leaves a case open: with no candidate (``A`` empty) Eq. 8 has nothing to maximise and the
ranking is over frontiers alone by ``F(r) - alpha_d dist(r)`` (``F_0 = 1``, the order the value map gives);
with candidates but no earlier frontier (``F'`` empty) ``F_0 = 1`` too. The ``no_global`` ablation (Table 1)
always prefers a candidate over a frontier; ``trusting`` uses no candidates at all (frontiers by ``F``).
Pure functions; the planner shell keeps the memory (:class:`SearchMemory`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

Ablation = Literal["helios", "no_global", "trusting"]
ABLATIONS: tuple[str, ...] = ("helios", "no_global", "trusting")
ValueScale = Literal["paper", "best"]
VALUE_SCALES: tuple[str, ...] = ("paper", "best")
# dist(r) of Eq. 10: the metres the robot travels from where it stands to the point (x, y)
Travel = Callable[[float, float], float]


@dataclass(frozen=True)
class CandidateObservation:
    """A candidate ``a`` now: id, class score ``S_a``, optimistic information gain ``IG_a`` (Eq. 12), centre."""

    instance_id: int
    S: float
    IG: float
    x: float
    y: float


@dataclass(frozen=True)
class StoredCandidate:
    """What was stored the first time ``a`` was detected: ``S_a0``, ``IG_a0`` and the centre then."""

    instance_id: int
    S0: float
    IG0: float
    x: float
    y: float


@dataclass(frozen=True)
class ChosenFrontier:
    """A previously chosen frontier ``f'``: its location and value-map score ``F_0(f')`` when chosen."""

    x: float
    y: float
    F0: float


@dataclass(frozen=True)
class FrontierOption:
    """A current frontier ``f``: index (into the planner's frontier list), location, value ``F(f)``."""

    index: int
    x: float
    y: float
    F: float


@dataclass(frozen=True)
class Choice:
    kind: Literal["frontier", "candidate"]
    ref: int  # frontier index or instance id
    value: float  # V (Eq. 10)
    x: float
    y: float
    other: float | None = None  # V of the best option of the other kind (None: there is none), for the reason


def describe(choice: Choice, committed: bool = False) -> str:
    """The decision of :func:`choose` in words: the kind chosen, its V (Eq. 10) and the best V of the other
    kind (what a step's reason says the agent decided)."""
    mine = "frontier" if choice.kind == "frontier" else f"candidate {choice.ref}"
    theirs = "best candidate" if choice.kind == "frontier" else "best frontier"
    other = f"{theirs} V {choice.other:.3g}" if choice.other is not None else f"no {theirs.split()[1]}"
    kept = ", the frontier it is on its way to" if committed else ""
    return f"global search (Eq. 10): {mine} V {choice.value:.3g}{kept}; {other}"


@dataclass
class SearchMemory:
    """The planner's memory for the objective: stored first detections and chosen frontiers, visited ones."""

    stored: dict[int, StoredCandidate] = field(default_factory=dict)
    chosen: list[ChosenFrontier] = field(default_factory=list)
    visited: set[int] = field(default_factory=set)

    def observe(self, candidates: Iterable[CandidateObservation]) -> None:
        """Store ``S_a0``, ``IG_a0`` and the centre of every candidate seen for the first time."""
        for c in candidates:
            if c.instance_id not in self.stored:
                self.stored[c.instance_id] = StoredCandidate(c.instance_id, c.S, c.IG, c.x, c.y)

    def choose_frontier(self, f: FrontierOption) -> None:
        """Add ``f`` to ``F'``: once per frontier the robot sets out for (the planner shell calls it when a
        newly chosen frontier's path is planned), not at every call of :func:`choose` -- a choice kept while
        the robot is on its way, or one whose path fails, is no new association of Eq. 9."""
        self.chosen.append(ChosenFrontier(f.x, f.y, f.F))

    def to_json(self) -> dict[str, object]:
        return {"stored": [vars(s) for s in self.stored.values()], "chosen": [vars(c) for c in self.chosen],
                "visited": sorted(self.visited)}

    @classmethod
    def from_json(cls, data: dict[str, object]) -> SearchMemory:
        m = cls()
        for s in data.get("stored", []):  # type: ignore[union-attr]
            st = StoredCandidate(**s)  # type: ignore[arg-type]
            m.stored[st.instance_id] = st
        m.chosen = [ChosenFrontier(**c) for c in data.get("chosen", [])]  # type: ignore[arg-type, union-attr]
        m.visited = {int(v) for v in data.get("visited", [])}  # type: ignore[union-attr]
        return m


def v0(fx: float, fy: float, stored: Sequence[StoredCandidate], alpha_d: float) -> float | None:
    """Eq. 8 for the previous frontier at ``(fx, fy)``; None when there is no stored candidate."""
    if not stored:
        return None
    return max(a.S0 * a.IG0 - alpha_d * math.hypot(a.x - fx, a.y - fy) for a in stored)


def f0_association(chosen: Sequence[ChosenFrontier], stored: Sequence[StoredCandidate], alpha_d: float) -> float:
    """Eq. 9 (module doc); always > 0: 1 when there is no previous frontier, no stored candidate or no
    previous frontier with a positive stored score and a positive ``V_0``."""
    if not chosen or not stored:
        return 1.0
    total, terms = 0.0, 0
    for f in chosen:
        v = v0(f.x, f.y, stored, alpha_d)
        if f.F0 > 0 and v is not None and v > 0 and math.isfinite(v):
            total += v / f.F0
            terms += 1
    return total / len(chosen) if terms else 1.0


def candidates_of(observed: Iterable[CandidateObservation], cs_a: float,
                  visited: set[int] | frozenset[int] = frozenset()) -> list[CandidateObservation]:
    """``A``: candidates with ``S >= cs_a`` not yet locally searched."""
    return [c for c in observed if cs_a <= c.S and c.instance_id not in visited and math.isfinite(c.S * c.IG)]


def values(robot_xy: tuple[float, float], frontiers: Sequence[FrontierOption],
           candidates: Sequence[CandidateObservation], memory: SearchMemory, alpha_d: float,
           scale: ValueScale = "paper", travel: Travel | None = None) -> list[Choice]:
    """Eq. 10 for every frontier and candidate, highest first (ties: candidates first, then lower index).

    ``scale``: ``paper`` -- the benefits ``S IG`` and ``F F0`` as Eq. 10 writes them. Their size is set by IG, a
    count of Gaussians (10-1000 here) and ``F0`` (which carries IG's scale onto ``F``), so Table 3's
    ``alpha_d = 0.001`` per metre changes no ranking: the robot crosses the house for a frontier worth 1 % more.
    ``best`` -- each benefit over the largest benefit of this step (the best option scores 1), so ``alpha_d`` is
    the share of the best benefit one metre costs, whatever the scale of IG; the order of the benefits alone
    (``alpha_d = 0``) is the same in both.

    ``travel``: ``dist(r)`` as the metres the robot would travel to ``r`` (a path on the map, from the planner
    shell); None: the straight line from the robot. The paper writes ``dist`` without saying which; the straight
    line ranks a frontier behind a wall as near even when the way round is ten steps long."""
    if scale not in VALUE_SCALES:
        raise ValueError(f"scale must be one of {VALUE_SCALES}, got {scale!r}")
    rx, ry = robot_xy
    F0 = f0_association(memory.chosen, list(memory.stored.values()), alpha_d)
    gains = [("candidate", c.instance_id, c.S * c.IG, c.x, c.y) for c in candidates]
    gains += [("frontier", f.index, f.F * F0, f.x, f.y) for f in frontiers if math.isfinite(f.F)]
    top = max((g[2] for g in gains if math.isfinite(g[2])), default=0.0)
    norm = top if scale == "best" and top > 0 else 1.0
    def dist(x: float, y: float) -> float:
        return travel(x, y) if travel is not None else math.hypot(x - rx, y - ry)

    out = [Choice(kind, ref, gain / norm - alpha_d * dist(x, y), x, y)  # type: ignore[arg-type]
           for kind, ref, gain, x, y in gains]
    out.sort(key=lambda ch: (-ch.value, ch.kind != "candidate", ch.ref))
    return out


def choose(robot_xy: tuple[float, float], frontiers: Sequence[FrontierOption],
           observed: Sequence[CandidateObservation], memory: SearchMemory, alpha_d: float, cs_a: float,
           ablation: Ablation = "helios", committed: int | None = None,
           scale: ValueScale = "paper", travel: Travel | None = None) -> Choice | None:
    """The next global-search target under ``ablation`` (module doc); None when there is nothing to go to.
    Stores first detections in ``memory``; the chosen frontier goes into ``F'`` only when the planner sets out
    for it (:meth:`SearchMemory.choose_frontier`).

    ``committed``: the index of the frontier the robot is on its way to (chosen at an earlier step, not reached
    yet). Eq. 10 says the robot goes to the ``r`` of highest ``V``; we read it as a choice of where to go that
    holds until the robot gets there, as a frontier waypoint does in VLFM, on which HELIOS builds: while a
    frontier ranks first, the committed one is kept, so the frontier values changing under a moving robot do
    not send it back and forth between frontiers (tuning seed 11: the first task's robot crossed the same room
    for ten steps and never reached the next room). A candidate that ranks first still wins at once."""
    if ablation not in ABLATIONS:
        raise ValueError(f"ablation must be one of {ABLATIONS}, got {ablation!r}")
    cands = [] if ablation == "trusting" else candidates_of(observed, cs_a, memory.visited)
    if ablation != "trusting":
        memory.observe(candidates_of(observed, cs_a))
    ranked = values(robot_xy, frontiers, cands, memory, alpha_d, scale, travel)
    if not ranked:
        return None
    best = ranked[0]
    if ablation == "no_global":
        best = next((c for c in ranked if c.kind == "candidate"), best)
    if best.kind == "frontier" and committed is not None:
        best = next((c for c in ranked if c.kind == "frontier" and c.ref == committed), best)
    other = next((c.value for c in ranked if c.kind != best.kind), None)
    return dataclasses.replace(best, other=other)
