"""The HELIOS task state machine (paper Fig. 3, sections 3.2, 4.1, 4.2; appendix 6.1): what the robot does next
in a ``pick_place`` or ``find_object`` task, from the object layer's instances and the map's frontiers.

One call of :meth:`TaskMachine.step` per planner step returns one :class:`Action`:

* ``frontier`` -- go to frontier ``ref`` (the shell plans the path) -- phase ``searching``;
* ``move`` -- go to a gaze pose -- phase ``local_search`` (the gaze points of a start-receptacle candidate, all of
  them, nearest first) or ``looking`` (the single best gaze point of a target / goal candidate);
* ``pick`` / ``place`` -- go to the pose and call the skill on instance ``ref`` -- phases ``picking`` /
  ``placing``; the simulator answers with a :class:`SkillOutcome` passed to the next step;
* ``stop`` -- ``find_object`` only: the stop call near the found object;
* ``done`` -- the episode ends (``success`` says whether the task was achieved, as far as the planner knows).

The order of decisions each step (the flow chart): holding the object -> the goal-receptacle decision (Eq. 11
with ``tau_b``; with no candidate or none worth a look: the frontier of highest value); not holding -> the
target decision (Eq. 11 with ``tau_g``), then the local search in progress, then the global search objective
(Eq. 10, :mod:`services.planner.helios`). A pick that fails (the oracle pick: target not in frame or not within
reach) counts against the pick limit (:class:`~services.planner.decisions.PickBudget`); the instance is ruled out
after :data:`MAX_FAILS_PER_INSTANCE` failures. A candidate is looked at from at most
:attr:`Thresholds.max_looks` gaze points; then the look rule passes to the next candidate. With no frontier
left, what was ruled out reopens (gaze points looked from, searched start receptacles, instances unreachable);
then, with candidates of the phase's class known, the machine acts on the best of them (no pick under a pick
limit) rather than end the episode with steps left. A skill pose the planner cannot reach leaves the instance out
of that step; :data:`MAX_UNREACHABLE_STEPS` such steps rule it out. With the step budget known
(``deadline`` ``commit``), the machine acts on the best known candidate of the phase's class once the steps left
are only enough to reach it (:meth:`TaskMachine._deadline`): a robot out of steps with the object in its gripper
has failed for certain, a place on the best goal receptacle it knows may succeed.
Ablations: ``trusting`` has no 3D layer (the mapper gives it each frame's detections
alone) and acts on the first detection, going to it until the skill was tried (no gaze choice, no objective);
``no_global`` always prefers a candidate over a frontier.

The state is plain data (:meth:`TaskMachine.to_json` / :meth:`TaskMachine.from_json`) so a restarted planner
continues the task where it was.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from services.planner import helios
from services.planner.decisions import PickBudget, Scored, decide
from services.planner.helios import Ablation, CandidateObservation, FrontierOption, SearchMemory

ActionKind = Literal["frontier", "move", "pick", "place", "stop", "done"]
Phase = Literal["searching", "local_search", "looking", "picking", "placing", "finished"]
MAX_FAILS_PER_INSTANCE = 2
# The steps to reach a candidate, estimated from the straight line (paths in a house bend round furniture and
# through doors) at the planner's step length, and the steps kept in hand (this implementation's estimate).
DEADLINE_DETOUR = 1.5
DEADLINE_MARGIN_STEPS = 1
# A gaze pose counts as reached within this distance, here and in the path planner (task_step): one tolerance,
# because a point the planner calls reached but the machine does not is asked for again at every step.
ARRIVE_TOLERANCE_M = 0.5
# An instance whose skill pose cannot be planned is left out of the decisions of that step only (the map grows and
# the next step may reach it); after this many such steps it is ruled out (this implementation's bound).
MAX_UNREACHABLE_STEPS = 3
# A pickable object is small: its reach is measured to a footprint of at most this half-size around the estimated
# centre. The footprint of its Gaussians grows with depth noise and with what lies around it (a towel's Gaussians
# reach onto the cabinet), and a pick called within reach of that footprint found the object farther than the
# arm's reach (evaluation traces: 4 of 21 failed picks).
PICKABLE_HALF_M = 0.15
# The pose of a pick / place / stop: on the line from the object's centre to the chosen gaze point (or to the
# robot when the object has no gaze point), this far from the centre, facing the object. The gaze contour lies
# gaze_radius_m (0.9 m) beyond the footprint of the object's Gaussians, the very reach of the oracle pick
# (0.9 m from the object's true box, services/sim/skills.py): with the planner's arrival tolerance (0.5 m)
# and a footprint seen from one side, a skill called from a gaze point was out of reach (tuning
# seed 11). 0.6 m leaves 0.3 m for both.
SKILL_APPROACH_M = 0.6


@dataclass(frozen=True)
class Gaze:
    x: float
    y: float
    yaw: float
    pitch: float = 0.0
    psi_prime: float = -math.inf
    ig: float = 0.0


@dataclass(frozen=True)
class SeenObject:
    """One object-layer instance as the machine reads it: per task class ``(S, U, Psi)``, the optimistic IG of
    its believed class, its centre and gaze points (from ``MapUpdate.objects``, see :func:`from_instance`)."""

    instance_id: int
    cls: str
    scores: dict[str, tuple[float, float, float]]
    x: float
    y: float
    ig: float = math.nan  # NaN: not computed (no gaze point, no pose set P for Eq. 12)
    gaze: tuple[Gaze, ...] = ()
    half: tuple[float, float] = (0.0, 0.0)  # half-sizes of the footprint of its Gaussians (x, y)

    def of(self, c: str) -> tuple[float, float, float] | None:
        return self.scores.get(c)

    def best_gaze(self) -> Gaze | None:
        return max(self.gaze, key=lambda g: (g.psi_prime, g.ig), default=None)


def from_instance(inst: Any) -> SeenObject:
    """A :class:`SeenObject` from an ``eqa.messages.ObjectInstance`` (read by field name).
    An instance without gaze points has no pose set ``P`` to compute Eq. 12 over: its IG is unknown (NaN), not
    0 -- it is no candidate of the global objective until it has some (``helios.candidates_of``), and its first
    detection is stored (``S_a0``, ``IG_a0``) only then."""
    scores = {str(k): (float(v[0]), float(v[1]), float(v[2])) for k, v in dict(inst.scores).items()}
    scores.setdefault(inst.cls, (float(inst.S), float(inst.U), float(inst.psi)))
    gaze = tuple(Gaze(g.x, g.y, g.yaw, g.pitch, g.psi_prime, g.ig) for g in inst.gaze)
    ext = getattr(inst, "extent", (0.0, 0.0, 0.0))
    return SeenObject(int(inst.instance_id), str(inst.cls), scores, float(inst.centre[0]), float(inst.centre[1]),
                      float(inst.ig) if gaze else math.nan, gaze, (max(float(ext[0]), 0.0) / 2,
                                                                   max(float(ext[1]), 0.0) / 2))


def approach_pose(obj: tuple[float, float], towards: tuple[float, float], dist_m: float) -> tuple[float, float, float]:
    """The skill pose (see SKILL_APPROACH_M): ``dist_m`` from ``obj`` on the way to ``towards`` (or ``towards``
    itself when nearer), facing ``obj``."""
    dx, dy = towards[0] - obj[0], towards[1] - obj[1]
    d = math.hypot(dx, dy)
    if d < 1e-6:
        return (towards[0], towards[1], 0.0)
    k = min(1.0, dist_m / d)
    x, y = obj[0] + dx * k, obj[1] + dy * k
    return (x, y, math.atan2(obj[1] - y, obj[0] - x))


@dataclass(frozen=True)
class SkillOutcome:
    """The simulator's answer to a ``pick`` / ``place`` / ``stop`` action."""

    skill: Literal["pick", "place", "stop"]
    success: bool
    ref: int | None = None
    reason: str = ""


@dataclass(frozen=True)
class Action:
    kind: ActionKind
    phase: Phase
    ref: int | None = None  # frontier index or instance id
    pose: tuple[float, float, float] | None = None  # x, y, yaw (move / pick / place / stop)
    pitch: float = 0.0
    reason: str = ""
    success: bool | None = None  # done only
    near: tuple[float, float, float, float] | None = None  # pick / place / stop: the object's x, y, half-sizes
    # done only: the end is for want of anything to search or act on (no frontier, no candidate), not a skill's
    # outcome or the pick limit -- the planner looks around before it accepts it
    exhausted: bool = False


@dataclass(frozen=True)
class Thresholds:
    """The paper's Table 3 values. The product takes its thresholds from ``eqa.settings.Settings.helios_*``
    (:meth:`from_settings`), whose ``tau_g`` (the pick) and ``tau_stop`` (the end of an object search) defaults
    were chosen on the tuning seed 11, each on its own kind of task. The paper names one tau_g for both: the
    two decisions cost differently when wrong (a wrong pick spends the pick, a wrong stop ends the episode)."""

    alpha_d: float = 0.001
    tau_g: float = 0.5
    tau_b: float = 0.5
    tau_inc: float = 0.05
    cs_a: float = 0.3
    cs_g: float = 0.3
    cs_b: float = 0.3
    tau_stop: float = 0.5  # Psi_g to stop an object search at (section 4.2; Table 3's tau_g)
    value_scale: helios.ValueScale = "paper"  # Eq. 10's benefits as they are, or over the step's best (helios.values)
    path_clearance: Literal["levels", "cut"] = "levels"  # how task paths meet the mapped clearance (task_step)
    max_looks: int = 3  # gaze points visited to look again at one candidate (this implementation's bound)
    deadline: Literal["commit", "off"] = "off"  # act on the best candidate when the steps run out (_deadline)
    distance: Literal["straight", "path"] = "straight"  # Eq. 10's dist: straight line or path on the map (task_step)

    @classmethod
    def from_settings(cls, s: Any) -> Thresholds:
        return cls(s.helios_alpha_d, s.helios_tau_g, s.helios_tau_b, s.helios_tau_inc, s.helios_cs_a, s.helios_cs_g,
                   s.helios_cs_b, s.helios_tau_stop, s.helios_value_scale, s.helios_path_clearance,
                   s.helios_max_looks, s.helios_deadline, s.helios_distance)


@dataclass
class TaskMachine:
    kind: Literal["pick_place", "find_object"]
    object: str
    start_receptacle: str | None = None
    goal_receptacle: str | None = None
    ablation: Ablation = "helios"
    pick_limit: int | None = None
    th: Thresholds = field(default_factory=Thresholds)
    max_steps: int | None = None  # the episode's step budget (None: unknown, no deadline)
    holding: bool = False
    phase: Phase = "searching"
    budget: PickBudget = field(default_factory=PickBudget)
    memory: SearchMemory = field(default_factory=SearchMemory)
    queue: list[Gaze] = field(default_factory=list)  # local search: gaze points still to visit
    queue_owner: int | None = None
    fails: dict[int, int] = field(default_factory=dict)  # failed picks per instance
    unreachable_steps: dict[int, int] = field(default_factory=dict)  # steps whose skill pose could not be planned
    bad_goals: set[int] = field(default_factory=set)  # goal instances a place failed on
    looked: dict[int, list[tuple[float, float]]] = field(default_factory=dict)  # gaze points looked from
    pending: Action | None = None  # the pick / place / stop action waiting for its outcome
    finished: Action | None = None
    checking: int | None = None  # find_object: the candidate the robot went to see from a gaze point before stopping
    # the frontier the robot is on its way to, given with each step (an argument of step, not kept state)
    committed: int | None = field(default=None, repr=False, compare=False)
    # instances whose skill pose could not be planned in this planning step (begin_step clears it; not kept)
    skip: set[int] = field(default_factory=set, repr=False, compare=False)
    reopened: bool = field(default=False, repr=False, compare=False)  # once per call of step (not kept)
    # goals still to be carried out in the episode, this one included (an argument of step, not kept state)
    steps_left: int | None = field(default=None, repr=False, compare=False)
    step_m: float = field(default=3.0, repr=False, compare=False)  # the planner's longest move per step
    # Eq. 10's dist from where the robot stands this step (an argument of step, not kept state; None: straight)
    travel: helios.Travel | None = field(default=None, repr=False, compare=False)
    # whether the robot has turned a full circle where it stands, or has no steps left for one (an argument of
    # step, not kept state): only then does the last resort take an instance not believed to be the class
    looked_around: bool = field(default=True, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.kind == "pick_place" and (not self.start_receptacle or not self.goal_receptacle):
            raise ValueError("a pick_place task needs a start and a goal receptacle")
        if self.budget.limit != self.pick_limit:
            self.budget = PickBudget(self.pick_limit, self.budget.attempts, self.budget.successes)

    # ---- the step ---------------------------------------------------------------------------------------
    def step(self, robot: tuple[float, float, float], frontiers: Sequence[FrontierOption],
             objects: Sequence[SeenObject], outcome: SkillOutcome | None = None,
             committed: int | None = None, steps_left: int | None = None, step_m: float = 3.0,
             travel: helios.Travel | None = None, looked_around: bool = True) -> Action:
        """The next action (module doc). ``committed``: the index of the frontier the robot is on its way to;
        it stays the frontier of choice while a frontier is what the machine goes to
        (:func:`services.planner.helios.choose`). ``steps_left``: goals the episode still carries out, this one
        included (None: unknown); ``step_m``: the longest move of one step; ``travel``: ``dist`` of Eq. 10 from
        the robot (:func:`services.planner.helios.values`; None: the straight line); ``looked_around``: the
        robot turned a full circle where it stands (or has no steps left to), see :meth:`_last_resort`."""
        self.committed, self.reopened = committed, False
        self.steps_left, self.step_m, self.travel = steps_left, step_m, travel
        self.looked_around = looked_around
        if self.finished is not None:
            return self.finished
        if outcome is not None:
            done = self._take(outcome)
            if done is not None:
                return done
        elif self.ablation == "trusting" and self.pending is not None:
            # no 3D layer: the detection it acts on is gone from the next frame's detections, so the trusting
            # agent keeps going to it until the skill's outcome comes (or the pose proves unreachable)
            return self.pending
        return self._decide(robot, frontiers, objects)

    def begin_step(self) -> None:
        """A new planning step: instances unreachable in the last one are options again (the map has grown)."""
        self.skip = set()

    def unreachable(self, instance_id: int, action: Action | None = None) -> None:
        """The planner found no path to ``action``'s pose for this instance. A gaze point of a look
        (``looking``) counts as looked from, one of a local search is dropped (the queue already lost it):
        the instance keeps its other gaze points. A skill pose (or no ``action`` given) leaves the instance out
        of this step's decisions; after :data:`MAX_UNREACHABLE_STEPS` such steps it is ruled out as a target /
        goal (one unplannable pose on a half-built map does not drop a candidate for good)."""
        if action is not None and action.kind == "move":
            if action.phase == "looking" and action.pose is not None:
                self.looked.setdefault(instance_id, []).append((action.pose[0], action.pose[1]))
            return
        self.pending = None
        if instance_id not in self.skip:
            self.skip.add(instance_id)
            self.unreachable_steps[instance_id] = self.unreachable_steps.get(instance_id, 0) + 1

    def _reopen(self) -> bool:
        """Nothing left to do: gaze points looked from, start receptacles searched and instances ruled out as
        unreachable become options again (the map and the layer have changed since). False: nothing to reopen."""
        if self.reopened or not (self.looked or self.memory.visited or self.unreachable_steps):
            return False
        self.reopened = True
        self.looked, self.unreachable_steps = {}, {}
        self.memory.visited = set()
        return True

    def _unreached(self) -> set[int]:
        """Instances out of the decisions for want of a path: this step's, and those unreachable too often."""
        return self.skip | {i for i, n in self.unreachable_steps.items() if n >= MAX_UNREACHABLE_STEPS}

    def _finish(self, success: bool, reason: str, exhausted: bool = False) -> Action:
        self.phase = "finished"
        self.finished = Action("done", "finished", reason=reason, success=success, exhausted=exhausted)
        return self.finished

    def _take(self, out: SkillOutcome) -> Action | None:
        self.pending = None
        if out.skill == "pick":
            self.budget.attempt(out.success)
            if out.success:
                self.holding = True
                self.queue, self.queue_owner = [], None
                return None
            if out.ref is not None:
                self.fails[out.ref] = self.fails.get(out.ref, 0) + 1
            if self.budget.exhausted:
                return self._finish(False, f"pick failed ({out.reason}); pick limit {self.budget.limit} used up")
            return None
        if out.skill == "place":
            if out.success:
                return self._finish(True, f"placed ({out.reason})")
            return self._finish(False, f"place failed: {out.reason}")  # the object is no longer held
        return self._finish(out.success, f"stopped ({out.reason})")

    # ---- candidates -------------------------------------------------------------------------------------
    def _scored(self, objects: Sequence[SeenObject], c: str, exclude: set[int]) -> list[Scored]:
        out = []
        for o in objects:
            s = o.of(c)
            if s is None or o.instance_id in exclude:
                continue
            if self.ablation == "trusting" and o.cls != c:  # a detection of c is an instance believed to be c
                continue
            g = self._approach(self._unlooked(o), (o.x, o.y, 0.0), best=True) if o.cls == c else None
            out.append(Scored(o.instance_id, s[0], s[2], g.psi_prime if g is not None else None))
        return out

    def _unlooked(self, o: SeenObject) -> SeenObject:
        """``o`` with the gaze points it may still be looked at from: none once ``th.max_looks`` looks
        are used up, else those not looked from yet. Its Psi' (Eq. 11) is that of the best of them, so a
        candidate whose looks are used up is no longer one to look at (the decision goes to the next)."""
        done = self.looked.get(o.instance_id, [])
        if len(done) >= self.th.max_looks:
            left: tuple[Gaze, ...] = ()
        else:
            left = tuple(g for g in o.gaze
                         if not any(math.hypot(g.x - x, g.y - y) <= ARRIVE_TOLERANCE_M for x, y in done))
        return SeenObject(o.instance_id, o.cls, o.scores, o.x, o.y, o.ig, left, o.half)

    def _approach(self, o: SeenObject, robot: tuple[float, float, float], best: bool) -> Gaze | None:
        """The gaze point to go to: the one of highest Psi' (``best``) or the nearest (trusting, picking)."""
        if not o.gaze:
            return None
        if best and self.ablation != "trusting":
            return o.best_gaze()
        return min(o.gaze, key=lambda g: math.hypot(g.x - robot[0], g.y - robot[1]))

    def _act_on(self, kind: Literal["pick", "place", "stop"], o: SeenObject, robot: tuple[float, float, float],
                reason: str) -> Action:
        g = self._approach(o, robot, best=False)
        pose = approach_pose((o.x, o.y), (g.x, g.y) if g is not None else robot[:2], SKILL_APPROACH_M)
        phase: Phase = {"pick": "picking", "place": "placing", "stop": "looking"}[kind]  # type: ignore[assignment]
        self.phase = phase
        hx, hy = (min(o.half[0], PICKABLE_HALF_M), min(o.half[1], PICKABLE_HALF_M)) if kind == "pick" else o.half
        self.pending = Action(kind, phase, o.instance_id, pose, g.pitch if g is not None else 0.0, reason,
                              near=(o.x, o.y, hx, hy))
        return self.pending

    def _look(self, o: SeenObject, robot: tuple[float, float, float], reason: str) -> Action | None:
        """Go to the candidate's best gaze point not looked from yet (paper: one at a time). Standing at it means
        the last frame was the look: it is marked and the next one is taken; after ``th.max_looks`` looks
        (or none left) the candidate gets no more looks (None: the caller goes on with the search)."""
        done = self.looked.setdefault(o.instance_id, [])
        while len(done) < self.th.max_looks:
            g = self._approach(self._unlooked(o), robot, best=True)
            if g is None:
                return None
            if math.hypot(g.x - robot[0], g.y - robot[1]) > ARRIVE_TOLERANCE_M:
                break
            done.append((g.x, g.y))
        else:
            return None
        self.phase = "looking"
        return Action("move", "looking", o.instance_id, (g.x, g.y, g.yaw), g.pitch, reason)

    def _decide(self, robot: tuple[float, float, float], frontiers: Sequence[FrontierOption],
                objects: Sequence[SeenObject]) -> Action:
        late = self._deadline(robot, objects)
        if late is not None:
            return late
        if self.kind == "find_object":
            return self._find(robot, frontiers, objects)
        if self.holding:
            return self._goal(robot, frontiers, objects)
        return self._search(robot, frontiers, objects)

    def _nothing_left(self, robot: tuple[float, float, float], frontiers: Sequence[FrontierOption],
                      objects: Sequence[SeenObject], reason: str) -> Action:
        """No frontier and no candidate to act on or look at: reopen what was ruled out and decide again; then
        act on the best known candidate (:meth:`_last_resort`); only then end the episode."""
        if self._reopen():
            return self._decide(robot, frontiers, objects)
        last = self._last_resort(robot, objects)
        if last is not None:
            return last
        return self._finish(False, reason, exhausted=True)

    def _best_frontier(self, robot: tuple[float, float, float], frontiers: Sequence[FrontierOption],
                       reason: str, objects: Sequence[SeenObject] = ()) -> Action:
        ranked = helios.values(robot[:2], frontiers, [], SearchMemory(), self.th.alpha_d, self.th.value_scale,
                               self.travel)
        if not ranked:
            return self._nothing_left(robot, frontiers, objects, f"{reason}; no frontier left to explore")
        self.phase = "searching"
        ref = self.committed if any(c.ref == self.committed for c in ranked) else ranked[0].ref
        value = next(c.value for c in ranked if c.ref == ref)
        kept = ", the frontier it is on its way to" if ref == self.committed else ""
        return Action("frontier", "searching", ref, reason=f"{reason}: V {value:.3g}{kept}")

    def _phase_skill(self) -> tuple[Literal["pick", "place", "stop"], str, set[int]] | None:
        """The skill of the phase, the class it acts on and the instances it may not act on; None: no skill
        other than through the threshold (a pick under a pick limit: a failed one ends the task, a search that
        goes on may still find the object)."""
        if self.kind == "find_object":
            return "stop", self.object, self._ruled_out()
        if self.holding:
            return "place", self.goal_receptacle or "", self._bad_goals()
        if self.budget.limit is not None:
            return None
        return "pick", self.object, self._ruled_out()

    def _best_known(self, cls: str, excluded: set[int], objects: Sequence[SeenObject], believed: bool = True
                    ) -> tuple[float, float, SeenObject] | None:
        """The instance believed to be ``cls`` (``believed``; else any instance scored for ``cls``) of highest
        Psi for ``cls`` (then S, then lowest id): (Psi, S, instance)."""
        pool = [(s[2], s[0], -o.instance_id, o) for o in objects if o.instance_id not in excluded
                and (s := o.of(cls)) is not None and (o.cls == cls or not believed) and math.isfinite(s[2])]
        if not pool:
            return None
        psi, S, _, o = max(pool, key=lambda t: t[:3])
        return psi, S, o

    def _last_resort(self, robot: tuple[float, float, float], objects: Sequence[SeenObject]) -> Action | None:
        """Nothing left to explore but candidates of the phase's class are known: rather than end the episode
        with steps left, act on the best of them (highest Psi, then S) below the threshold -- a skill call
        that may fail costs less than a certain failure. With no instance believed to be of the class, the
        instance of highest Psi for it is taken (a receptacle the layer believes to be another class may still be
        the goal; ending the episode fails for certain) -- but only once the robot has looked around where it
        stands (``looked_around``): new frames may open a frontier, and acting on an instance of Psi near 0 ends
        the task (tuning seed 11: a place on a kitchen counter of Psi 0.02 for "bed" with 58 steps left). None: no
        instance scored for the class, no skill to call (:meth:`_phase_skill`), or none believed before the
        look around."""
        phase = self._phase_skill()
        if phase is None:
            return None
        skill, cls, excluded = phase
        best = self._best_known(cls, excluded, objects)
        believed = best is not None
        if best is None and self.looked_around:
            best = self._best_known(cls, excluded, objects, believed=False)
        if best is None:
            return None
        psi, S, o = best
        what = (f"the best known {cls}" if believed
                else f"no instance believed to be a {cls}: the {o.cls} {o.instance_id}")
        return self._act_on(skill, o, robot, f"no frontier left: {what} (Psi {psi:.3f}, S {S:.3f})")

    def _deadline(self, robot: tuple[float, float, float], objects: Sequence[SeenObject]) -> Action | None:
        """The steps left are only enough to reach the best known candidate of the phase's class and call the
        skill there (straight-line distance to its skill pose times :data:`DEADLINE_DETOUR`, at ``step_m`` a
        step, plus :data:`DEADLINE_MARGIN_STEPS`): act on it now, whatever its Psi. Any other action ends the
        episode at its step limit, a certain failure (holding the object: not placed); the skill on the best
        candidate may succeed. None: no deadline (``th.deadline`` off, budget unknown, steps enough, no
        candidate, or a pick under a pick limit)."""
        if self.th.deadline != "commit" or self.steps_left is None:
            return None
        phase = self._phase_skill()
        if phase is None:
            return None
        skill, cls, excluded = phase
        best = self._best_known(cls, excluded, objects)
        if best is None:
            return None
        psi, S, o = best
        dist = max(math.hypot(o.x - robot[0], o.y - robot[1]) - SKILL_APPROACH_M, 0.0)
        need = math.ceil(DEADLINE_DETOUR * dist / max(self.step_m, 1e-6)) + DEADLINE_MARGIN_STEPS
        if self.steps_left > need:
            return None
        return self._act_on(skill, o, robot, f"{self.steps_left} steps left, about {need} needed to reach the best "
                            f"known {cls} (Psi {psi:.3f}, S {S:.3f}): acting on it before the steps run out")

    # ---- pick and place ---------------------------------------------------------------------------------
    def _ruled_out(self) -> set[int]:
        """Instances whose skill failed too often to try again, or that cannot be reached (:meth:`_unreached`)."""
        return {i for i, n in self.fails.items() if n >= MAX_FAILS_PER_INSTANCE} | self._unreached()

    def _bad_goals(self) -> set[int]:
        """Goal receptacles a place failed on, or that cannot be reached."""
        return self.bad_goals | self._unreached()

    def _act_or_look(self, skill: str, robot: tuple[float, float, float], objects: Sequence[SeenObject], cls: str,
                     excluded: set[int], tau: float, cs: float) -> Action | None:
        """Eq. 11 for the candidates of ``cls``: act (``skill``) on one confident enough, else go and look again
        at one whose optimistic score could get there; None: neither (back to search). A candidate whose looks
        come to an end here (the robot stands at its last gaze point) leaves the look rule and the decision is
        taken again over the others."""
        by_id = {o.instance_id: o for o in objects}
        for _ in range(len(by_id) + 1):
            d = decide(self._scored(objects, cls, excluded), tau, self.th.tau_inc, cs,
                       trusting=self.ablation == "trusting")
            if d.instance_id is None:
                return None
            target = by_id[d.instance_id]
            if d.action == "act":
                return self._act_on(skill, target, robot, d.reason)
            if d.action != "look":
                return None
            look = self._look(target, robot, d.reason)
            if look is not None:
                return look
        return None

    def _search(self, robot: tuple[float, float, float], frontiers: Sequence[FrontierOption],
                objects: Sequence[SeenObject]) -> Action:
        by_id = {o.instance_id: o for o in objects}
        a = self._act_or_look("pick", robot, objects, self.object, self._ruled_out(), self.th.tau_g, self.th.cs_g)
        if a is not None:
            return a
        # local search in progress: the next gaze point of the start receptacle, nearest first
        while self.queue:
            g = min(self.queue, key=lambda q: math.hypot(q.x - robot[0], q.y - robot[1]))
            self.queue.remove(g)
            if math.hypot(g.x - robot[0], g.y - robot[1]) <= ARRIVE_TOLERANCE_M:
                continue
            self.phase = "local_search"
            return Action("move", "local_search", self.queue_owner, (g.x, g.y, g.yaw), g.pitch,
                          f"local search of {self.start_receptacle} {self.queue_owner}: a gaze point "
                          f"({len(self.queue)} more)")
        if self.ablation == "trusting":
            return self._best_frontier(robot, frontiers, "trusting: frontier of highest value", objects)
        start = self.start_receptacle or ""
        observed = []
        for o in objects:
            s = o.of(start)
            if s is not None and o.cls == start:
                observed.append(CandidateObservation(o.instance_id, s[0], o.ig, o.x, o.y))
        choice = helios.choose(robot[:2], frontiers, observed, self.memory, self.th.alpha_d, self.th.cs_a,
                               self.ablation, self.committed, self.th.value_scale, self.travel)
        if choice is None:
            return self._nothing_left(robot, frontiers, objects,
                                      "nothing left to search: no frontier and no candidate start receptacle")
        said = helios.describe(choice, choice.kind == "frontier" and choice.ref == self.committed)
        if choice.kind == "frontier":
            self.phase = "searching"
            return Action("frontier", "searching", choice.ref, reason=said)
        self.memory.visited.add(choice.ref)
        o = by_id[choice.ref]
        self.queue, self.queue_owner = list(o.gaze), o.instance_id
        a = self._search(robot, frontiers, objects)  # the first gaze point (or, with none, the next choice)
        mine = a.phase == "local_search" and a.ref == o.instance_id
        return dataclasses.replace(a, reason=f"{said}; {a.reason}") if mine else a

    def _goal(self, robot: tuple[float, float, float], frontiers: Sequence[FrontierOption],
              objects: Sequence[SeenObject]) -> Action:
        goal = self.goal_receptacle or ""
        a = self._act_or_look("place", robot, objects, goal, self._bad_goals(), self.th.tau_b, self.th.cs_b)
        if a is not None:
            return a
        return self._best_frontier(robot, frontiers, "goal receptacle search: frontier of highest value", objects)

    # ---- find an object (section 4.2) --------------------------------------------------------------------
    def _find(self, robot: tuple[float, float, float], frontiers: Sequence[FrontierOption],
              objects: Sequence[SeenObject]) -> Action:
        """Section 4.2: "when a potential target object is identified the robot goes to generated gaze points
        around the object and then only stops if the uncertainty-weighted object score is high enough". A
        candidate confident enough to stop at (Eq. 11's act) is first seen again from its best gaze point
        (once; ``checking``), then the decision is taken again on the updated layer. The trusting agent stops
        at once. (With two classes, target and ``other``, one clean view already gives Psi ~0.6 >= tau_stop 0.5:
        without the look the stop decision was the trusting one.)"""
        if self.ablation != "trusting":
            d = decide(self._scored(objects, self.object, self._ruled_out()), self.th.tau_stop, self.th.tau_inc,
                       self.th.cs_g)
            if d.action == "act" and d.instance_id is not None:
                if self.checking == d.instance_id:  # went to its gaze point (or as near as the map allowed)
                    self.looked.setdefault(d.instance_id, []).append(robot[:2])
                    self.checking = None
                if not self.looked.get(d.instance_id):
                    o = {x.instance_id: x for x in objects}[d.instance_id]
                    look = self._look(o, robot, f"{d.reason}; a view from a gaze point before stopping")
                    if look is not None:
                        self.checking = d.instance_id
                        return look
        a = self._act_or_look("stop", robot, objects, self.object, self._ruled_out(), self.th.tau_stop, self.th.cs_g)
        if a is not None:
            return a
        return self._best_frontier(robot, frontiers, "object search: frontier of highest value", objects)

    # ---- persistence ------------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        def act(a: Action | None) -> dict[str, Any] | None:
            return None if a is None else {**vars(a), "pose": list(a.pose) if a.pose else None,
                                           "near": list(a.near) if a.near else None}

        return {
            "kind": self.kind, "object": self.object, "start_receptacle": self.start_receptacle,
            "goal_receptacle": self.goal_receptacle, "ablation": self.ablation, "pick_limit": self.pick_limit,
            "max_steps": self.max_steps,
            "th": vars(self.th), "holding": self.holding, "phase": self.phase,
            "budget": {"attempts": self.budget.attempts, "successes": self.budget.successes},
            "memory": self.memory.to_json(), "queue": [vars(g) for g in self.queue], "queue_owner": self.queue_owner,
            "fails": {str(k): v for k, v in self.fails.items()}, "bad_goals": sorted(self.bad_goals),
            "unreachable_steps": {str(k): v for k, v in self.unreachable_steps.items()},
            "looked": {str(k): [list(p) for p in v] for k, v in self.looked.items()},
            "pending": act(self.pending), "finished": act(self.finished), "checking": self.checking,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> TaskMachine:
        def act(a: dict[str, Any] | None) -> Action | None:
            if a is None:
                return None
            near = tuple(a["near"]) if a.get("near") else None
            return Action(**{**a, "pose": tuple(a["pose"]) if a["pose"] else None, "near": near})

        m = cls(d["kind"], d["object"], d["start_receptacle"], d["goal_receptacle"], d["ablation"], d["pick_limit"],
                Thresholds(**d["th"]), d.get("max_steps"))
        m.holding, m.phase = bool(d["holding"]), d["phase"]
        m.budget = PickBudget(m.pick_limit, int(d["budget"]["attempts"]), int(d["budget"]["successes"]))
        m.memory = SearchMemory.from_json(d["memory"])
        m.queue = [Gaze(**g) for g in d["queue"]]
        m.queue_owner = d["queue_owner"]
        m.fails = {int(k): int(v) for k, v in d["fails"].items()}
        m.bad_goals = {int(v) for v in d["bad_goals"]}
        m.unreachable_steps = {int(k): int(v) for k, v in d.get("unreachable_steps", {}).items()}
        m.looked = {int(k): [(float(p[0]), float(p[1])) for p in v] for k, v in d.get("looked", {}).items()}
        m.pending, m.finished = act(d["pending"]), act(d["finished"])
        m.checking = d.get("checking")
        return m
