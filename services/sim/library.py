"""The scene library: a scene id to its :class:`~services.sim.scene.Scene`.

``gen-<seed>`` is a generated house (:mod:`services.sim.housegen`), saved under ``scenes_dir/<id>/`` on first
use and reloaded from there; ``gen-<seed>-c<k>`` is that house after ``k`` rounds of changes
(:mod:`services.sim.changes`), made from it and saved the same way;
any other id is a mesh file (:func:`services.sim.scene.load_mesh_scene`). This
module sits above both the scene model and the generator, so neither imports the other's caller.
"""

from __future__ import annotations

from pathlib import Path

from services.sim.changes import changed_scene_id, next_house, parse_changed_id
from services.sim.housegen import generate_house
from services.sim.scene import GEN_ID, MESH_SUFFIXES, Scene, SceneNotFound, load_mesh_scene


def _mesh_candidates(scene_id: str, dirs: list[Path]) -> list[Path]:
    out = []
    for d in dirs:
        for suffix in MESH_SUFFIXES:
            out.append(d / f"{scene_id}{suffix}")
        sub = d / scene_id
        if sub.is_dir():
            out.extend(sorted(p for p in sub.iterdir() if p.suffix.lower() in MESH_SUFFIXES))
    return [p for p in out if p.is_file()]


def available_scenes(scenes_dir: Path) -> list[str]:
    """Scene ids present under ``scenes_dir`` (saved generated houses and mesh files)."""
    scenes_dir = Path(scenes_dir)
    if not scenes_dir.is_dir():
        return []
    ids = set()
    for p in scenes_dir.iterdir():
        if p.name.startswith("."):
            continue
        if p.is_dir() and ((p / "scene.json").exists() or any(c.suffix.lower() in MESH_SUFFIXES for c in p.iterdir())):
            ids.add(p.name)
        elif p.suffix.lower() in MESH_SUFFIXES:
            ids.add(p.stem)
    return sorted(ids)


def load_or_generate(scene_id: str, scenes_dir: Path, hm3d_dir: Path | None = None) -> Scene:
    """The scene ``scene_id``: ``gen-<seed>`` is loaded from ``scenes_dir/<id>/`` or generated and saved
    there; any other id is a mesh file ``scenes_dir/<id>.{glb,ply,obj}``, ``scenes_dir/<id>/*.glb`` (or the
    same under ``hm3d_dir``). Raises :class:`SceneNotFound` naming what exists and how to add a scene."""
    scenes_dir = Path(scenes_dir)
    if not isinstance(scene_id, str) or not scene_id or "/" in scene_id or scene_id.startswith("."):
        raise SceneNotFound(f"scene id {scene_id!r} is not valid")
    m = GEN_ID.match(scene_id)
    if m:
        directory = scenes_dir / scene_id
        if (directory / "scene.json").exists():
            return Scene.load(directory)
        scene = generate_house(int(m.group(1)))
        scene.save(directory)
        return scene
    try:
        changed = parse_changed_id(scene_id)
    except ValueError as exc:
        raise SceneNotFound(str(exc)) from exc
    if changed is not None:
        directory = scenes_dir / scene_id
        if (directory / "scene.json").exists():
            return Scene.load(directory)
        base, k = changed
        previous = load_or_generate(changed_scene_id(base, k - 1), scenes_dir)  # cached too: one round per house
        scene, _ = next_house(previous, k)
        scene.save(directory)
        return scene
    dirs = [scenes_dir] + ([Path(hm3d_dir)] if hm3d_dir else [])
    found = _mesh_candidates(scene_id, dirs)
    if found:
        return load_mesh_scene(found[0], scene_id=scene_id)
    have = available_scenes(scenes_dir)
    listed = ", ".join(have[:20]) + (" ..." if len(have) > 20 else "") if have else "none"
    raise SceneNotFound(
        f"unknown scene {scene_id!r}. Generated houses are 'gen-<seed>' (e.g. gen-00042, made on first use). "
        f"Scenes present in {scenes_dir}: {listed}. To add a real mesh, put {scene_id}.glb (or .ply/.obj) in "
        f"{scenes_dir} (EQA_SCENES_DIR) or a folder {scene_id}/ with the mesh in EQA_HM3D_DIR"
        f"{f' ({hm3d_dir})' if hm3d_dir else ' (unset)'}."
    )


def floor_area(scene_id: str, scenes_dir: Path, hm3d_dir: Path | None = None) -> float:
    """Floor area (m2) of the scene ``scene_id`` (the gateway's default step budget, ``3 * sqrt(area)``). A changed
    house has its base house's rooms, so its area is the base's (the changed house is built by the sim only)."""
    try:
        changed = parse_changed_id(scene_id)
    except ValueError as exc:
        raise SceneNotFound(str(exc)) from exc
    if changed is not None:
        scene_id = changed[0]
    return float(load_or_generate(scene_id, scenes_dir, hm3d_dir).floor_area_m2)
