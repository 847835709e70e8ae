"""Loader of the real HM-EQA question set (Explore-EQA) into :class:`eqa.messages.Question`.

``questions.csv`` holds ``scene, floor, question, choices, question_formatted, answer, label``;
``scene_init_poses.csv`` holds ``scene_floor, init_x, init_y, init_z, init_angle`` in habitat's frame
(``y`` up, agent forward ``-z`` turned by ``init_angle`` about ``+y``). Poses become our ``z``-up frame:
``x = init_x``, ``y = -init_z``, ``yaw = init_angle + pi/2``; ``init_y`` is the floor height of that storey.
The scans themselves (HM3D) are not here: :func:`missing_scans` says exactly what is missing and where to
put it (``EQA_HM3D_DIR``).
"""

from __future__ import annotations

import ast
import csv
import math
from dataclasses import dataclass
from pathlib import Path

from eqa.messages import Pose2D, Question
from services.sim.scene import MESH_SUFFIXES

POSES_FILE = "scene_init_poses.csv"
QUESTIONS_FILE = "questions.csv"


class HMEQAError(ValueError):
    """A missing or malformed HM-EQA file."""


@dataclass(frozen=True)
class InitPose:
    pose: Pose2D
    floor_height: float


def load_init_poses(path: Path) -> dict[tuple[str, int], InitPose]:
    """``(scene, floor) -> InitPose`` from ``scene_init_poses.csv``."""
    path = Path(path)
    if not path.is_file():
        raise HMEQAError(f"{path} does not exist")
    out = {}
    with path.open(newline="") as f:
        for n, row in enumerate(csv.DictReader(f), start=2):
            try:
                scene, floor = row["scene_floor"].rsplit("_", 1)
                x, y, z, a = (float(row[k]) for k in ("init_x", "init_y", "init_z", "init_angle"))
                yaw = math.atan2(math.sin(a + math.pi / 2), math.cos(a + math.pi / 2))
                out[(scene, int(floor))] = InitPose(Pose2D(x=x, y=-z, yaw=yaw), floor_height=y)
            except (KeyError, ValueError, AttributeError) as exc:
                raise HMEQAError(f"{path}:{n}: malformed row ({exc})") from exc
    return out


def load_hmeqa(data_dir: Path, hm3d_dir: Path | None = None) -> list[Question]:
    """All HM-EQA questions of ``data_dir`` (``questions.csv`` + ``scene_init_poses.csv``) as Questions,
    with their start poses. ``max_steps`` is left unset: the scene area is known only with the scan
    (``T = int(3 * sqrt(area))`` once loaded). ``query`` is empty: there is no structured parse of the
    real questions (the oracle scorer needs simulator semantics anyway)."""
    data_dir = Path(data_dir)
    qpath = data_dir / QUESTIONS_FILE
    if not qpath.is_file():
        raise HMEQAError(f"{qpath} does not exist (expected the HM-EQA {QUESTIONS_FILE} there)")
    poses = load_init_poses(data_dir / POSES_FILE)
    out = []
    with qpath.open(newline="") as f:
        for n, row in enumerate(csv.DictReader(f), start=2):
            try:
                scene = row["scene"].strip()
                floor = int(row["floor"])
                choices = [str(c) for c in ast.literal_eval(row["choices"])]
                init = poses.get((scene, floor))
                out.append(Question(
                    id=f"hmeqa-{n - 2:04d}", text=row["question"].strip(), choices=choices, scene=scene,
                    floor=floor, category=(row.get("label") or "").strip() or None,
                    answer=row["answer"].strip(), start_pose=init.pose if init else None,
                ))
            except (KeyError, ValueError, SyntaxError) as exc:
                raise HMEQAError(f"{qpath}:{n}: malformed row ({exc})") from exc
    return out


def scan_path(hm3d_dir: Path | None, scene: str) -> Path | None:
    """The mesh of one HM3D scene under ``hm3d_dir`` (``<scene>/*.glb``, not the ``.semantic`` one)."""
    if hm3d_dir is None:
        return None
    folder = Path(hm3d_dir) / scene
    if folder.is_dir():
        meshes = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES and ".semantic" not in p.name)
        if meshes:
            return meshes[0]
    for suffix in MESH_SUFFIXES:
        p = Path(hm3d_dir) / f"{scene}{suffix}"
        if p.is_file():
            return p
    return None


def missing_scans(questions: list[Question], hm3d_dir: Path | None) -> str | None:
    """``None`` if every scene of ``questions`` has a scan under ``hm3d_dir``, else what is missing and
    where to put it."""
    scenes = sorted({q.scene for q in questions})
    missing = [s for s in scenes if scan_path(hm3d_dir, s) is None]
    if not missing:
        return None
    example = missing[0]
    where = f"EQA_HM3D_DIR={hm3d_dir}" if hm3d_dir else "EQA_HM3D_DIR (unset)"
    return (
        f"HM3D scans missing for {len(missing)} of {len(scenes)} HM-EQA scenes (e.g. {', '.join(missing[:3])}). "
        "The HM-EQA questions need the HM3D v0.2 scans (license from Matterport, "
        "https://aihabitat.org/datasets/hm3d/). "
        f"Put each scene's mesh at <{where}>/<scene>/<name>.glb, e.g. {example}/{example.split('-', 1)[-1]}.glb "
        f"(a .glb with ordinary PNG/JPEG textures, .ply or .obj; Basis-compressed textures are not read), and "
        f"copy {POSES_FILE} next to them so that each storey's floor height is known."
    )
