"""Houses that change between a home's episodes: seeded rounds of moved, added and removed objects and
switched object states.

The changed house ``<base>-c<k>`` (e.g. ``gen-00042-c2``) is the generated house ``<base>`` after ``k`` rounds
of changes. Round ``r`` draws from ``numpy.random.default_rng([base seed, ROUND_STREAM, r])``, so rounds
1..k of ``-c<k>`` are rounds 1..k of every ``-c<j>``, ``j >= k``: a home's houses form one history.

A round makes :data:`CHANGES_PER_ROUND` changes to the small objects (:data:`services.sim.catalog.SMALL_OBJECTS`,
the objects the question generator asks about; furniture stays put so the rooms' free space stays as the
generator checked it):

* ``move``: the object goes to another surface it may stand on (a piece of furniture of its ``on`` list, or the
  floor), possibly in another room;
* ``add``: a new small object (kind, colour and state drawn as the generator draws them) on such a surface;
* ``remove``: the object is taken out of the house;
* ``state``: the object's state flips (``on``/``off``, ``open``/``closed``, ``folded``/``unfolded``), its
  geometry rebuilt so the state shows, as the generator builds it.

Every placement stays on its support's top (or a shelf board) inside its edges, overlaps no other object,
keeps clear of doors, leaves the robot's free space in one piece (a floor placement), and is visible from a
reachable pose (:func:`services.sim.visibility.witness_poses`); a drawn change that fits nowhere is drawn again.

:func:`changes_of` lists the changes of rounds 1..k; what they do to questions is :mod:`services.sim.change_impact`.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from services.sim import catalog
from services.sim.catalog import COLORS, FURNITURE, OPPOSITE_STATE, SMALL_OBJECTS
from services.sim.housegen import HALF_WALL, _object_boxes, _overlap
from services.sim.meshbuild import Frame2D, MeshBuilder
from services.sim.motion import GRID_RES, ROBOT_RADIUS, clearance_map
from services.sim.scene import CHANGED_ID, GEN_ID, InstanceInfo, Room, Scene
from services.sim.visibility import witness_poses

log = logging.getLogger(__name__)

MAX_ROUNDS = 20  # k of "-c<k>": a house is built round by round (about 0.2 s each), so k is bounded
CHANGES_PER_ROUND = 3
ROUND_STREAM = 31  # the seed stream of change rounds (the generator's own streams are 7 and 11)
KINDS = ("move", "add", "remove", "state")
KIND_WEIGHTS = np.array([0.35, 0.15, 0.15, 0.35])
ATTEMPTS = 24  # placements tried for one change before another change is drawn
SURFACE_INSET = 0.06  # m, kept free along a support's edges (shelf side panels and back, handles)
DOOR_KEEPOUT = 1.2  # m, in front of and behind a door no floor object is placed (as the generator)
FACINGS = ((0, 1), (0, -1), (1, 0), (-1, 0))


@dataclass(frozen=True)
class Change:
    """One change of one round. ``before``/``after`` hold the object's ``room``, ``room_kind``, ``position``,
    ``support`` and ``state`` (``before`` is None for an added object, ``after`` None for a removed one)."""

    round: int
    kind: str
    object_id: int
    category: str
    color: str
    before: dict[str, Any] | None = None
    after: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def changed_scene_id(base: str, k: int) -> str:
    """The scene id of ``base`` after ``k`` rounds (``k = 0``: the base house itself)."""
    if not GEN_ID.match(base):
        raise ValueError(f"scene {base!r} is not a generated house (gen-<seed>): only those can change")
    if not 0 <= int(k) <= MAX_ROUNDS:
        raise ValueError(f"rounds of changes must be 0..{MAX_ROUNDS}, not {k}")
    return base if k == 0 else f"{base}-c{int(k)}"


def parse_changed_id(scene_id: str) -> tuple[str, int] | None:
    """``(base id, k)`` of a changed house id, None for any other id; ValueError when k is out of bounds."""
    m = CHANGED_ID.match(scene_id)
    if m is None:
        return None
    k = int(m.group(2))
    if not 1 <= k <= MAX_ROUNDS:
        raise ValueError(f"scene {scene_id!r}: rounds of changes must be 1..{MAX_ROUNDS}")
    return m.group(1), k


# ---- the scene's objects as boxes on the floor -------------------------------------------------------------


def _aabb(o: InstanceInfo) -> tuple[float, float, float, float]:
    (x, y, _), (sx, sy, _) = o.position, o.size
    return (x - sx / 2, y - sy / 2, x + sx / 2, y + sy / 2)


def _base_z(o: InstanceInfo) -> float:
    return float(o.position[2] - o.size[2] / 2)


def _snapshot(o: InstanceInfo) -> dict[str, Any]:
    return {"room": o.room, "room_kind": o.room_kind, "position": list(o.position), "support": o.support,
            "state": o.attributes.get("state")}


def _levels(f: InstanceInfo) -> list[float]:
    """Heights where a small object can stand on furniture ``f`` (boards of shelves, tops of boxes/tables)."""
    kind = FURNITURE[f.category]
    h = kind.size[2]
    if kind.shape == "shelf":
        return [z + 0.03 for z in (0.45, 0.9, 1.35) if z + 0.03 < h - 0.3]
    return [h]


def _supports(scene: Scene, kind: catalog.SmallObjectKind) -> list[InstanceInfo | None]:
    """Furniture ``kind`` may stand on, in rooms it may be in (None = the floor). Seats and beds are left out:
    their backs, headboards and pillows lie on a side the scene graph does not record."""
    out: list[InstanceInfo | None] = []
    for f in scene.objects():
        fk = FURNITURE.get(f.category)
        if fk is None or f.category not in kind.on or fk.shape == "seat" or f.category == "bed":
            continue
        if kind.rooms and f.room_kind not in kind.rooms:
            continue
        out.append(f)
    if "floor" in kind.on and any(not kind.rooms or r.kind in kind.rooms for r in scene.rooms):
        out.append(None)
    return out


def _reach_size(scene: Scene) -> tuple[int, int]:
    """(number of free regions the robot cannot pass between, cells of the largest one)."""
    ok, _, _ = clearance_map(scene, ROBOT_RADIUS, GRID_RES)
    labels, n = ndimage.label(ok)
    if n == 0:
        return 0, 0
    sizes = np.bincount(labels.ravel())[1:]
    return int(n), int(sizes.max())


# ---- mesh surgery ----------------------------------------------------------------------------------------------


def _forget_derived(scene: Scene) -> None:
    scene._grids.clear()
    scene.cache.clear()


def _remove_mesh(scene: Scene, iid: int) -> None:
    keep = scene.triangle_instance != iid
    scene.triangles = scene.triangles[keep]
    scene.triangle_instance = scene.triangle_instance[keep]
    if scene.triangle_colors is not None:
        scene.triangle_colors = scene.triangle_colors[keep]
    _forget_derived(scene)


def _add_mesh(scene: Scene, iid: int, boxes: list[tuple[tuple[float, ...], tuple[float, ...], Any, str]]) -> None:
    mb = MeshBuilder()
    for lo, hi, color, faces in boxes:
        mb.box(lo, hi, iid, color, faces)
    v, t, ti, tc = mb.arrays()
    base = len(scene.vertices)
    scene.vertices = np.concatenate([scene.vertices, v]).astype(np.float32)
    scene.triangles = np.concatenate([scene.triangles, t + base]).astype(np.int32)
    scene.triangle_instance = np.concatenate([scene.triangle_instance, ti]).astype(np.int32)
    if scene.triangle_colors is not None:
        scene.triangle_colors = np.concatenate([scene.triangle_colors, tc]).astype(np.uint8)
    _forget_derived(scene)


def _compact(scene: Scene) -> None:
    """Drop the vertices no triangle uses any more (those of removed geometry)."""
    used = np.unique(scene.triangles)
    remap = np.full(len(scene.vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    scene.vertices = scene.vertices[used]
    scene.triangles = remap[scene.triangles].astype(np.int32)
    _forget_derived(scene)


# ---- placing a small object -------------------------------------------------------------------------------------


@dataclass
class _Placement:
    room: Room
    support: int | None
    boxes: list[tuple[tuple[float, ...], tuple[float, ...], Any, str]]
    aabb: tuple[float, float, float, float]
    z: float


def _boxes_at(category: str, state: str | None, color: str, x: float, y: float, z: float,
              facing: tuple[int, int]) -> tuple[list, tuple[float, float, float, float]]:
    w, d, h = SMALL_OBJECTS[category].size
    boxes = _object_boxes(category, state, COLORS[color], Frame2D((x, y), facing), 0.0, 0.0, z, w, d, h)
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    return boxes, (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def _door_keepouts(scene: Scene, room: Room) -> list[tuple[float, float, float, float]]:
    out = []
    for dr in scene.doors:
        if room.id not in dr.rooms:
            continue
        cx, cy = dr.center
        half = dr.width / 2 + 0.3
        if dr.axis == "x":
            out.append((cx - half, cy - DOOR_KEEPOUT, cx + half, cy + DOOR_KEEPOUT))
        else:
            out.append((cx - DOOR_KEEPOUT, cy - half, cx + DOOR_KEEPOUT, cy + half))
    return out


def _fits(scene: Scene, p: _Placement, skip: int | None) -> bool:
    """No overlap with other objects: on a support, with the objects at the same level of it; on the floor,
    with every object's floor footprint and the doors' keep-out areas; always inside the room's walls."""
    x0, y0, x1, y1 = p.room.rect
    inner = (x0 + HALF_WALL, y0 + HALF_WALL, x1 - HALF_WALL, y1 - HALF_WALL)
    a = p.aabb
    if not (a[0] >= inner[0] and a[1] >= inner[1] and a[2] <= inner[2] and a[3] <= inner[3]):
        return False
    for o in scene.objects():
        if o.id in (skip, p.support):
            continue
        if p.support is not None:
            if o.support == p.support and abs(_base_z(o) - p.z) < 0.05 and _overlap(a, _aabb(o), 0.02):
                return False
        elif _base_z(o) < 1.5 and _overlap(a, _aabb(o), 0.03):
            return False
    return p.support is not None or not any(_overlap(a, k) for k in _door_keepouts(scene, p.room))


def _propose(scene: Scene, rng: np.random.Generator, category: str, state: str | None, color: str,
             skip: int | None) -> _Placement | None:
    kind = SMALL_OBJECTS[category]
    supports = _supports(scene, kind)
    if not supports:
        return None
    s = supports[int(rng.integers(0, len(supports)))]
    facing = FACINGS[int(rng.integers(0, 4))]
    if s is None:
        rooms = [r for r in scene.rooms if not kind.rooms or r.kind in kind.rooms]
        room = rooms[int(rng.integers(0, len(rooms)))]
        x0, y0, x1, y1 = room.rect
        if x1 - x0 < 1.0 or y1 - y0 < 1.0:
            return None
        x, y, z = float(rng.uniform(x0 + 0.5, x1 - 0.5)), float(rng.uniform(y0 + 0.5, y1 - 0.5)), 0.0
        support = None
    else:
        room = scene.room(s.room) if s.room else None
        if room is None:
            return None
        levels = _levels(s)
        z = levels[int(rng.integers(0, len(levels)))]
        fx0, fy0, fx1, fy1 = _aabb(s)
        w, d, _ = kind.size
        m = SURFACE_INSET + max(w, d) / 2
        if fx1 - fx0 <= 2 * m or fy1 - fy0 <= 2 * m:
            return None
        x, y = float(rng.uniform(fx0 + m, fx1 - m)), float(rng.uniform(fy0 + m, fy1 - m))
        support = s.id
    boxes, aabb = _boxes_at(category, state, color, x, y, z, facing)
    if s is not None:
        fx0, fy0, fx1, fy1 = _aabb(s)
        if not (aabb[0] >= fx0 + SURFACE_INSET - 1e-6 and aabb[1] >= fy0 + SURFACE_INSET - 1e-6
                and aabb[2] <= fx1 - SURFACE_INSET + 1e-6 and aabb[3] <= fy1 - SURFACE_INSET + 1e-6):
            return None
    p = _Placement(room, support, boxes, aabb, z)
    return p if _fits(scene, p, skip) else None


def _put(scene: Scene, iid: int, p: _Placement) -> None:
    """Build object ``iid``'s geometry at ``p`` and update its scene-graph entry."""
    _add_mesh(scene, iid, p.boxes)
    lo = np.min([b[0] for b in p.boxes], axis=0)
    hi = np.max([b[1] for b in p.boxes], axis=0)
    info = scene.instances[iid]
    info.position = tuple(round(float(v), 4) for v in (lo + hi) / 2)  # type: ignore[assignment]
    info.size = tuple(round(float(v), 4) for v in hi - lo)  # type: ignore[assignment]
    info.support = p.support
    info.room, info.room_kind = p.room.id, p.room.kind


def _acceptable(scene: Scene, iid: int, p: _Placement, reach_before: tuple[int, int]) -> bool:
    """After ``_put``: a floor object left the robot's free space in one piece, and the object can be seen."""
    if p.support is None:
        n, largest = _reach_size(scene)
        w = p.aabb[2] - p.aabb[0] + 2 * ROBOT_RADIUS
        d = p.aabb[3] - p.aabb[1] + 2 * ROBOT_RADIUS
        if n > reach_before[0] or largest < reach_before[1] - math.ceil(w * d / GRID_RES**2):
            return False
    return iid in witness_poses(scene, None, ids=[iid], candidates=16)


def _place(scene: Scene, rng: np.random.Generator, iid: int, category: str, state: str | None, color: str) -> bool:
    """Put object ``iid`` somewhere new (its old geometry, if any, already gone); False when nothing fits."""
    reach = _reach_size(scene)
    for _ in range(ATTEMPTS):
        p = _propose(scene, rng, category, state, color, iid)
        if p is None:
            continue
        _put(scene, iid, p)
        if _acceptable(scene, iid, p, reach):
            return True
        _remove_mesh(scene, iid)
    return False


# ---- rounds ------------------------------------------------------------------------------------------------------


def _restore(scene: Scene, old: InstanceInfo, boxes: Any) -> None:
    scene.instances[old.id] = old
    scene.triangles, scene.triangle_instance, scene.triangle_colors = boxes
    _forget_derived(scene)


def _one_change(scene: Scene, rng: np.random.Generator, rnd: int, kind: str, done: set[int]) -> Change | None:
    small = [o for o in scene.objects() if o.category in SMALL_OBJECTS and o.id not in done]
    if kind == "add":
        cat = sorted(SMALL_OBJECTS)[int(rng.integers(0, len(SMALL_OBJECTS)))]
        sk = SMALL_OBJECTS[cat]
        color = sk.colors[int(rng.integers(0, len(sk.colors)))]
        state = sk.states[int(rng.integers(0, len(sk.states)))] if sk.states else None
        iid = max(scene.instances) + 1
        attrs = {"color": color} | ({"state": state} if state else {})
        scene.instances[iid] = InstanceInfo(iid, cat, None, None, attrs)
        if not _place(scene, rng, iid, cat, state, color):
            del scene.instances[iid]
            return None
        o = scene.instances[iid]
        return Change(rnd, "add", iid, cat, color, None, _snapshot(o))
    if kind == "state":
        small = [o for o in small if "state" in o.attributes]
    if not small:
        return None
    o = small[int(rng.integers(0, len(small)))]
    before = _snapshot(o)
    color = o.attributes.get("color", "")
    if kind == "remove":
        _remove_mesh(scene, o.id)
        del scene.instances[o.id]
        return Change(rnd, "remove", o.id, o.category, color, before, None)
    saved = copy.deepcopy(o), (scene.triangles, scene.triangle_instance, scene.triangle_colors)
    _remove_mesh(scene, o.id)
    if kind == "move":
        ok = _place(scene, rng, o.id, o.category, o.attributes.get("state"), color)
    else:  # state: the same spot, the other state (the footprint changes, so the facing that fits is searched)
        new_state = OPPOSITE_STATE[o.attributes["state"]]
        ok = False
        room = scene.room(o.room) if o.room else None
        reach = _reach_size(scene)
        for k in rng.permutation(4) if room is not None else []:
            boxes, aabb = _boxes_at(o.category, new_state, color, o.position[0], o.position[1], _base_z(o),
                                    FACINGS[int(k)])
            p = _Placement(room, o.support, boxes, aabb, _base_z(o))  # type: ignore[arg-type]
            if o.support is not None:
                s = scene.instances[o.support]
                fx0, fy0, fx1, fy1 = _aabb(s)
                if not (aabb[0] >= fx0 and aabb[1] >= fy0 and aabb[2] <= fx1 and aabb[3] <= fy1):
                    continue
            if not _fits(scene, p, o.id):
                continue
            _put(scene, o.id, p)
            if _acceptable(scene, o.id, p, reach):
                o.attributes["state"] = new_state
                ok = True
                break
            _remove_mesh(scene, o.id)
    if not ok:
        _restore(scene, saved[0], saved[1])
        return None
    return Change(rnd, kind, o.id, o.category, color, before, _snapshot(scene.instances[o.id]))


def apply_round(scene: Scene, base_seed: int, rnd: int) -> list[Change]:
    """Make round ``rnd``'s changes to ``scene`` in place (its mesh and scene graph); the changes made."""
    rng = np.random.default_rng([int(base_seed), ROUND_STREAM, int(rnd)])
    out: list[Change] = []
    done: set[int] = set()
    for _ in range(CHANGES_PER_ROUND * 4):
        if len(out) >= CHANGES_PER_ROUND:
            break
        kind = KINDS[int(rng.choice(len(KINDS), p=KIND_WEIGHTS / KIND_WEIGHTS.sum()))]
        ch = _one_change(scene, rng, rnd, kind, done)
        if ch is not None:
            out.append(ch)
            done.add(ch.object_id)
    return out


def next_house(prev: Scene, k: int) -> tuple[Scene, list[Change]]:
    """House ``-c<k>`` made from house ``-c<k-1>`` ``prev`` (the base house for ``k = 1``): a new scene after
    round ``k``, and that round's changes. The library builds a changed house this way from the cached one before
    it, so asking for ``-c1`` .. ``-c<k>`` in turn costs one round each."""
    base_id = prev.id if k == 1 else prev.id.rsplit("-c", 1)[0]
    if k != 1 and prev.id != changed_scene_id(base_id, k - 1):
        raise ValueError(f"house -c{k} is made from house -c{k - 1}, not from {prev.id}")
    sid = changed_scene_id(base_id, k)
    if prev.seed is None or k < 1:
        raise ValueError(f"scene {prev.id} has no seed, or k = {k} < 1: only generated houses can change")
    scene = Scene(
        id=sid, seed=prev.seed, vertices=prev.vertices.copy(), triangles=prev.triangles.copy(),
        triangle_instance=prev.triangle_instance.copy(),
        triangle_colors=None if prev.triangle_colors is None else prev.triangle_colors.copy(),
        instances=copy.deepcopy(prev.instances), rooms=list(prev.rooms), doors=list(prev.doors),
        wall_height=prev.wall_height, source=prev.source,
    )
    out = apply_round(scene, prev.seed, k)
    _compact(scene)
    return scene, out


def changed_house(base: Scene, k: int) -> tuple[Scene, list[Change]]:
    """The house ``base`` after rounds 1..k (a new scene, id ``<base>-c<k>``) and the changes of those rounds."""
    changed_scene_id(base.id, k)
    scene, out = base, []
    for rnd in range(1, int(k) + 1):
        scene, made = next_house(scene, rnd)
        out += made
    return scene, out


def changes_of(base: Scene, k: int) -> list[Change]:
    """The changes of rounds 1..k of ``base`` (in the order they were made)."""
    return changed_house(base, k)[1]
