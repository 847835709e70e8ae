"""``eqa ask``: one question end to end through the real services, printing the answer.

Without ``--url`` it starts the whole fleet (every service as its own process, talking only over Zenoh, and
the gateway on a free port), submits the question over HTTP, follows the episode's event stream, prints the
answer, the steps used and where the recording went, and stops the fleet. With ``--url`` it uses a running
gateway (``eqa up``). Without a question it asks a built-in demo question from a generated house, whose
ground truth is known, so the output also says whether the answer is right.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

from eqa import keys
from eqa.event_log import Identity, event_identity
from eqa.messages import (
    BOUND_STRATEGIES,
    EPS_GT,
    EPS_LT,
    MAX_CHOICES,
    Pose2D,
    Question,
    Strategy,
    eps_in_bounds,
    letters,
)

log = logging.getLogger(__name__)

PRODUCT_STRATEGIES = [s for s in get_args(Strategy) if s not in BOUND_STRATEGIES]  # the yardsticks read ground truth
DEMO_BENCHMARK_SEED, DEMO_HOUSE, DEMO_CATEGORY = 0, 151, "state"  # benchmark question gen-00151-sta0
DEMO_SCENE = f"gen-{DEMO_HOUSE:05d}"
ORACLE_LABEL = (
    "oracle scorer = a simulated perception model reading ground-truth labels of the visible pixels, not a VLM"
)


class AskError(Exception):
    """A problem the user can fix: one line, exit code 2."""


def parse_pose(text: str) -> Pose2D:
    """``x,y[,yaw]`` in metres/radians (argparse type over :meth:`Pose2D.parse`)."""
    try:
        return Pose2D.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def demo_question(scenes_dir: Path) -> Question:
    """Benchmark question ``gen-00151-sta0`` ("Is the box in the kitchen closed?", a 100 m2 house, ground
    truth known): with the packaged calibration the robot finds the box and stops, correct, at 12 of 30 steps."""
    from services.sim.questions import benchmark_candidates

    return benchmark_candidates(DEMO_BENCHMARK_SEED, DEMO_HOUSE, scenes_dir)[DEMO_CATEGORY][0]


def check_scene(scene: str, scenes_dir: Path) -> float:
    """Floor area of a scene the simulator can load; :class:`AskError` naming what exists otherwise."""
    from services.sim.library import load_or_generate
    from services.sim.scene import SceneNotFound

    try:
        return float(load_or_generate(scene, scenes_dir).floor_area_m2)
    except SceneNotFound as exc:
        raise AskError(str(exc).splitlines()[0]) from None


@dataclass
class Outcome:
    status: dict[str, Any]
    events: int
    seconds: float
    # a question that started from its home's memory and stopped on a table not calibrated for warm starts: the
    # reason of its first such decision (Decision.warm_calibrated False)
    warm_uncalibrated: str | None = None


def follow(url: str, body: dict[str, Any], token: str | None, timeout: float, quiet: bool,
           path: str = "/v1/questions") -> Outcome:
    """Submit over HTTP (``path``: ``/v1/questions`` or ``/v1/tasks``), print progress from the SSE stream, return
    the final status."""
    import httpx

    headers = {"Authorization": f"Bearer {token}"} if token else {}
    t0 = time.monotonic()
    with httpx.Client(base_url=url, headers=headers, timeout=httpx.Timeout(30.0, read=timeout)) as client:
        r = client.post(path, json=body)
        if r.status_code == 422:
            raise AskError(f"the gateway refused the question: {r.json().get('detail')}")
        if r.status_code >= 400:
            raise AskError(f"the gateway answered {r.status_code}: {r.text[:300]}")
        episode_id = r.json()["episode_id"]
        if not quiet:
            print(f"episode {episode_id} on {r.json().get('robot')}", flush=True)
        n = 0
        printer = StepPrinter(task=path == "/v1/tasks")
        uncalibrated: str | None = None
        with client.stream("GET", f"/v1/episodes/{episode_id}/events") as stream:
            for line in stream.iter_lines():
                if not line.startswith("data:"):
                    continue
                n += 1
                event = json.loads(line[5:].strip())
                if not quiet:
                    printer(event)
                if event.get("kind") == "decision" and event.get("warm_calibrated") is False and uncalibrated is None:
                    uncalibrated = str(event.get("reason", ""))
                if event.get("kind") in ("episode_end",) or event.get("state") in ("stopped", "failed", "cancelled"):
                    break
        status = client.get(f"/v1/episodes/{episode_id}").json()
    return Outcome(status=status, events=n, seconds=time.monotonic() - t0, warm_uncalibrated=uncalibrated)


def warm_warning(reason: str) -> str:
    """What ``eqa ask`` says of a question that started from its home's memory on a table not calibrated for warm
    starts: the note of the decision's reason (``services.stopper.state.WARM_NOT_CALIBRATED`` onwards)."""
    from services.stopper.state import WARM_NOT_CALIBRATED

    at = reason.find(WARM_NOT_CALIBRATED)
    note = reason[at:].rstrip(")") if at >= 0 else "stopping not calibrated for warm starts"
    return (f"this question started from its home's memory and its {note} (the coverage 1 - eps of Explore-EQA "
            "Claim 1 is not guaranteed; docs/homes.md, 'The exchangeability assumption')")


def _line(head: str, text: str, width: int | None = None) -> str:
    """``head`` then ``text`` whole, wrapped at words to the terminal's width (at least 60 columns), the
    continuation lines under the text's start: a long reason is never cut."""
    width = width or max(60, shutil.get_terminal_size((100, 24)).columns)
    return textwrap.fill(text or "", width=width, initial_indent=head, subsequent_indent=" " * len(head),
                         break_long_words=False, break_on_hyphens=False) or head.rstrip()


class StepPrinter:
    """Prints an episode's events as they come (:func:`_print_event`), each once: a step the sim sent again (a
    resend, a re-drive after a service instance came or went) brings the same frame, decision and goal again
    (:func:`eqa.event_log.event_identity`)."""

    def __init__(self, task: bool = False, width: int | None = None) -> None:
        self.task, self.width = task, width
        self.printed: set[Identity] = set()

    def __call__(self, event: dict[str, Any]) -> None:
        identity = event_identity(event)
        if identity in self.printed:
            return
        self.printed.add(identity)
        _print_event(event, self.task, self.width)


def _print_event(event: dict[str, Any], task: bool = False, width: int | None = None) -> None:
    """One line (wrapped, :func:`_line`) per event a user follows an episode by. In a ``task`` episode a step is
    the planner's goal; the stopper's decisions of its stand-in question (the ``max_steps`` rule, "running to the
    step limit") say nothing the step count does not, and they come from another service than the goal of
    the same step, so the bus may deliver either first: only the decision that ends the episode is printed. The
    planner's last goal (phase ``finished``) is not printed either: it races the episode's end to the gateway,
    which records nothing of an ended episode, and the end's summary says the same (its step and reason)."""
    kind = event.get("kind")
    if kind == "decision":
        if task and not event.get("stop"):
            return
        if event.get("rule") == "cp":
            pset = "{" + ",".join(event.get("prediction_set") or []) + "}"
            print(_line(f"  step {event.get('step'):>3}: set {pset:<11} ", event.get("reason", ""), width), flush=True)
        else:
            print(_line(f"  step {event.get('step'):>3}: ", event.get("reason", ""), width), flush=True)
    elif kind == "goal" and event.get("phase") and event.get("phase") != "finished":  # a task episode (eqa task)
        skill = event.get("skill") or "move"
        what = f"{skill} " if skill != "move" else ""
        print(_line(f"  step {event.get('step'):>3}: {event.get('phase'):<12} ", f"{what}{event.get('reason', '')}",
                    width), flush=True)
    elif kind == "frame" and event.get("skill"):
        s = event["skill"]
        print(_line(f"           {s['skill']} {'succeeded' if s['success'] else 'failed'}: ", s["reason"], width),
              flush=True)
    elif kind == "error":
        print(_line(f"  error from {event.get('source')}: ", event.get("reason", ""), width), flush=True)


def add_episode_run_options(p: argparse.ArgumentParser, timeout_s: float, waits_for: str) -> None:
    """The options of a command that runs one episode (``eqa ask``, ``eqa task``): a running gateway or a fleet
    of its own, how long to wait, and the output."""
    p.add_argument("--url", default=None, help="use a running gateway (eqa up) instead of starting a fleet")
    p.add_argument("--token", default=None, help="bearer token for --url")
    p.add_argument("--scorers", type=int, default=1, help="scorer replicas to start (default 1)")
    p.add_argument("--timeout", type=float, default=timeout_s, help=f"seconds to wait for {waits_for}")
    p.add_argument("--json", action="store_true", help="print the final status as JSON only")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "ask",
        help="ask one question end to end (starts the fleet unless --url is given)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("question", nargs="?", help="the question; omit it for the built-in demo question")
    p.add_argument("--choice", action="append", dest="choices", default=None,
                   help=f"one answer choice (repeat, 2..{MAX_CHOICES}); none = the scorer proposes answers")
    p.add_argument("--scene", help=f"scene id, e.g. gen-00042 (generated from seed 42); demo: {DEMO_SCENE}")
    p.add_argument("--pose", type=parse_pose, help="start pose x,y[,yaw]; default: sampled")
    p.add_argument("--strategy", default="semantic", choices=PRODUCT_STRATEGIES,
                   help="how to choose the next frontier (docs/results/exploration-strategies.md); default semantic")
    p.add_argument("--stop-rule", default="cp", choices=["cp", "entropy", "relevance", "max_steps"])
    p.add_argument("--eps", type=float, default=0.2, help="CP: 1-eps is the wanted success probability")
    p.add_argument("--threshold", type=float, default=None, help="entropy/relevance threshold")
    p.add_argument("--max-steps", type=int, default=None, help="step budget (default 3*sqrt(floor area))")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--home", default=None,
                   help="name of the home (house) the robot is in: the episode reads and extends its memory")
    add_episode_run_options(p, 600.0, "the answer")
    p.set_defaults(func=run)


def _body(args: argparse.Namespace, scenes_dir: Path) -> tuple[dict[str, Any], Question | None]:
    if args.question is None:
        if args.choices or args.scene:
            raise AskError("give a question with --choice/--scene, or none of them for the demo question")
        q = demo_question(scenes_dir)
        body: dict[str, Any] = {
            "question": q.text, "choices": q.choices, "scene": q.scene, "answer": q.answer,
            "start_pose": q.start_pose.model_dump() if q.start_pose else None, "max_steps": q.max_steps,
            "question_id": q.id,
        }
        demo: Question | None = q
    else:
        if not args.question.strip():
            raise AskError("the question is empty")
        if args.choices is not None and not 2 <= len(args.choices) <= MAX_CHOICES:
            raise AskError(f"give between 2 and {MAX_CHOICES} --choice options (or none), got {len(args.choices)}")
        if not args.scene:
            raise AskError("give --scene (e.g. --scene gen-00042)")
        body = {"question": args.question, "choices": args.choices, "scene": args.scene,
                "start_pose": args.pose.model_dump() if args.pose else None, "max_steps": args.max_steps}
        demo = None
    if not eps_in_bounds(args.eps):
        raise AskError(f"--eps must be between {EPS_GT:g} and {EPS_LT:g} (exclusive), got {args.eps}")
    if args.max_steps is not None:
        if args.max_steps < 1:
            raise AskError("--max-steps must be at least 1")
        body["max_steps"] = args.max_steps
    if args.pose is not None:
        body["start_pose"] = args.pose.model_dump()
    body.update(strategy=args.strategy, stop_rule=args.stop_rule, eps=args.eps, seed=args.seed)
    if args.home is not None:
        try:
            body["home"] = keys.check_id(args.home, "--home")
        except ValueError as exc:
            raise AskError(str(exc)) from None
    if args.threshold is not None:
        body["threshold"] = args.threshold
    return {k: v for k, v in body.items() if v is not None}, demo


def run(args: argparse.Namespace) -> int:
    from eqa.service import setup_logging
    from eqa_app.cli import UsageError, check_scorer, load_settings

    settings = load_settings()
    if args.url is None:
        check_scorer(settings)  # the fleet this command starts must be able to score
    setup_logging("WARNING" if args.json else settings.log_level, "eqa-ask")
    logging.getLogger("eqa.launcher").setLevel(logging.WARNING)
    logging.getLogger("httpx").setLevel(logging.WARNING)
    try:
        body, demo = _body(args, settings.scenes_path)
        if args.url is None:
            check_scene(body["scene"], settings.scenes_path)
    except AskError as exc:
        raise UsageError(str(exc)) from None
    if not args.json:
        print(f"question: {body['question']}")
        choices = body.get("choices") or []
        for label, choice in zip(letters(len(choices)) if choices else [], choices, strict=True):
            print(f"  {label}) {choice}")
        if not choices:
            print("  (no choices: the scorer proposes candidate answers, Explore-EQA section VI-A)")
        print(f"scene: {body['scene']}   strategy: {body['strategy']}   stop rule: {body['stop_rule']}"
              f" (eps {body['eps']})", flush=True)
    try:
        if args.url is not None:
            outcome = follow(args.url, body, args.token, args.timeout, args.json)
        else:
            outcome = _with_fleet(settings, body, args)
    except AskError as exc:
        raise UsageError(str(exc)) from None
    _report(outcome, settings, demo, args.json)
    return 0 if outcome.status.get("state") == "stopped" else 1


def _with_fleet(settings: Any, body: dict[str, Any], args: argparse.Namespace,
                path: str = "/v1/questions") -> Outcome:
    from eqa.launcher import ALL_SERVICES, Fleet, LaunchError, free_port

    port = free_port()
    fleet_settings = settings.model_copy(update={"gateway_host": "127.0.0.1", "gateway_port": port, "api_tokens": []})
    if not args.json:
        print(f"starting the fleet ({', '.join(ALL_SERVICES)}; {args.scorers} scorer replica(s)) ...", flush=True)
    t0 = time.monotonic()
    try:
        with Fleet(fleet_settings, services=ALL_SERVICES, scorers=args.scorers) as fleet:
            if not args.json:
                print(f"fleet up in {time.monotonic() - t0:.1f} s: {len(fleet.children)} processes over Zenoh "
                      f"({fleet.endpoint}); web console while it runs: http://127.0.0.1:{port}/", flush=True)
            return follow(f"http://127.0.0.1:{port}", body, None, args.timeout, args.json, path)
    except LaunchError as exc:
        raise AskError(f"the fleet did not start: {exc}") from None


def _report(outcome: Outcome, settings: Any, demo: Question | None, as_json: bool) -> None:
    s = outcome.status
    if as_json:
        print(json.dumps(s))
        return
    q = s.get("question") or {}
    choices = q.get("choices") or []
    answer = s.get("answer")
    text = s.get("answer_text") or (choices[letters(len(choices)).index(answer)] if answer and choices else "")
    print()
    if s.get("state") != "stopped":
        print(f"no answer: episode {s.get('state')}: {s.get('stop_reason')}")
    else:
        print(f"answer: {answer}) {text}")
    print(f"steps: {s.get('steps')} of {s.get('max_steps')} (normalised {s.get('normalized_steps', 0):.2f}); "
          f"stop reason: {s.get('stop_reason')}")
    if s.get("prediction_set"):
        print(f"prediction set: {{{', '.join(s['prediction_set'])}}}")
    if outcome.warm_uncalibrated is not None:
        print(f"warning: {warm_warning(outcome.warm_uncalibrated)}")
    if demo is not None and demo.answer is not None:
        verdict = "correct" if answer == demo.answer else "wrong"
        truth = demo.choices[letters(len(demo.choices)).index(demo.answer)]
        print(f"ground truth: {demo.answer}) {truth} -> {verdict}")
    if settings.scorer_backend == "oracle":
        print(f"note: {ORACLE_LABEL}")
    if s.get("recording"):
        from eqa.recording import recording_dir

        where = recording_dir(settings, s["episode_id"]).resolve()
        print(f"recording: {where}/ (one .rrd per service, one Rerun recording id; merged .rrd: "
              f"GET {s['recording']})")
    else:
        print("recording: off")
    print(f"time: {outcome.seconds:.1f} s, {outcome.events} events")
    sys.stdout.flush()
