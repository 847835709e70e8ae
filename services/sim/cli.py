"""``eqa sim ...`` commands: render one view, draw a floor plan, write the benchmark, check HM-EQA files, list
the changes of a changed house."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _scenes_dir(args: argparse.Namespace) -> Path:
    if args.scenes_dir:
        return Path(args.scenes_dir)
    from eqa.settings import Settings

    return Settings().scenes_path


def _message(exc: Exception) -> str:
    """The text of an exception; a KeyError subclass (SceneNotFound) quotes it, so drop those quotes only."""
    msg = str(exc)
    return msg[1:-1] if len(msg) > 1 and msg[0] == msg[-1] and msg[0] in "'\"" else msg


def _fail(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return 2


def _load(args: argparse.Namespace):
    from eqa.settings import Settings
    from services.sim.service import load_scene

    settings = Settings()
    if args.scenes_dir:
        settings = settings.model_copy(update={"scenes_dir": Path(args.scenes_dir)})
    return load_scene(settings, args.scene)


def cmd_render(args: argparse.Namespace) -> int:
    from PIL import Image

    from eqa.messages import Pose2D
    from services.sim.camera import camera_pose, intrinsics
    from services.sim.motion import pose_error
    from services.sim.render import Renderer
    from services.sim.scene import SceneLoadError, SceneNotFound

    try:
        pose = Pose2D.parse(args.pose)
        if args.width < 1 or args.height < 1:
            raise ValueError("--width and --height must be positive")
        scene = _load(args)
    except (ValueError, SceneNotFound, SceneLoadError) as exc:
        return _fail(_message(exc))
    reason = pose_error(scene, pose)
    if reason is not None and not args.force:
        return _fail(f"{reason} (use --force to render anyway)")
    K = intrinsics(args.width, args.height, args.hfov)
    out = Renderer(scene).render(camera_pose(pose, tilt_deg=args.tilt), K, args.width, args.height)
    dest = Path(args.out)
    dest.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(out.rgb).save(dest)
    print(f"wrote {dest} ({args.width}x{args.height}, scene {scene.id})")
    if args.depth_out:
        d = out.depth
        vis = (255 * (1 - np.clip(d / max(float(d.max()), 1e-6), 0, 1)) * (d > 0)).astype("uint8")
        Image.fromarray(vis).save(args.depth_out)
        print(f"wrote {args.depth_out} (depth, near = bright)")
    return 0


def cmd_floorplan(args: argparse.Namespace) -> int:
    from services.sim.floorplan import draw_floorplan, read_trajectory
    from services.sim.scene import SceneLoadError, SceneNotFound

    try:
        traj = read_trajectory(Path(args.trajectory)) if args.trajectory else None
        scene = _load(args)
    except (OSError, ValueError, KeyError, SceneNotFound, SceneLoadError) as exc:
        return _fail(_message(exc))
    dest = draw_floorplan(scene, Path(args.out), traj)
    print(f"wrote {dest} (scene {scene.id}, {scene.floor_area_m2:.0f} m2, {len(scene.rooms)} rooms)")
    return 0


def cmd_benchmark(args: argparse.Namespace) -> int:
    from services.sim.questions import benchmark

    if args.seed < 0:
        return _fail("--seed must be >= 0")
    bench = benchmark(args.seed, _scenes_dir(args))
    dest = bench.save(Path(args.out))
    print(f"wrote {dest}: {len(bench.calibration)} calibration + {len(bench.test)} test questions "
          f"over {len(bench.scenes)} houses")
    return 0


def cmd_changes(args: argparse.Namespace) -> int:
    """The changes of rounds 1..k of a generated house as JSON; with ``--questions``, which of the house's
    generated questions they affect."""
    from services.sim.change_impact import impact
    from services.sim.changes import MAX_ROUNDS, changed_house
    from services.sim.library import load_or_generate
    from services.sim.scene import GEN_ID, SceneLoadError, SceneNotFound

    if not GEN_ID.match(args.scene):
        return _fail(f"--scene must be a generated house gen-<seed> (e.g. gen-00042), not {args.scene!r}")
    if not 1 <= args.rounds <= MAX_ROUNDS:
        return _fail(f"--rounds must be 1..{MAX_ROUNDS}")
    try:
        base = load_or_generate(args.scene, _scenes_dir(args))
    except (SceneNotFound, SceneLoadError) as exc:
        return _fail(_message(exc))
    house, changes = changed_house(base, args.rounds)
    out: dict[str, object] = {"scene": house.id, "changes": [c.to_json() for c in changes]}
    if args.questions:
        from services.sim.questions import generate_questions

        rows = []
        for q in generate_questions(base, np.random.default_rng([0, int(base.seed or 0), 11])):
            im = impact(q, changes, house)
            rows.append({"id": q.id, "text": q.text, "answer": q.answer, "affected": im.affected,
                         "answer_changed": im.answer_changed, "evidence_changed": im.evidence_changed,
                         "answer_now": im.question.answer if im.question else None, "touched": im.touched})
        out["questions"] = rows
    print(json.dumps(out, indent=1))
    return 0


def cmd_hmeqa(args: argparse.Namespace) -> int:
    from services.sim.hmeqa import HMEQAError, load_hmeqa, missing_scans

    hm3d = Path(args.hm3d_dir) if args.hm3d_dir else None
    if hm3d is None:
        from eqa.settings import Settings

        hm3d = Settings().hm3d_dir
    try:
        qs = load_hmeqa(Path(args.data_dir))
    except HMEQAError as exc:
        return _fail(str(exc))
    scenes = sorted({q.scene for q in qs})
    print(json.dumps({"questions": len(qs), "scenes": len(scenes),
                      "with_start_pose": sum(q.start_pose is not None for q in qs)}))
    missing = missing_scans(qs, hm3d)
    if missing:
        print(missing, file=sys.stderr)
        return 1
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    sim = subparsers.add_parser("sim", help="simulator tools: render, floorplan, benchmark, hmeqa, changes")
    sub = sim.add_subparsers(dest="sim_command", required=True)

    p = sub.add_parser("render", help="render the robot's camera view at a pose to a PNG")
    p.add_argument("--scene", required=True, help="scene id, e.g. gen-00042 or a mesh id")
    p.add_argument("--pose", required=True, help="x,y[,yaw] of the robot base (m, rad)")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--depth-out", default=None, help="also write a depth picture here")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--hfov", type=float, default=120.0, help="horizontal field of view (deg)")
    p.add_argument("--tilt", type=float, default=-30.0, help="camera pitch (deg, negative = down)")
    p.add_argument("--force", action="store_true", help="render even from a pose the robot cannot take")
    p.add_argument("--scenes-dir", default=None, help="default: EQA_SCENES_DIR or EQA_DATA_DIR/scenes")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("floorplan", help="draw a top-down floor plan with rooms, objects and a trajectory")
    p.add_argument("--scene", required=True)
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--trajectory", default=None, help="JSON list of [x,y(,yaw)] or lines 'x,y[,yaw]'")
    p.add_argument("--scenes-dir", default=None)
    p.set_defaults(func=cmd_floorplan)

    p = sub.add_parser("benchmark", help="write the fixed benchmark (300 calibration + 200 test questions)")
    p.add_argument("--out", required=True, help="output JSON")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scenes-dir", default=None)
    p.set_defaults(func=cmd_benchmark)

    p = sub.add_parser("changes", help="list the seeded changes of house gen-<seed>-c<k> (moves, additions, "
                       "removals, state switches) and the questions they affect")
    p.add_argument("--scene", required=True, help="the base house, e.g. gen-00042")
    p.add_argument("--rounds", type=int, default=1, help="k: rounds of changes (1..20)")
    p.add_argument("--questions", action="store_true", help="also: the house's generated questions, affected or not")
    p.add_argument("--scenes-dir", default=None)
    p.set_defaults(func=cmd_changes)

    p = sub.add_parser("hmeqa", help="read the real HM-EQA files and say which HM3D scans are missing")
    p.add_argument("--data-dir", required=True, help="folder with questions.csv and scene_init_poses.csv")
    p.add_argument("--hm3d-dir", default=None, help="default: EQA_HM3D_DIR")
    p.set_defaults(func=cmd_hmeqa)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="eqa")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))
