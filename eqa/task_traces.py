"""Task traces: the per-step record of a task episode, the metrics replayed from it, and the failure cause of
a run (HELIOS appendix 6.4, Fig. 5 / 6: the failure-mode break-down).

A trace is what the simulator stores under :func:`eqa.store.task_trace_key` (``eqa:trace:task:<episode id>``,
:meth:`services.sim.task_episode.TaskEpisode.trace_doc`): the task with its ground truth, the pick limit, the
planner's end reason and one entry per step -- the planner's goal that led to the step (``phase``, ``skill``,
``target`` instance, ``reason``, the decision's ``numbers``: ``Psi``, ``Psi_prime``, ``IG``, ``S``, ``U``,
``V``, ``F``, ``F0`` as far as they apply), the ``pose`` reached, whether the motion ``collided``, the
``skill_result`` and, after it, the cumulative ``collisions``, ``pick_attempts``, ``path_m`` and the phase
flags ``FindObj``, ``Pick``, ``FindRec``, ``Place`` (``found`` for object search).

:func:`replay_metrics` recomputes the episode's OVMM metrics from the entries alone (the simulator's rule,
:meth:`services.sim.task_episode.TaskEpisode.metrics`), so a table is reproduced from exported traces without
running an episode (``eqa bench ovmm --replay DIR``). :func:`failure_cause` names the first thing that failed:

* ``pick_place`` -- ``collision`` when a motion hit an obstacle (OVMM's SR is lost at that moment, whatever
  came after; the phase it happened in is kept), else the first phase not reached: ``object not found``,
  ``pick failed`` (the object was found, no pick succeeded: out of reach, or the pick limit used up),
  ``receptacle not found``, ``place failed``; a search that did not end in its phase says why: ``out of steps``
  (the step budget), ``search ended`` (the planner gave up: no frontier left, no reachable action) or ``pick
  limit used up`` (the picks went to something else: a false detection, out of reach);
* ``find_object`` -- ``stopped away from the object`` (the stop call farther than 1 m from every target box),
  else ``object not found`` (out of steps / search ended); collisions do not fail an object search (its SR is
  the stop's success, HM3D ObjectNav);
* ``success``; ``run failed`` for an episode the fleet did not finish (no trace, an error).

Pure functions over plain data (the kernel imports no service).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

OVMM_FLAGS = ("FindObj", "Pick", "FindRec", "Place")
OVMM_METRICS = (*OVMM_FLAGS, "SR")
PICK_PLACE_CAUSES = ("collision", "object not found: out of steps", "object not found: search ended",
                     "object not found: pick limit used up", "pick failed",
                     "receptacle not found: out of steps", "receptacle not found: search ended", "place failed",
                     "run failed", "success")
FIND_CAUSES = ("stopped away from the object", "object not found: out of steps", "object not found: search ended",
               "run failed", "success")
MAX_TRACE_STEPS = 10_000  # Task.max_steps' bound


class TraceError(ValueError):
    """A trace that cannot be read (missing fields, wrong types)."""


def steps_of(trace: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The per-step entries of a stored trace, checked for the fields the replay reads."""
    if trace is None:
        return []
    steps = trace.get("steps")
    if not isinstance(steps, list) or len(steps) > MAX_TRACE_STEPS:
        raise TraceError("a task trace has a list 'steps' of at most 10000 entries")
    for i, s in enumerate(steps):
        if not isinstance(s, dict) or not isinstance(s.get("step"), int):
            raise TraceError(f"trace entry {i} is not an object with an integer 'step'")
        for k in ("collisions", "pick_attempts"):
            if not isinstance(s.get(k, 0), int | float):
                raise TraceError(f"trace entry {i}: {k!r} is not a number")
    return steps


def replay_metrics(kind: str, trace: dict[str, Any], pick_limit: int | None = None) -> dict[str, float]:
    """The episode's metrics from its trace (module doc): the flags and counts of the last entry; SR = all four
    flags and no collision; with a pick limit exceeded every metric is 0 (the paper's rule). ``find_object``:
    SR = the stop's success, SPL = SR x shortest / max(shortest, travelled)."""
    steps = steps_of(trace)
    last = steps[-1] if steps else {}
    collisions = float(last.get("collisions", 0))
    if kind == "find_object":
        found = bool(last.get("found", False))
        shortest = float((trace.get("task") or {}).get("shortest_path_m") or 0.0)
        spl = shortest / max(shortest, float(last.get("path_m", 0.0)), 1e-9) if found else 0.0
        return {"SR": float(found), "SPL": round(spl, 6), "collisions": collisions}
    attempts = float(last.get("pick_attempts", 0))
    if pick_limit is not None and attempts > pick_limit:
        vals = dict.fromkeys(OVMM_METRICS, 0.0)
    else:
        vals = {k: float(bool(last.get(k, False))) for k in OVMM_FLAGS}
        vals["SR"] = float(all(vals[k] for k in OVMM_FLAGS) and collisions == 0)
    return {**vals, "collisions": collisions, "pick_attempts": attempts}


@dataclass(frozen=True)
class Failure:
    """The first failure of a run: ``cause`` (one of :data:`PICK_PLACE_CAUSES` / :data:`FIND_CAUSES`), the task
    ``phase`` it happened in (the planner's phase at that step, or the last one) and the ``step``."""

    cause: str
    phase: str | None = None
    step: int | None = None

    @property
    def failed(self) -> bool:
        return self.cause != "success"


def failure_cause(kind: str, trace: dict[str, Any] | None, metrics: dict[str, float], state: str = "stopped",
                  reason: str = "", max_steps: int | None = None, steps_run: int | None = None) -> Failure:
    """The first failure of one run (module doc) from its trace, its final metrics and its end (``reason``,
    and ``steps_run`` of ``max_steps`` when there is no trace)."""
    steps = steps_of(trace)
    if state == "failed" or not (steps or metrics):
        return Failure("run failed", None, None)
    if not steps:  # no trace: the final metrics alone (no phase, no step)
        last = {"step": None, **{k: bool(metrics.get(k)) for k in OVMM_FLAGS}, "found": bool(metrics.get("SR"))}
        if kind == "pick_place" and metrics.get("collisions", 0.0) > 0:
            last["collided"] = True
        steps = [last]
        if (max_steps is not None and steps_run is not None and steps_run >= max_steps):
            reason = f"{reason} step limit"
    last = steps[-1]
    end_phase = next((s.get("phase") for s in reversed(steps) if s.get("phase")), None)
    text = f"{reason} {(trace or {}).get('end_reason') or ''}"
    out_of_steps = (max_steps is not None and len(steps) >= max_steps) or "step limit" in text
    ending = "out of steps" if out_of_steps else "pick limit used up" if "pick limit" in text else "search ended"
    if kind == "find_object":
        if metrics.get("SR", 0.0) >= 1.0:
            return Failure("success", end_phase, last["step"])
        stop = next((s for s in steps if (s.get("skill_result") or {}).get("skill") == "stop"), None)
        if stop is not None or "not near a target object" in text:  # the sim's stop report (a trace or not)
            return Failure("stopped away from the object", (stop or {}).get("phase"), (stop or {}).get("step"))
        return Failure(f"object not found: {ending}", end_phase, last["step"])
    hit = next((s for s in steps if s.get("collided")), None)
    if hit is not None:
        return Failure("collision", hit.get("phase"), hit["step"])
    if metrics.get("SR", 0.0) >= 1.0:
        return Failure("success", end_phase, last["step"])
    if not last.get("FindObj"):
        return Failure(f"object not found: {ending}", end_phase, last["step"])
    if not last.get("Pick"):
        picks = [s for s in steps if (s.get("skill_result") or {}).get("skill") == "pick"]
        return Failure("pick failed", "picking", picks[-1]["step"] if picks else last["step"])
    if not last.get("FindRec"):
        return Failure(f"receptacle not found: {ending}", end_phase, last["step"])
    place = next((s for s in steps if (s.get("skill_result") or {}).get("skill") == "place"), None)
    return Failure("place failed", "placing", place["step"] if place else last["step"])


def breakdown(rows: Iterable[tuple[str, Failure]], kind: str) -> dict[str, dict[str, int]]:
    """Counts per variant and cause (every cause of ``kind`` listed, in order, zeros included)."""
    causes = PICK_PLACE_CAUSES if kind == "pick_place" else FIND_CAUSES
    counts: dict[str, Counter[str]] = {}
    for variant, f in rows:
        counts.setdefault(variant, Counter())[f.cause] += 1
    return {v: {c: int(n[c]) for c in causes} for v, n in counts.items()}


def collision_phases(rows: Iterable[tuple[str, Failure]]) -> dict[str, dict[str, int]]:
    """Per variant, the task phase in which the first collision of each collision-failed run happened."""
    out: dict[str, Counter[str]] = {}
    for variant, f in rows:
        if f.cause == "collision":
            out.setdefault(variant, Counter())[f.phase or "start"] += 1
    return {v: dict(c) for v, c in out.items()}


def format_breakdown(table: dict[str, dict[str, int]], kind: str, variants: Sequence[str],
                     phases: dict[str, dict[str, int]] | None = None) -> str:
    """The failure break-down as a text table: per cause, the share of runs of each variant (n each)."""
    causes = PICK_PLACE_CAUSES if kind == "pick_place" else FIND_CAUSES
    vs = [v for v in variants if v in table]
    n = {v: sum(table[v].values()) for v in vs}
    lines = [f"{'first failure':<36} " + " ".join(f"{v + f' (n={n[v]})':>20}" for v in vs)]
    for c in causes:
        if not any(table[v][c] for v in vs):
            continue
        cells = " ".join(f"{table[v][c]:>8d} ({100 * table[v][c] / max(n[v], 1):5.1f} %)  " for v in vs)
        lines.append(f"{c:<36} {cells}")
    for v, ph in (phases or {}).items():
        if ph:
            lines.append(f"collisions of {v} by phase: " + ", ".join(f"{p} {k}" for p, k in sorted(ph.items())))
    return "\n".join(lines)


def task_outcome(kind: str, metrics: dict[str, float], state: str, reason: str, steps: int | None = None,
                 max_steps: int | None = None, trace: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a user reads about a finished task episode: ``success`` (SR), the first failure's ``cause`` and
    ``phase`` (:func:`failure_cause`; from the final metrics when no trace is at hand) and one line of
    ``text``."""
    f = failure_cause(kind, trace, metrics, state, reason, max_steps, steps)
    if not f.failed:
        text = "success"
    elif f.cause == "run failed":
        text = f"failed: the run did not finish ({reason})" if reason else "failed: the run did not finish"
    else:
        text = "failed: " + f.cause.replace(": ", " (", 1) + (")" if ": " in f.cause else "")
        if f.phase:
            text += f", in phase {f.phase}"
        if f.step is not None:
            text += f" at step {f.step}"
    return {"success": not f.failed, "cause": f.cause, "phase": f.phase, "step": f.step, "text": text}


def kind_of_metrics(metrics: dict[str, float]) -> str:
    """``pick_place`` when the metrics carry OVMM's phases, else ``find_object``."""
    return "pick_place" if "FindObj" in metrics else "find_object"
