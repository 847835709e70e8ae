"""HELIOS tasks on generated houses (paper sections 4.1, 4.2) and their fixed benchmark.

* ``pick_place``: "Move the (object) from the (start_receptacle) to the (goal_receptacle)" (OVMM form). The
  object is a small, pickable object standing on a piece of furniture (the start receptacle); the goal
  receptacle is a class of flat-topped furniture present elsewhere in the house (another class than the
  start receptacle). As in OVMM, every object of the class standing on a start receptacle of the class counts
  (``object_ids``), and every instance of the goal class (``goal_receptacle_ids``).
* ``find_object``: "Find a (object)", ended by a stop call; success = stop within :data:`FIND_SUCCESS_M` of an
  instance; ``shortest_path_m`` (geodesic, from the start to the nearest such pose) gives the SPL.

Every task is feasible by construction: at least one object can be picked (in frame and within reach from a
reachable pose, :func:`services.sim.skills.pick_poses`), a goal receptacle can be reached, and the robot's
start pose is in the same connected free space. The houses are the generator's as they are (they already
carry small objects on furniture): nothing here changes a house or the question benchmark.

The benchmark follows the project's seed rules (:mod:`eqa.seeds`): the tasks of seed ``s`` use houses
``gen-{s*10000 + 5000 + i}`` (a range the question benchmark, houses ``s*10000 + i`` with i < 1000, never
uses); :data:`~eqa.seeds.TUNING_SEED` is the tuning split, :data:`~eqa.seeds.EVALUATION_SEEDS` the evaluation
sets.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eqa import grid as gridm
from eqa.budget import task_steps_for
from eqa.messages import Pose2D, Task
from eqa.seeds import seed_role
from services.sim import catalog
from services.sim.benchfile import load_json, save_json
from services.sim.catalog import display_name
from services.sim.library import load_or_generate
from services.sim.motion import GRID_RES, START_CLEARANCE, reachable_map, sample_start_pose
from services.sim.paths import geodesic_field
from services.sim.scene import Scene
from services.sim.skills import REACH_M, pick_poses

log = logging.getLogger(__name__)

# Small objects a one-arm mobile manipulator picks (OVMM objects: household items under ~0.5 m).
PICKABLE: frozenset[str] = frozenset({
    "laptop", "towel", "box", "backpack", "vase", "book", "mug", "kettle", "fruit_bowl", "toolbox", "cushion",
    "shoes", "lamp",
})
# Furniture with a flat top between 0.4 and 1.0 m: goal receptacles a dropped object can rest on.
GOAL_RECEPTACLES: frozenset[str] = frozenset(
    k.category for k in catalog.FURNITURE.values()
    if k.surface and k.shape in ("box", "table") and 0.4 <= k.size[2] <= 1.0
    and k.category not in ("stove", "washing_machine", "dryer", "bathroom_sink")
)
FIND_SUCCESS_M = 1.0  # find_object: stop within this of an instance's box (HM3D ObjectNav: 1 m)
MIN_FIND_PATH_M = 1.0  # find_object: the start is farther than this (geodesic) from every success pose
TASK_HOUSE_OFFSET = 5000
PICK_PLACE_PER_HOUSE = 2
FIND_PER_HOUSE = 1


def instruction(obj: str, start: str | None = None, goal: str | None = None) -> str:
    if start is None or goal is None:
        return f"Find a {display_name(obj)}"
    return f"Move the {display_name(obj)} from the {display_name(start)} to the {display_name(goal)}"


def geodesic_from(reach: np.ndarray, origin: tuple[float, float], start: Pose2D) -> np.ndarray:
    """Geodesic distance (m) from ``start`` to every cell of the boolean ``reach`` grid (8-connected, no corner
    cutting); ``inf`` where it cannot be reached."""
    i0, j0 = gridm.cell_of_point(start.x, start.y, origin, GRID_RES)
    return geodesic_field(reach, GRID_RES, [(i0, j0, 0.0)])


def _near_box_mask(shape: tuple[int, int], origin: tuple[float, float], centre: tuple[float, ...],
                   size: tuple[float, ...], within: float) -> np.ndarray:
    xs, _ = gridm.cell_center(0, np.arange(shape[1]), origin, GRID_RES)
    _, ys = gridm.cell_center(np.arange(shape[0]), 0, origin, GRID_RES)
    dx = np.maximum(np.abs(xs - centre[0]) - size[0] / 2, 0.0)
    dy = np.maximum(np.abs(ys - centre[1]) - size[1] / 2, 0.0)
    return np.hypot(dy[:, None], dx[None, :]) <= within


def generate_tasks(scene: Scene, rng: np.random.Generator, pick_place: int = PICK_PLACE_PER_HOUSE,
                   find: int = FIND_PER_HOUSE) -> list[Task]:
    """Up to ``pick_place`` OVMM-style and ``find`` object-search tasks in ``scene`` (module doc); fewer when
    the house offers no feasible one. Deterministic for a given ``rng`` state."""
    start = sample_start_pose(scene, rng, START_CLEARANCE)
    reach, ox, oy = reachable_map(scene, start)
    origin = (ox, oy)
    objs = scene.objects()
    max_steps = task_steps_for(scene.floor_area_m2)
    by_cat: dict[str, list[int]] = {}
    for o in objs:
        by_cat.setdefault(o.category, []).append(o.id)
    pickable_cache: dict[int, bool] = {}

    def can_pick(oid: int) -> bool:
        if oid not in pickable_cache:
            pickable_cache[oid] = bool(pick_poses(scene, oid, reach, origin, max_candidates=12))
        return pickable_cache[oid]

    def reachable_near(oid: int, within: float) -> bool:
        info = scene.instances[oid]
        return bool((reach & _near_box_mask(reach.shape, origin, info.position, info.size, within)).any())

    out: list[Task] = []
    # pick and place: (object class, start receptacle class) pairs with a pickable instance
    pairs: dict[tuple[str, str], list[int]] = {}
    for o in objs:
        if o.category in PICKABLE and o.support is not None and o.support in scene.instances:
            pairs.setdefault((o.category, scene.instances[o.support].category), []).append(o.id)
    order = sorted(pairs)
    used_objects: set[str] = set()
    for k in rng.permutation(len(order)):
        if len(out) >= pick_place:
            break
        obj_cat, start_cat = order[int(k)]
        if obj_cat in used_objects:
            continue
        ids = sorted(pairs[(obj_cat, start_cat)])
        if not any(can_pick(i) for i in ids):
            continue
        goals = sorted(c for c in GOAL_RECEPTACLES if c != start_cat and c in by_cat
                       and any(reachable_near(g, REACH_M - 0.1) for g in by_cat[c]))
        if not goals:
            continue
        goal_cat = goals[int(rng.integers(0, len(goals)))]
        supports = sorted({scene.instances[i].support for i in ids if scene.instances[i].support is not None})
        used_objects.add(obj_cat)
        out.append(Task(
            id=f"{scene.id}-pp{len(out)}", kind="pick_place", text=instruction(obj_cat, start_cat, goal_cat),
            scene=scene.id, object=obj_cat, start_receptacle=start_cat, goal_receptacle=goal_cat,
            object_ids=ids, start_receptacle_ids=supports, goal_receptacle_ids=sorted(by_cat[goal_cat]),
            start_pose=start, max_steps=max_steps,
        ))
    # find an object: a class of small objects, at least one instance pickable (in view and near)
    cats = sorted(c for c in by_cat if c in catalog.SMALL_OBJECTS and c not in used_objects)
    geo: np.ndarray | None = None
    n_find = 0
    for k in rng.permutation(len(cats)):
        if n_find >= find:
            break
        cat = cats[int(k)]
        ids = sorted(by_cat[cat])
        if not any(can_pick(i) for i in ids):
            continue
        if geo is None:
            geo = geodesic_from(reach, origin, start)
        goal_mask = np.zeros(reach.shape, bool)
        for i in ids:
            info = scene.instances[i]
            goal_mask |= _near_box_mask(reach.shape, origin, info.position, info.size, FIND_SUCCESS_M)
        best = float(geo[goal_mask & reach].min()) if (goal_mask & reach).any() else math.inf
        if not math.isfinite(best) or best < MIN_FIND_PATH_M:
            continue
        out.append(Task(
            id=f"{scene.id}-find{n_find}", kind="find_object", text=instruction(cat), scene=scene.id, object=cat,
            object_ids=ids, start_pose=start, max_steps=max_steps, shortest_path_m=round(best, 3),
        ))
        n_find += 1
    return out


# ---- the fixed benchmark -----------------------------------------------------------------------------------


def task_scene_id(seed: int, index: int) -> str:
    return f"gen-{seed * 10000 + TASK_HOUSE_OFFSET + index:05d}"


@dataclass
class TaskBenchmark:
    """A fixed task set of one seed: ``pick_place`` and ``find_object`` tasks; ``role`` = how figures from it
    must be labelled (:func:`eqa.seeds.seed_role`: ``tuning`` or ``evaluation``)."""

    seed: int
    tasks: list[Task] = field(default_factory=list)

    @property
    def role(self) -> str:
        return seed_role(self.seed)

    def of_kind(self, kind: str) -> list[Task]:
        return [t for t in self.tasks if t.kind == kind]

    def to_json(self) -> dict[str, object]:
        return {"seed": self.seed, "role": self.role, "tasks": [t.model_dump(mode="json") for t in self.tasks]}

    def save(self, path: Path) -> Path:
        return save_json(self.to_json(), path)

    @classmethod
    def load(cls, path: Path) -> TaskBenchmark:
        data = load_json(path)
        return cls(seed=int(data["seed"]), tasks=[Task.model_validate(t) for t in data["tasks"]])


def house_tasks(seed: int, index: int, scenes_dir: Path | None = None, pick_place: int = PICK_PLACE_PER_HOUSE,
                find: int = FIND_PER_HOUSE) -> list[Task]:
    """The tasks of house ``index`` of benchmark ``seed`` (:func:`task_scene_id`), as :func:`task_benchmark`
    draws them: the pick-and-place ones first, all from the house's one start pose."""
    from services.sim.housegen import generate_house

    sid = task_scene_id(seed, index)
    scene = load_or_generate(sid, scenes_dir) if scenes_dir is not None else generate_house(
        seed * 10000 + TASK_HOUSE_OFFSET + index)
    return generate_tasks(scene, np.random.default_rng([seed, index, 17]), pick_place, find)


def task_benchmark(seed: int, pick_place: int = 60, find: int = 30, scenes_dir: Path | None = None,
                   progress: bool = False) -> TaskBenchmark:
    """``pick_place`` + ``find`` tasks of benchmark ``seed`` over houses ``task_scene_id(seed, i)``, in order,
    at most :data:`PICK_PLACE_PER_HOUSE` / :data:`FIND_PER_HOUSE` per house. Deterministic."""
    if pick_place < 0 or find < 0 or pick_place + find > 10_000:
        raise ValueError("task counts must be >= 0 and at most 10000 in all")
    pp: list[Task] = []
    fo: list[Task] = []
    index = 0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=pick_place + find, desc=f"tasks seed {seed}", unit="task")
    while len(pp) < pick_place or len(fo) < find:
        if index >= 4 * (pick_place + find) + 20:
            raise RuntimeError(f"task benchmark seed {seed}: houses ran out of feasible tasks")
        want_pp = min(PICK_PLACE_PER_HOUSE, pick_place - len(pp))
        want_fo = min(FIND_PER_HOUSE, find - len(fo))
        got = house_tasks(seed, index, scenes_dir, want_pp, want_fo)
        new_pp = [t for t in got if t.kind == "pick_place"]
        new_fo = [t for t in got if t.kind == "find_object"]
        pp += new_pp
        fo += new_fo
        if bar is not None:
            bar.update(len(new_pp) + len(new_fo))
        index += 1
    if bar is not None:
        bar.close()
    return TaskBenchmark(seed=seed, tasks=pp + fo)



# ---- ground truth of a task given in words ----------------------------------------------------------------


def with_ground_truth(task: Task, scene: Scene, start: Pose2D) -> Task:
    """``task`` with the simulator's ground truth filled in from ``scene``'s graph when it has none (a task
    typed by a user, ``POST /v1/tasks``): the same sets :func:`generate_tasks` gives -- every object of the
    class standing on a start receptacle of the class (for ``find_object`` every object of the class), every
    instance of the goal class -- and, for ``find_object``, the geodesic from ``start`` to the nearest success
    pose (SPL). A task that already lists its ``object_ids`` (a benchmark task) is returned as it is. Classes
    the house lacks leave the lists empty: the skills then fail with "not near a target object"."""
    if task.object_ids:
        return task
    objs = scene.objects()
    of_class = sorted(o.id for o in objs if o.category == task.object)
    update: dict[str, object] = {}
    if task.kind == "pick_place":
        starts = {o.id for o in objs if o.category == task.start_receptacle}
        ids = sorted(i for i in of_class if scene.instances[i].support in starts)
        update["object_ids"] = ids
        update["start_receptacle_ids"] = sorted({scene.instances[i].support for i in ids})  # type: ignore[misc]
        update["goal_receptacle_ids"] = sorted(o.id for o in objs if o.category == task.goal_receptacle)
    else:
        update["object_ids"] = of_class
        if of_class and task.shortest_path_m is None:
            reach, ox, oy = reachable_map(scene, start)
            geo = geodesic_from(reach, (ox, oy), start)
            goal_mask = np.zeros(reach.shape, bool)
            for i in of_class:
                info = scene.instances[i]
                goal_mask |= _near_box_mask(reach.shape, (ox, oy), info.position, info.size, FIND_SUCCESS_M)
            ok = goal_mask & reach & np.isfinite(geo)
            if ok.any():
                update["shortest_path_m"] = round(float(geo[ok].min()), 3)
    lacks = scene_lacks(task, scene)
    if lacks is not None:
        log.warning("task %r: %s; its skills cannot succeed", task.text, lacks)
    return task.model_copy(update=update)


MAX_LISTED = 24  # classes or pairs named in a "the house has no ..." line at most


def _listing(items: list[str]) -> str:
    more = f", ... ({len(items) - MAX_LISTED} more)" if len(items) > MAX_LISTED else ""
    return ", ".join(items[:MAX_LISTED]) + more


def scene_lacks(task: Task, scene: Scene) -> str | None:
    """One line saying what of ``task`` the house ``scene`` lacks and what it has instead, or None when it has
    everything the task names: for pick and place an object of the class standing on a start receptacle of
    its class and an instance of the goal receptacle class, for an object search an object of the class. Such a
    task cannot succeed in the simulator (its skills read the scene graph), so the simulator refuses it and
    ``eqa task`` checks it before starting a fleet."""
    objs = scene.objects()
    classes = {o.category for o in objs}
    if task.kind == "find_object":
        if task.object in classes:
            return None
        small = sorted(display_name(c) for c in classes if c in catalog.SMALL_OBJECTS)
        return f"{scene.id} has no {display_name(task.object)} (its small objects: {_listing(small)})"
    pairs = sorted({(o.category, scene.instances[o.support].category) for o in objs
                    if o.support is not None and o.support in scene.instances})
    if (task.object, task.start_receptacle) not in pairs:
        on = [f"{display_name(a)} on {display_name(b)}" for a, b in pairs if a in PICKABLE]
        return (f"{scene.id} has no {display_name(task.object)} on a {display_name(task.start_receptacle or '')} "
                f"(its pickable objects: {_listing(on)})")
    if task.goal_receptacle not in classes:
        goals = sorted(display_name(c) for c in classes if c in GOAL_RECEPTACLES)
        return (f"{scene.id} has no {display_name(task.goal_receptacle or '')} (its goal receptacles: "
                f"{_listing(goals)})")
    return None
