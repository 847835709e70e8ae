"""Closed-world existence answers: "No" once the asked room has been observed and no view of it showed the object.

Pure numpy, no I/O. Neither paper answers an existence question from what was *not* seen: Explore-EQA reads the
answer from the most relevant view (section V-B), and a view without the object is not relevant to "Is there a
mug in the kitchen?", so the answer of a "no" question is a guess from the VLM's priors. The closed-world rule
reads three per-step signals, every one available to a robot with a real VLM:

* ``object_yes``: the scorer's P(Yes) to ``PRESENCE`` ("Is there a mug in this image?",
  :mod:`services.vlm_scorer.prompts`), asked on every view;
* ``in_room``: its P(Yes) to ``IN_ROOM`` ("Is this image taken in the kitchen?"); a step with
  ``in_room >= in_room_min`` is a *room view*;
* the asked room's extent on the robot's own map, built from the ``IN_ROOM`` answers
  (:mod:`services.mapper.room_extent`): its area and the share of its boundary still open to frontiers.

The rule (:func:`firing_step`): evidence of the object is ``k_yes`` room views with ``object_yes >=
presence_min``; the rule fires at the first step where the room is observed (area ``>= min_area_m2``, open
share ``<= max_open``) and there is no evidence so far. From that step the answer is "No" and the episode may
stop. A later view cannot undo it: the episode ends there.

With conformal stopping (:func:`apply`), the steps from the firing step on score ``f`` = :func:`no_distribution`
(``confidence`` on "No") with ``Rel = 1``: a conclusion drawn from the whole map, not one view. The transformed
sequence is a deterministic causal function of the episode's signals, so calibrating ``kappa`` on traces
transformed by the same rule keeps Eq. 6 and Claim 1, as for the answer memory
(:mod:`services.stopper.answer_memory`).

The thresholds are declared, and chosen on the tuning seed only, in ``docs/results/closed-world-answers.md``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from eqa.messages import PresenceEvidence as PresenceStep
from services.stopper.object_evidence import yes_no


@dataclass(frozen=True)
class ClosedWorldParams:
    k_yes: int = 1  # room views saying "yes, the object is here" that count as evidence
    min_area_m2: float = 2.0  # the room's extent must cover this much before it counts as observed
    max_open: float = 0.2  # and at most this share of its boundary may touch a frontier
    presence_min: float = 0.5  # P(Yes) to PRESENCE from which a view says the object is there
    in_room_min: float = 0.5  # P(Yes) to IN_ROOM from which a view is of the room
    confidence: float = 0.9  # CP: f("No") from the firing step on
    padding: float = 1e-3  # CP: f of each padding choice

    def __post_init__(self) -> None:
        if not (isinstance(self.k_yes, int) and 1 <= self.k_yes <= 100):
            raise ValueError(f"k_yes must be an integer in 1..100, got {self.k_yes!r}")
        for name in ("min_area_m2", "max_open", "presence_min", "in_room_min", "confidence", "padding"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"closed-world {name} must be a finite number >= 0, got {v!r}")
        for name in ("max_open", "presence_min", "in_room_min", "confidence"):
            if getattr(self, name) > 1:
                raise ValueError(f"closed-world {name} must be <= 1, got {getattr(self, name)!r}")
        if not 0 <= self.padding < 0.1:
            raise ValueError(f"closed-world padding must be in [0, 0.1), got {self.padding!r}")


def step_verdict(yes_so_far: int, s: PresenceStep, params: ClosedWorldParams) -> tuple[int, bool]:
    """One step of the rule: ``(room views with the object so far, whether the rule concludes "No" here)``.
    Once ``yes_so_far >= k_yes`` the rule never concludes."""
    yes = yes_so_far
    if s.in_room is not None and s.in_room >= params.in_room_min and s.object_yes >= params.presence_min:
        yes += 1
    if yes >= params.k_yes:
        return yes, False
    return yes, s.room_area_m2 >= params.min_area_m2 and s.open_share <= params.max_open


def firing_step(steps: Sequence[PresenceStep], params: ClosedWorldParams) -> int | None:
    """The first step at which the rule concludes "No" (module docstring), or None."""
    yes = 0
    for t, s in enumerate(steps):
        yes, fires = step_verdict(yes, s, params)
        if yes >= params.k_yes:
            return None
        if fires:
            return t
    return None


def no_index(choices: Sequence[str]) -> int | None:
    """Index of the "No" choice, or None when the question is no yes/no question."""
    return next((i for i, c in enumerate(choices) if yes_no(c) is False), None)


def no_distribution(choices: Sequence[str], params: ClosedWorldParams) -> np.ndarray | None:
    """``f`` of a closed-world "No": ``confidence`` on "No", ``padding`` on each choice that is neither yes nor
    no, the rest on "Yes"; None without a "No" and a "Yes" choice."""
    yn = [yes_no(c) for c in choices]
    if False not in yn or True not in yn:
        return None
    f = np.array([params.confidence if v is False else 0.0 if v is True else params.padding for v in yn])
    f[yn.index(True)] = max(1.0 - f.sum(), 0.0)
    return f / f.sum()


def apply(probs: np.ndarray, relevance: np.ndarray, fire: int | None, choices: Sequence[str],
          params: ClosedWorldParams) -> tuple[np.ndarray, np.ndarray]:
    """``(f, Rel)`` of an episode's steps with the closed-world conclusion from step ``fire`` on (unchanged when
    ``fire`` is None or the question has no yes/no choices)."""
    f = np.array(probs, dtype=np.float64)
    rel = np.array(relevance, dtype=np.float64)
    if f.ndim != 2 or rel.shape != (f.shape[0],) or f.shape[1] != len(choices):
        raise ValueError(f"apply needs (T, {len(choices)}) distributions and (T,) relevances, got {f.shape}, "
                         f"{rel.shape}")
    dist = no_distribution(choices, params)
    if fire is None or dist is None or not 0 <= fire < f.shape[0]:
        return f, rel
    f[fire:] = dist
    rel[fire:] = 1.0
    return f, rel
