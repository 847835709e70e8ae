"""The evidence ceiling of an exploration benchmark: could any robot have perceived the evidence within the budget?

For one question, the earliest step ``k`` at which a robot starting at the question's start pose can stand at a
pose from which the simulated perception model perceives an evidence object (quality > 0, the oracle scorer's
:meth:`~services.vlm_scorer.backends.oracle.OracleBackend.view_quality` of the rendered frame), when every step moves
it at most ``max_step_m`` along a shortest path of the true house (:func:`services.sim.paths.geodesic_field` on the
ground-truth navigable grid) and it may face any direction on arrival. When no object is the evidence (a "no"
existence question), the evidence is the asked room: the earliest step at which the robot can stand inside it.

The step is reported as ``(k + 1) / T`` like the first-evidence CDF (:func:`eqa_app.evaluation.evidence_cdf`),
so the share of questions with a ceiling step within each budget is the curve no strategy can beat (within the
sampled viewpoints: up to :data:`VIEWS_PER_STEP` per step, :data:`MAX_VIEWS` per question, nearest the object
first, so the ceiling is a close lower estimate of the true one, not an over-estimate of it).

Ground truth throughout: benchmark use only. Scorer: the simulated perception model, not a VLM/detector.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

VIEWS_PER_STEP = 3  # rendered candidate poses per reachable step ring
MAX_VIEWS = 48  # rendered candidate poses per question


@dataclass(frozen=True)
class Ceiling:
    """``step``: the earliest frame index at which the evidence can be perceived (None: not within the budget);
    ``first_at``: ``(step + 1) / T`` or None; ``views``: how many candidate poses were rendered."""

    question_id: str
    step: int | None
    first_at: float | None
    views: int
    reason: str


def ceiling_steps(geo_m: np.ndarray, step_m: float) -> np.ndarray:
    """Frame index at which the robot can first stand on each cell: ``ceil(d / step_m)`` moves (0 at the start
    cell); ``-1`` where the true house gives no path."""
    k = np.full(geo_m.shape, -1, np.int64)
    ok = np.isfinite(geo_m)
    k[ok] = np.ceil(geo_m[ok] / step_m - 1e-9).astype(np.int64)
    return k


def question_ceiling(question: Any, scene: Any, renderer: Any, oracle: Any, width: int, height: int,
                     step_m: float) -> Ceiling:
    """The evidence ceiling of one benchmark question (module doc). ``oracle``: an
    :class:`~services.vlm_scorer.backends.oracle.OracleBackend` (its perception thresholds decide what is seen);
    ``step_m``: the planner's longest move per step (``PlannerParams.max_step_m``)."""
    from eqa import grid as gridm
    from eqa.messages import Pose2D
    from services.sim import camera
    from services.sim.motion import ROBOT_RADIUS, clearance_map
    from services.sim.paths import PATH_RES, geodesic_field

    T = int(question.max_steps)
    start = question.start_pose
    if start is None:
        raise ValueError(f"question {question.id} has no start pose")
    reach, ox, oy = clearance_map(scene, ROBOT_RADIUS, PATH_RES)
    origin = (ox, oy)
    i0, j0 = gridm.cell_of_point(start.x, start.y, origin, PATH_RES)
    geo = geodesic_field(reach, PATH_RES, [(i0, j0, 0.0)])
    steps = ceiling_steps(geo, step_m)
    usable = (steps >= 0) & (steps <= T - 1)
    rows, cols = reach.shape
    xs, _ = gridm.cell_center(0, np.arange(cols), origin, PATH_RES)
    _, ys = gridm.cell_center(np.arange(rows), 0, origin, PATH_RES)

    def done(k: int | None, views: int, reason: str) -> Ceiling:
        return Ceiling(question.id, k, None if k is None else (k + 1) / T, views, reason)

    evidence = [i for i in question.evidence_ids if i in scene.instances]
    if not evidence:  # the evidence is a room: stand inside one of the asked rooms
        rooms = [r for r in scene.rooms if any(r.contains(x, y) for x, y in question.targets)]
        inside = np.zeros_like(reach)
        for r in rooms:
            x0, y0, x1, y1 = r.rect
            inside |= ((xs[None, :] > x0) & (xs[None, :] < x1)) & ((ys[:, None] > y0) & (ys[:, None] < y1))
        k = steps[usable & inside]
        return done(int(k.min()) if k.size else None, 0, "room reachable" if k.size else "room out of reach")
    K = camera.intrinsics(width, height)
    views = 0
    seen: list[int] = []
    for obj in evidence:
        px, py = (float(v) for v in scene.instances[obj].position[:2])
        dist = np.hypot(ys[:, None] - py, xs[None, :] - px)
        near = usable & (dist <= oracle.p.max_range_m)
        for k in np.unique(steps[near]):
            if (seen and k >= min(seen)) or views >= MAX_VIEWS:
                break
            ii, jj = np.nonzero(near & (steps == k))
            order = np.argsort(dist[ii, jj], kind="stable")
            # the cell nearest the object, then cells spread over the ring (other viewing directions)
            pick = np.unique(np.linspace(0, len(order) - 1, min(VIEWS_PER_STEP, len(order))).round().astype(int))
            hit = False
            for idx in order[pick]:
                cx, cy = float(xs[jj[idx]]), float(ys[ii[idx]])
                pose = Pose2D(x=cx, y=cy, yaw=math.atan2(py - cy, px - cx))
                frame = renderer.render(camera.camera_pose(pose), K, width, height)
                views += 1
                if perceived(frame, obj, oracle, width * height):
                    hit = True
                    break
            if hit:
                seen.append(int(k))
                break
    if seen:
        return done(min(seen), views, "perceivable")
    return done(None, views, "not perceivable within T" if near_any(usable, evidence, scene, xs, ys, oracle)
                else "out of reach within T")


def perceived(frame: Any, instance: int, oracle: Any, pixels: int) -> bool:
    """Whether the simulated perception model perceives ``instance`` in a rendered frame (quality > 0)."""
    mask = frame.instances == instance
    if not mask.any():
        return False
    d = frame.depth[mask]
    d = d[np.isfinite(d) & (d > 0)]
    return oracle.view_quality(float(mask.sum()) / pixels, float(np.median(d)) if d.size else None) > 0


def near_any(usable: np.ndarray, evidence: Sequence[int], scene: Any, xs: np.ndarray, ys: np.ndarray,
             oracle: Any) -> bool:
    """Whether any cell reachable within the budget lies within the perception model's range of an evidence object."""
    for obj in evidence:
        px, py = (float(v) for v in scene.instances[obj].position[:2])
        if (usable & (np.hypot(ys[:, None] - py, xs[None, :] - px) <= oracle.p.max_range_m)).any():
            return True
    return False


def ceiling_cdf(ceilings: Sequence[Ceiling], budgets: Sequence[float]) -> list[float]:
    """Share of questions whose evidence can be perceived within each normalised budget (the curve above every
    strategy's first-evidence CDF)."""
    if not ceilings:
        return [math.nan] * len(budgets)
    return [float(np.mean([c.first_at is not None and c.first_at <= b + 1e-9 for c in ceilings])) for b in budgets]


def benchmark_ceilings(questions: Sequence[Any], settings: Any, width: int, height: int) -> list[Ceiling]:
    """:func:`question_ceiling` of every question (scenes and renderers loaded once per house)."""
    from services.planner.step import PlannerParams
    from services.sim.library import load_or_generate
    from services.sim.render import Renderer
    from services.vlm_scorer.backends.oracle import OracleBackend

    oracle = OracleBackend.from_settings(settings)
    step_m = PlannerParams().max_step_m
    out: list[Ceiling] = []
    by_scene: dict[str, list[Any]] = {}
    for q in questions:
        by_scene.setdefault(q.scene, []).append(q)
    for scene_id, qs in by_scene.items():
        scene = load_or_generate(scene_id, settings.scenes_path)
        renderer = Renderer(scene)
        out += [question_ceiling(q, scene, renderer, oracle, width, height, step_m) for q in qs]
    return out
