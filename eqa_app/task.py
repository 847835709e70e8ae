"""``eqa task``: one HELIOS task end to end through the real services, printing the outcome of each phase.

Without ``--url`` it starts the whole fleet (every service as its own process, over Zenoh, and the gateway on a
free port), submits the task to ``POST /v1/tasks``, follows the episode's events (the phases: searching, local
search, looking, picking, placing, and the skills' outcomes), prints the per-phase metrics (FindObj, Pick,
FindRec, Place, SR for pick-and-place; SR, SPL for object search), and stops the fleet. With ``--url`` it uses a
running gateway (``eqa up``). Ground-truth metrics need a generated house (``gen-<seed>``): its object ids are
read from the scene graph by the simulator, never by the planner. A task naming an object or receptacle the
house lacks is refused before anything starts, with what the house has (the simulator refuses it too).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from eqa.messages import Task

log = logging.getLogger(__name__)

PHASES_PICK_PLACE = ("FindObj", "Pick", "FindRec", "Place", "SR")
SIMULATED = ("perception: oracle detector = a simulated perception model reading ground-truth labels of the "
             "visible pixels, not a detector")

# The demo task and the outcome its run had, both set from ``python -m eqa_app.task_demo`` (the rule and the
# committed runs: eqa_app/task_demo.py; tests/tasks/test_task_cli.py checks them against the runs).
DEMO_TASK_ID = "gen-115006-pp1"
DEMO_OUTCOME = "failed: pick failed, in phase picking at step 80"
DEMO_SUCCESSES = (9, 24)  # tasks of the rule's pool that succeeded, of all

EXIT_CODES = """exit codes:
  0  the task succeeded
  1  the task failed (the end says the first failure), or the episode did not finish (error, timeout)
  2  bad input: an instruction, scene or option the command cannot use, a task naming an object or
     receptacle the house lacks (the error says what it has), or a gateway that refused the request
  130 interrupted (Ctrl-C)"""


def help_text() -> str:
    """The description of ``eqa task --help``: the module doc, the examples with what each does (every one is
    run by tests/tasks/test_task_cli.py), the exit codes."""
    wins, pool = DEMO_SUCCESSES
    examples = f"""examples:
  eqa task
      the demo: {DEMO_TASK_ID} of the tuning seed 11, a typical task there (eqa_app/task_demo.py: helios
      succeeds in {wins} of {pool}), with the draws of its benchmark run, so it ends as that run did:
      "{DEMO_OUTCOME}"; exit {0 if DEMO_OUTCOME == "success" else 1}
  eqa task "Move the kettle from the kitchen counter to the coffee table" --scene gen-15000
      pick and place in generated house 15000 (start pose sampled from seed 0, fresh detector draws each
      run); prints each step, then the phases FindObj, Pick, FindRec, Place, SR; exit 0 when the kettle
      ends on a coffee table, else 1
  eqa task "Find a potted plant" --scene gen-15000 --ablation trusting --seed 3 --max-steps 10
      object search by the trusting agent (it acts on its first detection), at most 10 steps; --seed 3
      repeats the start pose and the simulated detector's draws, so every run prints the same steps: it
      stops at step 7, not near a plant; exit 1
  eqa task "Move the mug from the kitchen counter to the dining table" --scene gen-15000
      refused at once, exit 2: "gen-15000 has no mug on a kitchen counter (its pickable objects: ...)"
"""
    return f"{__doc__}\n{examples}\n{EXIT_CODES}\n"


def demo_task(scenes_dir: Path) -> Task:
    """The demo task (:data:`DEMO_TASK_ID`, chosen by :mod:`eqa_app.task_demo`'s rule) from the tuning seed's
    task benchmark."""
    from eqa.seeds import TUNING_SEED
    from eqa_app.task_demo import DEMO_POOL
    from services.sim.tasks import task_benchmark

    tasks = task_benchmark(TUNING_SEED, pick_place=DEMO_POOL, find=0, scenes_dir=scenes_dir).tasks
    return next(t for t in tasks if t.id == DEMO_TASK_ID)


def _pick_limit(text: str) -> int | None:
    from services.planner.decisions import pick_limit  # one parser of "1", "5", "unlimited"

    try:
        return pick_limit(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(subparsers: argparse._SubParsersAction) -> None:
    from eqa_app.ask import add_episode_run_options, parse_pose

    p = subparsers.add_parser(
        "task", help="run one pick-and-place or object-search task end to end (HELIOS) and print each phase",
        description=help_text(), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("instruction", nargs="?",
                   help="'Move the <object> from the <start receptacle> to the <goal receptacle>' or "
                   "'Find a <object>'; omit it for the demo, a typical task of the tuning seed 11")
    p.add_argument("--scene", help="scene id, e.g. gen-15000 (a generated house)")
    p.add_argument("--pose", type=parse_pose, help="start pose x,y[,yaw]; default: sampled")
    p.add_argument("--ablation", default="helios", choices=["helios", "no_global", "trusting"],
                   help="agent variant (paper Table 1): helios (full), no_global (always a candidate before a "
                   "frontier), trusting (acts on the first detection)")
    p.add_argument("--pick-limit", type=_pick_limit, default=None,
                   help="pick attempts: 1, 5, ... or unlimited (default unlimited)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="step budget (default 6*sqrt(floor area), the task benchmark's)")
    p.add_argument("--seed", type=int, default=None,
                   help="repeat a run: the start pose sampling and the simulated perception models' draws come from "
                   "this seed, so the same command prints the same steps (default: start pose from seed 0, fresh "
                   "draws every run; the demo: the draws of its benchmark run)")
    p.add_argument("--no-record", action="store_true", help="no Rerun recording")
    add_episode_run_options(p, 900.0, "the end")
    p.set_defaults(func=run)


def seed_draws(seed: int) -> str:
    """The draw key (``POST /v1/tasks`` ``draws``) of a run repeated with ``--seed``: a function of the seed alone."""
    return f"seed-{seed}"


def check_task(instruction: str, scene_id: str, scenes_dir: Path) -> None:
    """:class:`~eqa_app.ask.AskError` when the instruction cannot be read or names an object or receptacle the
    house lacks (:func:`services.sim.tasks.scene_lacks`: one line with what it has)."""
    from pydantic import ValidationError

    from eqa.instructions import InstructionError, parse_instruction
    from eqa_app.ask import AskError
    from services.sim.library import load_or_generate
    from services.sim.tasks import scene_lacks

    try:
        p = parse_instruction(instruction)
        task = Task(kind=p.kind, text=instruction, scene=scene_id, object=p.object,  # type: ignore[arg-type]
                    start_receptacle=p.start_receptacle, goal_receptacle=p.goal_receptacle)
    except InstructionError as exc:
        raise AskError(str(exc)) from None
    except ValidationError as exc:
        raise AskError("; ".join(str(e.get("msg", "")).removeprefix("Value error, ") for e in exc.errors())) from None
    lacks = scene_lacks(task, load_or_generate(scene_id, scenes_dir))
    if lacks is not None:
        raise AskError(lacks)


def _body(args: argparse.Namespace, scenes_dir: Path) -> dict[str, Any]:
    from eqa.instructions import InstructionError, parse_instruction
    from eqa_app.ask import AskError

    instruction, scene, pose, seed, draws = args.instruction, args.scene, args.pose, args.seed, None
    if seed is not None:
        draws = seed_draws(seed)
    if instruction is None:
        from eqa_app.task_demo import demo_draws

        demo = demo_task(scenes_dir)
        instruction = demo.text
        if scene is None and pose is None:
            pose = demo.start_pose
        scene = scene or demo.scene
        if seed is None and (scene, pose) == (demo.scene, demo.start_pose) and args.max_steps in (None, demo.max_steps):
            seed, draws = demo_draws(demo.id, demo.max_steps or 0)  # the rule's run, step for step
    try:
        parse_instruction(instruction)
    except InstructionError as exc:
        raise AskError(str(exc)) from None
    if scene is None:
        raise AskError("give --scene (e.g. --scene gen-15000)")
    body: dict[str, Any] = {"instruction": instruction, "scene": scene, "ablation": args.ablation,
                            "pick_limit": args.pick_limit, "seed": seed or 0, "record": not args.no_record}
    if draws is not None:
        body["draws"] = draws
    if pose is not None:
        body["start_pose"] = pose.model_dump()
    if args.max_steps is not None:
        if args.max_steps < 1:
            raise AskError("--max-steps must be at least 1")
        body["max_steps"] = args.max_steps
    return body


def exit_code(status: dict[str, Any]) -> int:
    """:data:`EXIT_CODES` of a finished task episode's status."""
    if status.get("state") == "failed" and str(status.get("stop_reason") or "").startswith("sim refused"):
        return 2  # the robot refused the task as given (a house without the named object, a bad pose)
    out = outcome_of(status)
    return 0 if status.get("state") == "stopped" and out is not None and out["success"] else 1


def outcome_of(s: dict[str, Any]) -> dict[str, Any] | None:
    """The task's outcome (:func:`eqa.task_traces.task_outcome`): the gateway's, else from the metrics; None
    without metrics."""
    from eqa.task_traces import task_outcome

    m = s.get("metrics") or {}
    task = s.get("task") or {}
    return s.get("outcome") or (task_outcome(task.get("kind", "pick_place"), m, s.get("state", ""),
                                             s.get("stop_reason") or "", s.get("steps"), s.get("max_steps"))
                                if m else None)


def run(args: argparse.Namespace) -> int:
    from eqa.service import setup_logging
    from eqa_app.ask import AskError, _with_fleet, check_scene, follow
    from eqa_app.cli import UsageError, check_scorer, load_settings

    settings = load_settings()
    if args.url is None:
        check_scorer(settings)
    setup_logging("WARNING" if args.json else settings.log_level, "eqa-task")
    for name in ("eqa.launcher", "httpx"):
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        body = _body(args, settings.scenes_path)
        if args.url is None:  # a running gateway checks on its own scenes (its simulator refuses what is missing)
            check_scene(body["scene"], settings.scenes_path)
            check_task(body["instruction"], body["scene"], settings.scenes_path)
    except AskError as exc:
        raise UsageError(str(exc)) from None
    if not args.json:
        limit = body["pick_limit"] or "unlimited"
        repeat = f"   seed: {body['seed']} (draws {body['draws']})" if "draws" in body else ""
        print(f"task: {body['instruction']}\nscene: {body['scene']}   agent: {body['ablation']}   "
              f"pick attempts: {limit}{repeat}", flush=True)
    try:
        if args.url is not None:
            outcome = follow(args.url, body, args.token, args.timeout, args.json, "/v1/tasks")
        else:
            outcome = _with_fleet(settings, body, args, "/v1/tasks")
    except AskError as exc:
        raise UsageError(str(exc)) from None
    report(outcome.status, settings, args.json, outcome.seconds, outcome.events)
    return exit_code(outcome.status)


def report(s: dict[str, Any], settings: Any, as_json: bool, seconds: float = 0.0, events: int = 0) -> None:
    """The per-phase outcome of a finished task episode."""
    if as_json:
        print(json.dumps(s))
        return
    m = s.get("metrics") or {}
    task = s.get("task") or {}
    out = outcome_of(s)
    state = s.get("state")
    if out is not None and state == "stopped":
        state = "task succeeded" if out["success"] else "task failed"
    print()
    print(f"episode {s.get('episode_id')}: {state} after {s.get('steps')} of {s.get('max_steps')} steps: "
          f"{s.get('stop_reason')}")
    if not m:
        print("no metrics (the episode ended before the simulator reported any)")
    elif task.get("kind") == "find_object":
        print(f"  found: {'yes' if m.get('SR') else 'no'}   SPL: {m.get('SPL', 0.0):.3f}   "
              f"collisions: {int(m.get('collisions', 0))}")
    else:
        marks = "   ".join(f"{k}: {'yes' if m.get(k) else 'no'}" for k in PHASES_PICK_PLACE)
        print(f"  {marks}")
        print(f"  pick attempts: {int(m.get('pick_attempts', 0))}   collisions: {int(m.get('collisions', 0))}")
    if out is not None:
        print(f"  outcome: {out['text']}")
    if settings.scorer_backend == "oracle":
        print(f"note: {SIMULATED}")
    if s.get("recording"):
        from eqa.recording import recording_dir

        print(f"recording: {recording_dir(settings, s['episode_id']).resolve()}/ (rerun it; merged: "
              f"GET {s['recording']})")
    if seconds:
        print(f"time: {seconds:.1f} s, {events} events")
    sys.stdout.flush()
