"""One planning step of a HELIOS task episode: the state machine's action (:mod:`services.planner.task_fsm`) turned
into the step's goal on the 2D map.

* ``frontier`` -> :func:`services.planner.step.plan_step` towards that one frontier (same paths, clearances,
  commitment and turning-in-place rules as question episodes);
* ``move`` / ``pick`` / ``place`` / ``stop`` -> :func:`plan_to_pose`: a collision-free path to the gaze pose
  (at most ``max_step_m`` per step, like every goal); the skill is asked for only on the step the robot arrives
  (``Goal.skill``), before that the goal is a plain move; a pose that cannot be reached takes the option away
  for this step (:meth:`~services.planner.task_fsm.TaskMachine.unreachable`) and the machine decides again;
  a frontier the machine sets out for goes into Eq. 9's ``F'``; when every frontier is one gone to, all are
  options again; when no action can be planned at all, the robot backs out to a more open point
  (:func:`escape_move`);
* ``done`` -> ``Goal.done`` with the reason.

One collision model (:mod:`eqa.robot`): every path of a task step -- to a frontier, a gaze point or a skill
pose -- keeps :func:`eqa.robot.mapped_clearance_m` (the collision radius plus the map margin) from the mapped
occupied cells. A path that would come closer is cut before it does (a robot already closer may move away,
never nearer); the planning grid's clearance levels only choose the route. A skill pose (``pick`` / ``place`` /
``stop``) is a reachable point of the map that keeps that clearance and lies within
:data:`SKILL_REACH_M` of the object's estimated footprint -- the robot is sent exactly there, so the arrival
tolerance of gaze poses does not eat into the reach; among such points the one nearest the machine's preferred
pose (on the line to the chosen gaze point, :data:`~services.planner.task_fsm.SKILL_APPROACH_M` from the
centre, where the fixed head camera sees the object) is taken.

Frontier values for Eq. 10 come from ``Frontier.sv`` (the value map's score of the frontier for the class being
searched, in [0, 1]).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from eqa import grid as gridm
from eqa import robot as body
from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner.helios import FrontierOption, Travel
from services.planner.paths import MapError, PlanningGrid, check_map, planning_grid, truncate
from services.planner.step import Memory, PlannerParams, StepPlan, disk_mask, full_turn, look_around, plan_step, wrap
from services.planner.task_fsm import ARRIVE_TOLERANCE_M, Action, SeenObject, SkillOutcome, TaskMachine

# A skill pose lies this far from the object's estimated footprint at most: the oracle pick's reach less a margin
# for the footprint's error (Gaussians of a partly seen object; this implementation's choice, by hand).
SKILL_REACH_MARGIN_M = 0.2
SKILL_REACH_M = body.REACH_M - SKILL_REACH_MARGIN_M
MAX_TRIES = 64  # actions asked of the machine in one step at most (each failed one removes an option)


def cut_clearances(levels: tuple[float, ...], need_m: float) -> tuple[float, ...]:
    """The planning clearance levels that keep ``need_m`` (the mapped clearance every task path is cut at):
    a route planned closer to an obstacle is cut there and the robot creeps along it. ``need_m`` itself is
    the last level."""
    return (*(c for c in levels if c > need_m), need_m)


def clearance_field(grid: GridSpec, occupied: np.ndarray) -> np.ndarray:
    """Metres from each cell centre to the nearest mapped occupied cell centre (inf with none)."""
    occ = np.asarray(occupied, bool)
    if not occ.any():
        return np.full(occ.shape, np.inf)
    return ndimage.distance_transform_edt(~occ) * grid.resolution


def _clearance_at(field: np.ndarray, grid: GridSpec, pts: np.ndarray) -> np.ndarray:
    i, j = gridm.cell_of(pts[:, 0], pts[:, 1], gridm.origin_of(grid), grid.resolution)
    ok = gridm.inside(i, j, field.shape)
    out = np.zeros(len(pts))
    out[ok] = field[i[ok], j[ok]]
    return out


def safe_prefix(path: list[tuple[float, float]], field: np.ndarray, grid: GridSpec,
                need_m: float | None = None) -> tuple[list[tuple[float, float]], bool]:
    """``path`` cut before the first point closer than ``need_m`` (default: the mapped clearance of
    :mod:`eqa.robot`) to a mapped occupied cell -- or, when the start is already closer, before the first
    point closer than the start (sampled every half cell). Returns the kept path and whether it is whole."""
    need = body.mapped_clearance_m() if need_m is None else need_m
    if len(path) < 2:
        return list(path), True
    step = grid.resolution / 2
    start = float(_clearance_at(field, grid, np.array([path[0]], float))[0])
    floor = min(need, start) - 1e-9
    out = [path[0]]
    for a, b in itertools.pairwise(path):
        seg = math.dist(a, b)
        n = max(2, math.ceil(seg / step) + 1)
        t = np.linspace(0.0, 1.0, n)[1:]
        pts = np.array(a)[None] + t[:, None] * (np.array(b) - np.array(a))[None]
        bad = np.flatnonzero(_clearance_at(field, grid, pts) < floor)
        if bad.size:
            k = int(bad[0])
            if k > 0:
                out.append((float(pts[k - 1, 0]), float(pts[k - 1, 1])))
            return out, False
        out.append(b)
    return out, True


ESCAPE_RADIUS_M = 1.5  # how far a stuck robot looks for a more open point
ESCAPE_MIN_M = 0.3  # and how far at least it moves (a point next to it plans no differently)
ESCAPE_OPEN_M = 0.1  # a robot that keeps the mapped clearance looks for this much more of it


def escape_move(grid: GridSpec, free: np.ndarray, field: np.ndarray, pose: Pose2D, memory: Memory,
                radius_m: float = ESCAPE_RADIUS_M) -> StepPlan | None:
    """No action could be planned from where the robot stands: it is closer than the mapped clearance to a
    mapped obstacle (the map grew around it, or a path was cut into a gap), or the planning grid's blocks
    around it are shut; turning in place does not change either. A straight move to the nearest known-free
    point between ESCAPE_MIN_M and ``radius_m`` away that keeps the mapped clearance (ESCAPE_OPEN_M more when
    the robot already keeps it), never coming closer to an obstacle than the robot is now
    (:func:`safe_prefix`). None: no such point."""
    need = body.mapped_clearance_m()
    here = float(_clearance_at(field, grid, np.array([[pose.x, pose.y]]))[0])
    want = need if here < need else need + ESCAPE_OPEN_M
    origin = gridm.origin_of(grid)
    r0, c0 = gridm.cell_of_point(pose.x, pose.y, origin, grid.resolution)
    k = math.ceil(radius_m / grid.resolution)
    rows = np.arange(max(0, r0 - k), min(grid.rows, r0 + k + 1))
    cols = np.arange(max(0, c0 - k), min(grid.cols, c0 + k + 1))
    R, C = np.meshgrid(rows, cols, indexing="ij")
    ok = np.asarray(free, bool)[R, C] & (field[R, C] >= want)
    x, y = gridm.cell_center(R[ok], C[ok], origin, grid.resolution)
    d = np.hypot(x - pose.x, y - pose.y)
    for i in np.argsort(d, kind="stable")[:400]:
        if d[i] > radius_m:
            break
        if d[i] < ESCAPE_MIN_M:
            continue
        goal = (float(x[i]), float(y[i]))
        path, whole = safe_prefix([(pose.x, pose.y), goal], field, grid, need)
        if whole:
            yaw = wrap(math.atan2(goal[1] - pose.y, goal[0] - pose.x))
            why = (f"closer than {need:.2f} m to an obstacle ({here:.2f} m)" if here < need
                   else "no action can be planned from here")
            return StepPlan("move", f"{why}: backing out to ({goal[0]:.2f}, {goal[1]:.2f}), {float(d[i]):.2f} m "
                            "away, where more room is", pose=Pose2D(x=goal[0], y=goal[1], yaw=yaw), path=path,
                            clearance_m=want, memory=memory.copy())
    return None


@dataclass
class PoseStep:
    plan: StepPlan | None  # None: the pose cannot be reached
    arrived: bool
    reason: str


def _box_distance(x: np.ndarray, y: np.ndarray, near: tuple[float, float, float, float]) -> np.ndarray:
    ox, oy, hx, hy = near
    return np.hypot(np.maximum(np.abs(x - ox) - hx, 0.0), np.maximum(np.abs(y - oy) - hy, 0.0))


def plan_to_pose(grid: GridSpec, free: np.ndarray, occupied: np.ndarray, robot: Pose2D,
                 target: tuple[float, float, float], params: PlannerParams | None = None,
                 near: tuple[float, float, float, float] | None = None,
                 dist_field: np.ndarray | None = None,
                 refused: list[tuple[float, float]] | None = None) -> PoseStep:
    """A path from ``robot`` to the pose ``target = (x, y, yaw)`` with clearance (tried at each of
    ``params.clearances_m``), cut at ``params.max_step_m`` and before it comes closer than the mapped clearance
    to an occupied cell (module doc; ``dist_field``: :func:`clearance_field`, computed when not given). On arrival
    the robot stands at the target (or the nearest traversable point within :data:`ARRIVE_TOLERANCE_M`)
    facing ``yaw``. ``near = (x, y, half_x, half_y)``: a skill pose for that object footprint -- the
    reachable point within :data:`SKILL_REACH_M` of it keeping the mapped clearance, nearest the target,
    facing the object's centre (module doc). ``refused``: goal positions the simulator refused in this episode
    (``Memory.refused``); the path and the pose keep ``params.refused_radius_m`` from them, as frontier steps
    do -- without it a refused skill or gaze pose is planned again at every attempt and every step (the same
    block stays the nearest to the preferred pose), and the robot turns in place to the end of the episode."""
    params = params or PlannerParams()
    try:
        check_map(grid, free, occupied)
    except MapError as exc:
        return PoseStep(None, False, f"malformed map: {exc}")
    dist_field = clearance_field(grid, occupied) if dist_field is None else dist_field
    tx, ty, tyaw = target
    need = body.mapped_clearance_m()
    if near is not None:
        here = float(_box_distance(np.array([robot.x]), np.array([robot.y]), near)[0])
        if here <= SKILL_REACH_M and math.hypot(tx - robot.x, ty - robot.y) <= ARRIVE_TOLERANCE_M:
            yaw = math.atan2(near[1] - robot.y, near[0] - robot.x)
            pose = Pose2D(x=robot.x, y=robot.y, yaw=wrap(yaw))
            return PoseStep(StepPlan("move", "within reach: turning to face the object", pose=pose,
                                     path=[(robot.x, robot.y)]), True, "arrived")
    elif math.hypot(tx - robot.x, ty - robot.y) <= 0.05:
        pose = Pose2D(x=robot.x, y=robot.y, yaw=wrap(tyaw))
        return PoseStep(StepPlan("move", "at the pose: turning to face it", pose=pose,
                                 path=[(robot.x, robot.y)]), True, "arrived")
    extra = disk_mask(grid, list(refused or ()), params.refused_radius_m)
    for clearance in params.clearances_m:
        pg = planning_grid(grid, free, occupied, clearance, params.coarse_m, params.max_blocks, extra)
        if not pg.search_from(robot.x, robot.y, params.snap_radius_m) or pg.dist is None:
            continue
        cxy = (near[0], near[1]) if near is not None else (tx, ty)
        span = ARRIVE_TOLERANCE_M if near is None else SKILL_REACH_M + max(near[2], near[3])
        ii, jj, cx, cy, geo = pg.reached_near(*cxy, span)
        if ii.size == 0:
            continue
        e = np.hypot(cx - tx, cy - ty)
        if near is not None:
            ok = (_box_distance(cx, cy, near) <= SKILL_REACH_M) & (
                _clearance_at(dist_field, grid, np.stack([cx, cy], axis=1)) >= need)
            ii, jj, e, geo = ii[ok], jj[ok], e[ok], geo[ok]
            if ii.size == 0:
                continue
        elif float(e.min()) > ARRIVE_TOLERANCE_M:
            continue
        m = int(np.argmin(e + 1e-3 * geo))
        block = (int(ii[m]), int(jj[m]))
        pulled, complete, full = pg.world_path(block, params.max_step_m)
        if not pulled:
            continue
        path, fits = truncate(pulled, params.max_step_m)
        arrived = fits and complete
        if (near is None and arrived and pg.segment_clear(path[-1], (tx, ty))
                and math.dist(path[-1], (tx, ty)) > 1e-6):
            path = [*path, (tx, ty)]
            path, fits = truncate(path, params.max_step_m)
            arrived = fits
        path, whole = safe_prefix(path, dist_field, grid, need)
        arrived = arrived and whole
        if len(path) < 2 and not arrived:
            continue
        gx, gy = path[-1]
        if arrived and near is not None:
            yaw = math.atan2(near[1] - gy, near[0] - gx)
        elif arrived:
            yaw = tyaw
        else:
            (ax, ay), (bx, by) = path[-2] if len(path) > 1 else (robot.x, robot.y), path[-1]
            yaw = math.atan2(by - ay, bx - ax) if math.hypot(bx - ax, by - ay) > 1e-6 else robot.yaw
        what = "arrives at" if arrived else "heads for"
        plan = StepPlan("move", f"{what} ({tx:.2f}, {ty:.2f}) (clearance {pg.clearance_m:.2f} m)",
                        pose=Pose2D(x=gx, y=gy, yaw=wrap(yaw)), path=path, full_path=full,
                        clearance_m=pg.clearance_m)
        return PoseStep(plan, arrived, plan.reason)
    return PoseStep(None, False, f"no path to ({tx:.2f}, {ty:.2f}) with clearance")


# a frontier or a receptacle's centre counts as reached from a traversable block this near it (a receptacle's
# half-size and more; wall and clearance keep the blocks on the far side of a wall farther than this from it)
TRAVEL_REACH_M = 1.2


def travel_distances(grid: GridSpec, free: np.ndarray, occupied: np.ndarray, robot: Pose2D,
                     params: PlannerParams) -> Travel:
    """``dist`` of Eq. 10 as the way the robot would travel (``EQA_HELIOS_DISTANCE=path``): to a point, the
    geodesic on the planning grid from the robot to the nearest reachable block within :data:`TRAVEL_REACH_M` of
    it plus the straight rest, at the first of ``params.clearances_m`` that has such a block (the levels the
    paths are planned at). A point with none at any level gets the straight line: no path is known, and the
    planner drops the option when its path fails. The grids are built on the first query."""
    levels: list[PlanningGrid | None] = []

    def level(k: int) -> PlanningGrid | None:
        while len(levels) <= k:
            pg = planning_grid(grid, free, occupied, params.clearances_m[len(levels)], params.coarse_m,
                               params.max_blocks)
            levels.append(pg if pg.search_from(robot.x, robot.y, params.snap_radius_m) else None)
        return levels[k]

    def travel(x: float, y: float) -> float:
        for k in range(len(params.clearances_m)):
            pg = level(k)
            if pg is None:
                continue
            _, _, cx, cy, geo = pg.reached_near(x, y, TRAVEL_REACH_M)
            rest = np.hypot(cx - x, cy - y)
            near = rest <= TRAVEL_REACH_M
            if near.any():
                return float(np.min(geo[near] + rest[near]))
        return math.hypot(x - robot.x, y - robot.y)

    return travel


@dataclass
class TaskStep:
    """The goal of one task step: a plan (or done), the skill to run on arrival, the phase for events."""

    plan: StepPlan
    skill: str = "move"
    target: int | None = None
    phase: str = "searching"
    memory: Memory = field(default_factory=Memory)


def frontier_options(frontiers: list[Frontier]) -> list[FrontierOption]:
    return [FrontierOption(i, f.x, f.y, f.sv) for i, f in enumerate(frontiers)
            if all(math.isfinite(v) for v in (f.x, f.y, f.sv))]


def committed_option(memory: Memory, options: list[FrontierOption], params: PlannerParams) -> int | None:
    """The frontier option the robot is on its way to: the one nearest the committed target of
    :class:`~services.planner.step.Memory`, within ``commit_radius_m``, while the commitment lasts
    (``max_commit_steps``) -- :func:`services.planner.step.plan_step`'s rule 4, applied to the machine's choice
    so that it holds across steps (:func:`services.planner.helios.choose`). None: no commitment."""
    t = memory.target
    if t is None or memory.committed_steps >= params.max_commit_steps or not options:
        return None
    d, idx = min((math.hypot(o.x - t.x, o.y - t.y), o.index) for o in options)
    return idx if d <= params.commit_radius_m else None


def task_step(machine: TaskMachine, grid: GridSpec, free: np.ndarray, occupied: np.ndarray, pose: Pose2D,
              frontiers: list[Frontier], objects: list[SeenObject], outcome: SkillOutcome | None,
              memory: Memory, rng: np.random.Generator, params: PlannerParams | None = None,
              max_tries: int = MAX_TRIES, step: int | None = None) -> TaskStep:
    """Ask the machine for its action and plan it (module doc). ``memory`` is the planner's frontier memory
    (not modified; the result carries the one to keep). An action that cannot be planned takes its option away
    (the frontier, the gaze point, the instance: :meth:`TaskMachine.unreachable`) and the machine is asked
    again; when ``max_tries`` actions all fail the robot turns in place to see more (a new frame, new options)
    rather than ending the episode with steps left. ``step``: the episode's step index; with the machine's
    ``max_steps`` it gives the goals left (this one and those after it) for the machine's deadline."""
    params = params or PlannerParams()
    if machine.th.path_clearance == "cut":
        params = params.model_copy(update={"clearances_m": cut_clearances(params.clearances_m,
                                                                          body.mapped_clearance_m())})
    machine.begin_step()
    robot = (pose.x, pose.y, pose.yaw)
    # the goal of step s is carried out at step s + 1; the episode's last frame is step max_steps - 1
    steps_left = machine.max_steps - 1 - step if machine.max_steps is not None and step is not None else None
    dist_field = clearance_field(grid, occupied) if np.shape(occupied) == (grid.rows, grid.cols) else None
    travel = travel_distances(grid, free, occupied, pose, params) \
        if machine.th.distance == "path" and dist_field is not None and np.shape(free) == np.shape(occupied) else None
    # frontiers the robot already went to are no option (plan_step would refuse them and turn in place) -- while
    # others are left: when every frontier is one gone to, they are all options again (the map around them has
    # changed; ending the search with steps left finds nothing)
    every = frontier_options(frontiers)
    options = [o for o in every
               if not any(math.hypot(o.x - vx, o.y - vy) <= params.visited_radius_m for vx, vy in memory.visited)]
    reopened = not options and bool(every)
    if reopened:
        options = every
        memory = memory.copy()
        memory.visited = []
    turn: TaskStep | None = None  # plan_step's turn in place (it counts the turns) for an unreachable frontier
    circle_left = max(full_turn(params) - memory.turns, 0)
    looked_around = circle_left == 0 or (steps_left is not None and steps_left <= circle_left + 1)
    for _ in range(max_tries):
        committed = committed_option(memory, options, params)
        act: Action = machine.step(robot, options, objects, outcome, committed, steps_left, params.max_step_m,
                                   travel, looked_around)
        outcome = None  # consumed
        if act.kind == "done":
            out = escape_move(grid, free, dist_field, pose, memory) if turn is not None and dist_field is not None \
                else None
            if out is not None:
                machine.finished, machine.phase = None, "searching"
                return TaskStep(out, "move", None, "searching", out.memory)
            if turn is not None:
                # out of options only because this step's frontiers proved unreachable (a skill outcome ends
                # the episode on the first try, before any): turn in place to see more, plan_step's rule
                machine.finished, machine.phase = None, "searching"
                return turn
            if act.exhausted:
                # nothing mapped is left to search: new frames from here may open frontiers the map has not
                # got yet (a doorway seen edge-on); a full circle of turns in place first, plan_step's rule
                look = look_around(act.reason, pose, len(frontiers), memory.copy(), params)
                if look.kind == "turn":
                    machine.finished, machine.phase = None, "searching"
                    return TaskStep(look, "move", None, "searching", look.memory)
                return TaskStep(look, phase="finished", memory=memory)
            return TaskStep(StepPlan("done", act.reason, memory=memory.copy()), phase="finished", memory=memory)
        if act.kind == "frontier":
            assert act.ref is not None
            plan = plan_step(grid, free, occupied, pose, [frontiers[act.ref]], "fbe", memory, rng, params)
            if plan.kind == "move" and dist_field is not None:
                plan = _keep_clear(plan, grid, dist_field, pose, memory)
            if plan.kind in ("done", "turn"):  # that frontier cannot be reached: let the machine choose again
                options = [o for o in options if o.index != act.ref]
                if plan.kind == "turn" and turn is None:
                    turn = TaskStep(plan, "move", None, act.phase, plan.memory)
                continue
            # the machine chose the frontier (Eq. 10): its reason, then the path; the path planner's own choice
            # among the one frontier it was given ("uniform over reachable frontiers") decided nothing
            plan.reason = f"{act.reason}; {plan.route or plan.reason}"
            if reopened:
                plan.reason += "; every frontier left is one gone to before: all are options again"
            if act.ref != committed:
                machine.memory.choose_frontier(next(o for o in options if o.index == act.ref))  # F' (Eq. 9)
            return TaskStep(plan, "move", None, act.phase, plan.memory)
        assert act.pose is not None
        ps = plan_to_pose(grid, free, occupied, pose, act.pose, params, near=act.near, dist_field=dist_field,
                          refused=memory.refused)
        if ps.plan is None:
            if act.ref is not None:
                machine.unreachable(act.ref, act)
            continue
        ps.plan.reason = f"{act.reason}; {ps.plan.reason}"
        skill = act.kind if act.kind in ("pick", "place", "stop") and ps.arrived else "move"
        kept = memory.copy()
        if ps.plan.kind == "move":
            kept.turns = 0  # a look-around's full circle counts from where the robot stands
        return TaskStep(ps.plan, skill, act.ref, act.phase, kept)
    out = escape_move(grid, free, dist_field, pose, memory) if dist_field is not None else None
    if out is not None:
        return TaskStep(out, "move", None, machine.phase, out.memory)
    if turn is not None:
        return turn
    yaw = wrap(pose.yaw + math.radians(params.turn_deg))
    spin = StepPlan("turn", f"no reachable action after {max_tries} tries: turning in place to see more",
                    pose=Pose2D(x=pose.x, y=pose.y, yaw=yaw), path=[(pose.x, pose.y)], memory=memory.copy())
    return TaskStep(spin, "move", None, machine.phase, memory)


def _keep_clear(plan: StepPlan, grid: GridSpec, field: np.ndarray, pose: Pose2D, memory: Memory) -> StepPlan:
    """A frontier move cut before it comes closer than the mapped clearance to an occupied cell (module doc);
    ``done`` when nothing of it is left. A cut move has not arrived: the frontier is not marked visited."""
    path, whole = safe_prefix(plan.path, field, grid)
    if whole:
        return plan
    if len(path) < 2 or math.dist(path[0], path[-1]) < 0.05:
        return StepPlan("done", "the path to the frontier comes closer than the collision radius to an obstacle",
                        memory=memory.copy())
    (ax, ay), (bx, by) = path[-2], path[-1]
    mem = plan.memory.copy()
    mem.visited = list(memory.visited)
    plan.path = path
    plan.pose = Pose2D(x=bx, y=by, yaw=wrap(math.atan2(by - ay, bx - ax)))
    plan.reason = f"{plan.reason}; cut at {bx:.2f}, {by:.2f} before an obstacle"
    plan.route = f"{plan.route}; cut at {bx:.2f}, {by:.2f} before an obstacle" if plan.route else ""
    plan.memory = mem
    return plan


def outcome_of(report: Any) -> SkillOutcome | None:
    """A :class:`SkillOutcome` from ``MapUpdate.skill`` (an ``eqa.messages.SkillReport``) or None."""
    if report is None:
        return None
    return SkillOutcome(report.skill, bool(report.success), report.target, report.reason)
