"""One planning step: from the map of step t to the next pose (Explore-EQA IV-B, IV-D, appendix B).

Rules, in order:

1. Frontiers that are malformed (non-finite), outside the map, near a frontier the robot already went to
   (it faced it from up close and it stayed unknown), or excluded for this step (the simulator refused a
   goal at it) are not candidates.
2. The robot's reachable space is searched at the full clearance (0.3 m); when no candidate is reachable
   there, again at the reduced clearances (0.2 m, then 0.1 m: doorways on the map are narrower than the
   real ones) (:mod:`services.planner.paths`).
3. A candidate is reachable when a reachable traversable point lies within ``approach_radius_m`` of it:
   its *approach point* (the reachable point nearest the frontier).
4. The committed far target of earlier steps is kept while a candidate lies within ``commit_radius_m`` of
   it; otherwise a new frontier is chosen by the strategy (:mod:`services.planner.sampling`), its weight
   multiplied by ``exp(-geodesic distance / distance_decay_m)`` for every strategy. The deterministic rules
   ``vlfm``, ``gain`` and ``topo`` (and the yardsticks ``perfect_vlfm`` / ``perfect_gain`` that run them on
   ground-truth values) rank the frontiers by value and distance instead and also drop a commitment whose
   value fell (:mod:`services.planner.frontier_rules`).
5. The robot moves along the path at most ``max_step_m`` (3 m). On arrival at the approach point it faces
   along the frontier normal (into the unknown) and the frontier is marked visited; on the way it faces
   along the path.
6. With no reachable candidate the robot turns in place by ``turn_deg`` to look around; after a full turn
   without any candidate the episode is done, with the reason.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from eqa import grid as gridm
from eqa.messages import Frontier, GridSpec, Pose2D, Strategy
from services.planner import frontier_rules, sampling
from services.planner.paths import MapError, PlanningGrid, check_map, path_length, planning_grid, truncate


class PlannerParams(BaseModel):
    """Planner constants (Explore-EQA: 3 m between poses; clearance kept from obstacles and unknown)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    max_step_m: float = Field(default=3.0, gt=0)
    # tried in order; the last (0.1 m, under the 0.2 m robot radius but on a map whose walls the voxels already
    # thicken by a cell) lets paths through 1 m doors that the mapped free space narrows to ~0.6 m
    clearances_m: tuple[float, ...] = (0.3, 0.2, 0.1)
    coarse_m: float = Field(default=0.2, gt=0)
    max_blocks: int = Field(default=400_000, ge=100)
    snap_radius_m: float = Field(default=1.0, ge=0)
    approach_radius_m: float = Field(default=1.5, gt=0)
    commit_radius_m: float = Field(default=1.0, ge=0)
    max_commit_steps: int = Field(default=12, ge=1)
    visited_radius_m: float = Field(default=0.75, ge=0)
    refused_radius_m: float = Field(default=0.35, ge=0)
    turn_deg: float = Field(default=60.0, gt=0, le=180)
    # exp(-geodesic / decay) on the sampling weight of every strategy (the reference code's dist_T, 10 m there);
    # 3 m: fbe observes 94 % of the reachable floor of 20 generated houses within T (92 % with 10 m, 91 % off)
    distance_decay_m: float | None = Field(default=3.0, ge=0)
    # the deterministic rules vlfm / gain / topo (services.planner.frontier_rules), chosen on the tuning seed 11
    # (eqa_app/benches/tune_explore.py; docs/results/exploration-strategies.md): value units (ln SV) per metre of path
    rule_cost_per_m: float = Field(default=0.1, ge=0, le=10)
    rule_commit_margin: float = Field(default=0.1, ge=0, le=10)  # value units
    gain_weight: float = Field(default=0.5, ge=0, le=100)  # value units for a fully unknown disk
    gain_radius_m: float = Field(default=2.0, gt=0, le=10)
    topo_core_m: float = Field(default=0.5, gt=0, le=5)  # a room's core is farther than this from walls
    topo_hop_cost: float = Field(default=0.3, ge=0, le=100)  # value units per doorway

    def rule_params(self) -> frontier_rules.RuleParams:
        return frontier_rules.RuleParams(self.rule_cost_per_m, self.rule_commit_margin, self.gain_weight,
                                         self.gain_radius_m, self.topo_core_m, self.topo_hop_cost)


@dataclass
class Memory:
    """What the planner remembers of one episode between steps (copied, never shared, per attempt)."""

    target: Frontier | None = None
    committed_steps: int = 0
    visited: list[tuple[float, float]] = field(default_factory=list)
    refused: list[tuple[float, float]] = field(default_factory=list)
    turns: int = 0

    def copy(self) -> Memory:
        return dataclasses.replace(self, visited=list(self.visited), refused=list(self.refused))


@dataclass
class StepPlan:
    """The outcome of one step: a move, a turn in place, or done."""

    kind: str  # "move" | "turn" | "done"
    reason: str
    # A move to a frontier: the reason's part about the path alone (where to, how far, the clearance), without
    # the frontier's index and the strategy's note; for a caller that chose the frontier itself (a task step).
    route: str = ""
    pose: Pose2D | None = None
    path: list[tuple[float, float]] = field(default_factory=list)  # robot -> goal pose (<= max_step_m)
    full_path: list[tuple[float, float]] = field(default_factory=list)  # robot -> approach point
    frontier: Frontier | None = None
    frontier_index: int | None = None
    probabilities: list[float] = field(default_factory=list)  # per frontier, 0 when not a candidate
    clearance_m: float | None = None
    geodesic_m: list[float] = field(default_factory=list)  # per frontier, inf when not reachable
    sampled: bool = False  # the strategy chose the frontier this step (not a kept commitment)
    memory: Memory = field(default_factory=Memory)
    timing_ms: dict[str, float] = field(default_factory=dict)

    @property
    def done(self) -> bool:
        return self.kind == "done"


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _valid_frontier(f: Frontier, grid: GridSpec) -> str | None:
    if not all(math.isfinite(v) for v in (f.x, f.y, f.nx, f.ny)):
        return "non-finite position or normal"
    if not gridm.contains(grid, f.x, f.y):
        return "outside the map"
    return None


def _near(points: list[tuple[float, float]], x: float, y: float, r: float) -> bool:
    return any(math.hypot(px - x, py - y) <= r for px, py in points)


def disk_mask(grid: GridSpec, points: list[tuple[float, float]], r: float) -> np.ndarray | None:
    if not points or r <= 0:
        return None
    mask = np.zeros((grid.rows, grid.cols), dtype=bool)
    rc = math.ceil(r / grid.resolution)
    for x, y in points:
        ci, cj = gridm.cell_of_point(x, y, gridm.origin_of(grid), grid.resolution)
        i0, i1 = max(0, ci - rc), min(grid.rows, ci + rc + 1)
        j0, j1 = max(0, cj - rc), min(grid.cols, cj + rc + 1)
        if i0 >= i1 or j0 >= j1:
            continue
        ii, jj = np.mgrid[i0:i1, j0:j1]
        cx, cy = gridm.cell_center(ii, jj, gridm.origin_of(grid), grid.resolution)
        mask[i0:i1, j0:j1] |= np.hypot(cx - x, cy - y) <= r
    return mask


def approach_points(
    pg: PlanningGrid, frontiers: list[Frontier], ok: np.ndarray, radius_m: float
) -> tuple[list[tuple[int, int] | None], np.ndarray]:
    """For each frontier: the reachable block nearest to it within ``radius_m`` (None if none) and the
    geodesic distance robot -> block -> frontier (inf if unreachable)."""
    assert pg.dist is not None
    R, C = pg.dist.shape
    rad = math.ceil(radius_m / pg.block_m) + 1
    out: list[tuple[int, int] | None] = []
    geo = np.full(len(frontiers), np.inf)
    for n, f in enumerate(frontiers):
        if not ok[n]:
            out.append(None)
            continue
        bi, bj = pg.block_of(f.x, f.y)
        r0, r1 = max(0, bi - rad), min(R, bi + rad + 1)
        c0, c1 = max(0, bj - rad), min(C, bj + rad + 1)
        if r0 >= r1 or c0 >= c1:
            out.append(None)
            continue
        win = pg.dist[r0:r1, c0:c1]
        ii, jj = np.nonzero(np.isfinite(win))
        if ii.size == 0:
            out.append(None)
            continue
        cx, cy = pg.block_centre(ii + r0, jj + c0)
        e = np.hypot(cx - f.x, cy - f.y)
        within = e <= radius_m
        if not within.any():
            out.append(None)
            continue
        # nearest to the frontier; ties (same ring) broken by the geodesic distance from the robot
        score = np.where(within, e + 1e-3 * win[ii, jj], np.inf)
        m = int(np.argmin(score))
        out.append((int(ii[m] + r0), int(jj[m] + c0)))
        geo[n] = float(win[ii[m], jj[m]] + e[m])
    return out, geo


def _candidates(frontiers: list[Frontier], grid: GridSpec, mem: Memory, params: PlannerParams,
                exclude: list[tuple[float, float]] | None) -> tuple[np.ndarray, str]:
    """Rule 1: which frontiers are candidates, and a note counting the others by why they are not."""
    dropped: dict[str, int] = {}
    ok = np.zeros(len(frontiers), dtype=bool)
    for i, f in enumerate(frontiers):
        why = _valid_frontier(f, grid)
        if why is None and _near(mem.visited, f.x, f.y, params.visited_radius_m):
            why = "visited already"
        if why is None and exclude and _near(exclude, f.x, f.y, 0.5):
            why = "refused by the simulator this step"
        if why is None:
            ok[i] = True
        else:
            dropped[why] = dropped.get(why, 0) + 1
    return ok, "; ".join(f"{v} frontier(s) {k}" for k, v in dropped.items())


@dataclass
class _Reach:
    """Rules 2-3: the planning grid searched from the robot, and each frontier's approach point and geodesic
    distance (inf when unreachable)."""

    grid: PlanningGrid
    approach: list[tuple[int, int] | None]
    geodesic: np.ndarray
    reachable: np.ndarray
    start_found: bool


def _reach(grid: GridSpec, free: np.ndarray, occupied: np.ndarray, pose: Pose2D, frontiers: list[Frontier],
           ok: np.ndarray, mem: Memory, params: PlannerParams, timing: dict[str, float]) -> _Reach:
    """Search the reachable space at each clearance in turn until a candidate is reachable (rules 2-3)."""
    n = len(frontiers)
    extra = disk_mask(grid, mem.refused, params.refused_radius_m)
    pg: PlanningGrid | None = None
    approach: list[tuple[int, int] | None] = [None] * n
    geo = np.full(n, np.inf)
    reach = np.zeros(n, dtype=bool)
    start_found = False
    for clearance in params.clearances_m:
        pg = planning_grid(grid, free, occupied, clearance, params.coarse_m, params.max_blocks, extra)
        started = pg.search_from(pose.x, pose.y, params.snap_radius_m)
        for key, v in pg.timing_ms.items():
            timing[key] = timing.get(key, 0.0) + v
        if not started:
            continue
        start_found = True
        if not ok.any():
            break
        approach, geo = approach_points(pg, frontiers, ok, params.approach_radius_m)
        reach = np.isfinite(geo)
        if reach.any():
            break
    timing["search"] = timing.get("traversable", 0.0) + timing.get("dijkstra", 0.0)
    assert pg is not None
    return _Reach(pg, approach, geo, reach, start_found)


def _unreachable_reason(reached: _Reach, n: int, ok: np.ndarray, dropped_note: str, params: PlannerParams) -> str:
    if not reached.start_found:
        return (
            f"no free cell with {min(params.clearances_m):.2f} m clearance within "
            f"{params.snap_radius_m:.1f} m of the robot"
        )
    if n == 0:
        return "no frontier left: the map is fully explored"
    if not ok.any():
        return f"no usable frontier ({dropped_note})"
    return f"none of {int(ok.sum())} frontier(s) is reachable with clearance"


def full_turn(params: PlannerParams) -> int:
    """The turns in place of one full circle (rule 6)."""
    return math.ceil(360.0 / params.turn_deg)


def look_around(why: str, pose: Pose2D, n: int, mem: Memory, params: PlannerParams) -> StepPlan:
    """Rule 6: turn in place to look around, or done after a full turn without any candidate."""
    circle = full_turn(params)
    if mem.turns >= circle:
        return StepPlan("done", f"{why}, even after turning in place a full circle", memory=mem,
                        probabilities=[0.0] * n)
    mem.turns += 1
    mem.target = None
    mem.committed_steps = 0
    yaw = wrap(pose.yaw + math.radians(params.turn_deg))
    return StepPlan(
        "turn",
        f"{why}: turning in place to look around ({mem.turns}/{circle})",
        pose=Pose2D(x=pose.x, y=pose.y, yaw=yaw),
        path=[(pose.x, pose.y)],
        probabilities=[0.0] * n,
        memory=mem,
    )


def _choose(frontiers: list[Frontier], reached: _Reach, strategy: Strategy, mem: Memory, rng: np.random.Generator,
            params: PlannerParams, maps: tuple[GridSpec, np.ndarray, np.ndarray, np.ndarray | None],
            pose: Pose2D) -> tuple[int, np.ndarray, str, bool]:
    """Rule 4: the committed target if a candidate is still near it, else the strategy's pick; returns the
    frontier's index, the per-frontier probabilities, a note and whether the strategy sampled it. The
    deterministic rules (``vlfm``, ``gain``, ``topo``) keep or drop their commitment by value
    (:mod:`services.planner.frontier_rules`); ``maps``: (grid, free, occupied, explored) for them."""
    n = len(frontiers)
    probs = np.zeros(n)
    if frontier_rules.rule_of(strategy) is not None:
        committed = mem.target if mem.committed_steps < params.max_commit_steps else None
        idx_r, probs, note, fresh = frontier_rules.choose(
            strategy, frontiers, reached.reachable, reached.geodesic, *maps, (pose.x, pose.y),
            params.rule_params(), committed, params.commit_radius_m)
        assert idx_r is not None
        if fresh:
            mem.committed_steps = 0
        return idx_r, probs, note, fresh
    if mem.target is not None and mem.committed_steps < params.max_commit_steps:
        target = mem.target
        d = np.array([math.hypot(f.x - target.x, f.y - target.y) if reached.reachable[i] else np.inf
                      for i, f in enumerate(frontiers)])
        if d.size and float(d.min()) <= params.commit_radius_m:
            idx = int(np.argmin(d))
            probs[idx] = 1.0
            return idx, probs, f"kept the committed target (step {mem.committed_steps + 1} towards it)", False
    mem.committed_steps = 0
    idx, probs, note = sampling.choose(
        strategy, [f.weight for f in frontiers], reached.reachable, reached.geodesic, rng, params.distance_decay_m
    )
    assert idx is not None
    return idx, probs, note, True


def _advance(mem: Memory, frontier: Frontier, path: list[tuple[float, float]], arrived: bool, pose: Pose2D,
             strategy: Strategy, sampled: bool, committed: Frontier | None) -> tuple[float, str]:
    """The goal's yaw and what the step does to ``frontier``, with ``mem`` updated for the move: a frontier
    arrived at is visited (face it, drop the target); else it is the target kept (face along the path's last
    leg), one more step committed to it."""
    if arrived:
        mem.visited.append((frontier.x, frontier.y))
        mem.target = None
        mem.committed_steps = 0
        mem.turns = 0
        return math.atan2(frontier.ny, frontier.nx), "arrives at"
    (ax, ay), (bx, by) = path[-2], path[-1]
    yaw = math.atan2(by - ay, bx - ax) if math.hypot(bx - ax, by - ay) > 1e-6 else pose.yaw
    mem.target = frontier
    if frontier_rules.rule_of(strategy) is not None and not sampled and committed is not None:
        # the rules compare a kept target's value with its value when it was chosen
        mem.target = frontier.model_copy(update={"sv": committed.sv, "sv_normal": committed.sv_normal})
    mem.committed_steps += 1
    mem.turns = 0
    return yaw, "heads for"


def plan_step(
    grid: GridSpec,
    free: np.ndarray,
    occupied: np.ndarray,
    pose: Pose2D,
    frontiers: list[Frontier],
    strategy: Strategy,
    memory: Memory,
    rng: np.random.Generator,
    params: PlannerParams | None = None,
    exclude: list[tuple[float, float]] | None = None,
    explored: np.ndarray | None = None,
) -> StepPlan:
    """Plan the next pose of one step (module doc). Never raises for bad maps: returns ``done`` with the
    reason instead. ``memory`` is not modified; the plan carries the memory to keep if the goal is taken.
    ``explored``: the mapper's explored plane (the ``gain`` rule's unknown area; same shape as ``free``)."""
    params = params or PlannerParams()
    t_start = time.perf_counter()
    mem = memory.copy()
    timing: dict[str, float] = {}

    def finish(plan: StepPlan) -> StepPlan:
        timing["step"] = (time.perf_counter() - t_start) * 1e3
        plan.timing_ms = timing
        return plan

    try:
        check_map(grid, free, occupied)
    except MapError as exc:
        return finish(StepPlan("done", f"malformed map: {exc}", memory=mem))
    _, _, x1, y1 = gridm.bounds(grid)
    if not gridm.contains(grid, pose.x, pose.y):
        return finish(
            StepPlan(
                "done",
                f"robot pose ({pose.x:.2f}, {pose.y:.2f}) is outside the map "
                f"x [{grid.origin_x:.2f}, {x1:.2f}) y [{grid.origin_y:.2f}, {y1:.2f})",
                memory=mem,
            )
        )

    n = len(frontiers)
    ok, dropped_note = _candidates(frontiers, grid, mem, params, exclude)
    reached = _reach(grid, free, occupied, pose, frontiers, ok, mem, params, timing)
    if not reached.reachable.any():
        return finish(look_around(_unreachable_reason(reached, n, ok, dropped_note, params), pose, n, mem, params))

    if explored is not None and np.shape(explored) != np.shape(free):
        return finish(StepPlan("done", f"malformed map: explored {np.shape(explored)} but free {np.shape(free)}",
                               memory=mem))
    committed = mem.target
    idx, probs, note, sampled = _choose(frontiers, reached, strategy, mem, rng, params,
                                        (grid, free, occupied, explored), pose)
    frontier = frontiers[idx]
    pg, geo = reached.grid, reached.geodesic
    target_block = reached.approach[idx]
    assert target_block is not None
    pulled, complete, full = pg.world_path(target_block, params.max_step_m)
    if not pulled:
        return finish(StepPlan("done", "internal: no path to a reachable block", memory=mem))
    path, fits = truncate(pulled, params.max_step_m)
    arrived = fits and complete
    gx, gy = path[-1]
    yaw, what = _advance(mem, frontier, path, arrived, pose, strategy, sampled, committed)
    moved = path_length(path)
    route = (f"({frontier.x:.1f}, {frontier.y:.1f}) moving {moved:.1f} of {float(geo[idx]):.1f} m "
             f"(clearance {pg.clearance_m:.2f} m)")
    reason = f"{note}; {what} frontier {idx} {route}"
    if dropped_note:
        reason += f"; {dropped_note}"
    return finish(
        StepPlan(
            "move",
            reason,
            route=f"{what} the frontier at {route}",
            pose=Pose2D(x=gx, y=gy, yaw=wrap(yaw)),
            path=path,
            full_path=full,
            frontier=frontier,
            frontier_index=idx,
            probabilities=[float(v) for v in probs],
            clearance_m=pg.clearance_m,
            geodesic_m=[float(v) for v in geo],
            sampled=sampled,
            memory=mem,
        )
    )
