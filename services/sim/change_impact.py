"""What house changes do to questions: a question's ground truth in a changed house, and whether the changes
affect it.

:func:`rederive` recomputes a question's ground truth (answer letter, evidence ids, targets) in a changed house
(:mod:`services.sim.changes`) from its structured ``query``, the way :mod:`services.sim.questions` makes it;
:func:`impact` says whether a question is affected by the changes (its answer or its evidence changed).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from eqa.messages import Pose2D, Question
from services.sim import catalog
from services.sim.changes import Change
from services.sim.motion import GRID_RES, START_CLEARANCE, clearance_map, pose_error
from services.sim.questions import NUMBER_WORDS, question_targets
from services.sim.scene import Scene


@dataclass
class Impact:
    """What the changes do to one question: ``question`` is its ground truth in the changed house (None when
    the question has none there: the object it names is gone, is no longer the only one, or the true answer
    is not among its choices)."""

    affected: bool
    answer_changed: bool
    evidence_changed: bool
    question: Question | None
    touched: list[int] = field(default_factory=list)  # evidence objects (old or new) the changes touched



def _letter(q: Question, text: str) -> str | None:
    return "ABCD"[q.choices.index(text)] if text in q.choices else None


def _ground_truth(q: Question, scene: Scene) -> tuple[str | None, list[int]]:
    """(answer letter or None, evidence ids) of ``q``'s query in ``scene``, as :mod:`questions` makes them."""
    query = q.query
    qtype, cat = query.get("type"), query.get("category", "")
    kind = query.get("room_kind", "")
    objs = scene.objects()
    in_kind = [o.id for o in objs if o.category == cat and o.room_kind == kind]
    if qtype == "counting":
        ids = sorted(in_kind if kind else [o.id for o in objs if o.category == cat])
        n = len(ids)
        return (_letter(q, NUMBER_WORDS[n]) if n < len(NUMBER_WORDS) else None), ids
    if qtype == "existence":
        return _letter(q, "Yes" if in_kind else "No"), sorted(in_kind)
    if qtype in ("identification", "state"):
        if len(in_kind) != 1:
            return None, sorted(in_kind)
        ob = scene.instances[in_kind[0]]
        if qtype == "identification":
            return _letter(q, ob.attributes.get("color", "").capitalize()), in_kind
        yes = ob.attributes.get("state") == query.get("value")
        return _letter(q, "Yes" if yes else "No"), in_kind
    if qtype == "location":
        ids = [o.id for o in objs if o.category == cat and o.attributes.get("color") == query.get("color")]
        if len(ids) != 1:
            return None, sorted(ids)
        ob = scene.instances[ids[0]]
        return _letter(q, f"In the {catalog.display_name(ob.room_kind or '')}"), ids
    raise ValueError(f"question {q.id}: unknown query type {qtype!r}")


def _nearest_free(scene: Scene, pose: Pose2D) -> Pose2D:
    """``pose`` if the robot may start there in ``scene``, else the nearest pose with the start clearance."""
    if pose_error(scene, pose, clearance=START_CLEARANCE) is None:
        return pose
    ok, ox, oy = clearance_map(scene, START_CLEARANCE)
    cells = np.argwhere(ok)
    if len(cells) == 0:
        return pose
    xy = np.column_stack([ox + (cells[:, 1] + 0.5) * GRID_RES, oy + (cells[:, 0] + 0.5) * GRID_RES])
    best = int(np.argmin(np.hypot(xy[:, 0] - pose.x, xy[:, 1] - pose.y)))
    return Pose2D(x=round(float(xy[best, 0]), 3), y=round(float(xy[best, 1]), 3), yaw=pose.yaw)


def rederive(question: Question, scene: Scene) -> Question | None:
    """``question`` asked in ``scene`` (a changed house of its own): the same text, choices and query with the
    ground truth of ``scene``; None when it has none there (see :class:`Impact`). The start pose stays unless
    an added object stands on it (then the nearest free pose)."""
    answer, evidence = _ground_truth(question, scene)
    if answer is None:
        return None
    same = scene.id == question.scene
    return question.model_copy(update={
        "id": question.id if same else f"{question.id}-{scene.id.rsplit('-', 1)[-1]}",
        "scene": scene.id, "answer": answer, "evidence_ids": evidence,
        "targets": question_targets(scene, evidence, question.query.get("room_kind")),
        "start_pose": None if question.start_pose is None else _nearest_free(scene, question.start_pose),
    })


def impact(question: Question, changes: list[Change], scene: Scene) -> Impact:
    """Whether ``changes`` (that made ``scene`` out of the question's house) affect ``question``: its answer
    changed, or its evidence did (other evidence objects, or an evidence object moved, was added, removed or
    switched its state). A question without ground truth in ``scene`` is affected."""
    new = rederive(question, scene)
    touched_ids = {c.object_id for c in changes}
    if new is None:
        _, ev = _ground_truth(question, scene)
        touched = sorted(touched_ids & (set(question.evidence_ids) | set(ev)))
        return Impact(True, True, True, None, touched)
    answer_changed = new.answer != question.answer
    ev_old, ev_new = set(question.evidence_ids), set(new.evidence_ids)
    touched = sorted(touched_ids & (ev_old | ev_new))
    evidence_changed = ev_old != ev_new or bool(touched)
    return Impact(answer_changed or evidence_changed, answer_changed, evidence_changed, new, touched)
