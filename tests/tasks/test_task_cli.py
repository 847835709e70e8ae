"""``eqa task`` as a user meets it (eqa_app/task.py, the step printer of eqa_app/ask.py): the examples of its --help,
the exit codes, whole step reasons, one line per step, what the HELIOS agent decided, repeatable runs, the demo."""

from __future__ import annotations

import math
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from eqa.messages import Frontier, GridSpec, Pose2D
from services.planner.helios import FrontierOption
from services.planner.step import Memory
from services.planner.task_fsm import Gaze, SeenObject, TaskMachine

REPO = Path(__file__).resolve().parents[2]


def _task_help() -> str:
    from eqa_app.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices["task"].format_help()  # type: ignore[attr-defined]


def _examples(text: str) -> list[tuple[list[str], str]]:
    """(argv after ``eqa``, what the help says happens) of every example: a line ``  eqa ...`` and the indented
    lines under it."""
    lines = text.splitlines()
    out = []
    for i, line in enumerate(lines):
        if re.match(r"^ {2}eqa ", line):
            said = []
            for nxt in lines[i + 1:]:
                if not nxt.startswith("      "):
                    break
                said.append(nxt.strip())
            out.append((shlex.split(line.strip())[1:], " ".join(said)))
    return out


def test_every_example_of_the_help_runs_as_it_says(tmp_path: Path) -> None:
    """Each example parses; an example whose objects the house lacks is marked refused (exit 2) with the error it
    prints, every other one names objects its house has (the check ``eqa task`` makes before starting a fleet)."""
    from eqa_app.ask import AskError
    from eqa_app.cli import build_parser
    from eqa_app.task import _body, check_task

    examples = _examples(_task_help())
    assert len(examples) >= 3 and all(said for _, said in examples), examples
    assert any(argv == ["task"] for argv, _ in examples)  # the demo
    for argv, said in examples:
        assert argv[0] == "task"
        args = build_parser().parse_args(argv)
        body = _body(args, tmp_path)
        refused = re.search(r'refused at once, exit 2: "(.+?)(\.\.\.)?\)?"', said)
        if refused:
            with pytest.raises(AskError) as err:
                check_task(body["instruction"], body["scene"], tmp_path)
            assert str(err.value).startswith(refused.group(1)), (argv, str(err.value))
        else:
            check_task(body["instruction"], body["scene"], tmp_path)  # raises naming what the house lacks


def test_every_eqa_task_command_in_the_readme_and_docs_names_objects_its_house_has(tmp_path: Path) -> None:
    from eqa_app.cli import build_parser
    from eqa_app.task import _body, check_task

    found = []
    for doc in [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]:
        for m in re.finditer(r"eqa task( \"[^\"]*\")?( --[a-z-]+( [^ #`\n]+)?)*", doc.read_text()):
            argv = shlex.split(m.group(0))[1:]
            if "--help" in argv:
                continue
            body = _body(build_parser().parse_args(argv), tmp_path)
            check_task(body["instruction"], body["scene"], tmp_path)  # raises naming what the house lacks
            found.append(argv)
    assert len(found) >= 5, found


def test_a_task_the_house_cannot_hold_fails_fast_with_exit_2_and_what_it_has(tmp_path: Path) -> None:
    env = {**os.environ, "EQA_DATA_DIR": str(tmp_path), "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-m", "eqa_app", "task", "Move the mug from the kitchen counter to the "
                          "dining table", "--scene", "gen-15000"], capture_output=True, text=True, timeout=120,
                         env=env, cwd=REPO)
    assert out.returncode == 2, out
    err = out.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: gen-15000 has no mug on a kitchen counter (its pickable "
                                               "objects: "), out.stderr
    assert "kettle on kitchen counter" in err[0] and "starting the fleet" not in out.stdout


def test_the_simulator_names_what_a_house_lacks(tmp_path: Path) -> None:
    from eqa.messages import Task
    from services.sim.library import load_or_generate
    from services.sim.tasks import scene_lacks

    scene = load_or_generate("gen-15000", tmp_path)

    def pp(obj: str, start: str, goal: str) -> Task:
        return Task(kind="pick_place", text="x", scene="gen-15000", object=obj, start_receptacle=start,
                    goal_receptacle=goal)

    assert scene_lacks(pp("kettle", "kitchen_counter", "coffee_table"), scene) is None
    assert scene_lacks(pp("kettle", "kitchen_counter", "dining_table"), scene).startswith(  # type: ignore[union-attr]
        "gen-15000 has no dining table (its goal receptacles: ")
    find = Task(kind="find_object", text="x", scene="gen-15000", object="mug")
    assert "has no mug (its small objects: " in (scene_lacks(find, scene) or "")
    assert scene_lacks(find.model_copy(update={"object": "potted_plant"}), scene) is None


def test_exit_codes_say_success_failure_and_refusal() -> None:
    from eqa_app.task import EXIT_CODES, exit_code

    pp = {"kind": "pick_place"}
    won = {"FindObj": 1.0, "Pick": 1.0, "FindRec": 1.0, "Place": 1.0, "SR": 1.0}
    lost = {**won, "Place": 0.0, "SR": 0.0}
    assert exit_code({"state": "stopped", "task": pp, "metrics": won, "stop_reason": "task ended: placed"}) == 0
    assert exit_code({"state": "stopped", "task": pp, "metrics": lost, "stop_reason": "step limit reached"}) == 1
    assert exit_code({"state": "failed", "task": pp, "stop_reason": "no message for 30 s"}) == 1
    assert exit_code({"state": "failed", "task": pp, "stop_reason": "sim refused the episode: task refused: "
                      "gen-1 has no mug"}) == 2
    assert exit_code({"state": "stopped", "task": pp, "outcome": {"success": True}}) == 0
    assert "exit codes:" in _task_help() and all(f"  {c} " in EXIT_CODES for c in (0, 1, 2, 130))


def test_a_long_reason_is_printed_whole_wrapped_at_words(capsys: pytest.CaptureFixture[str]) -> None:
    from eqa_app.ask import _print_event

    reason = " ".join(f"word{i:02d}-part" for i in range(40)) + " thelastword"
    _print_event({"kind": "goal", "step": 3, "phase": "searching", "skill": "move", "reason": reason}, True, 80)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) > 1 and all(len(line) <= 80 for line in lines)
    assert lines[0].startswith("  step   3: searching    word00-part")
    indent = lines[0].index("word00")
    assert all(line[:indent].strip() == "" for line in lines[1:])
    assert " ".join(" ".join(line.split()) for line in lines).endswith(reason)  # every word, none cut


def test_a_task_prints_the_stoppers_decision_only_when_it_ends_the_episode(capsys: pytest.CaptureFixture[str]
                                                                         ) -> None:
    from eqa_app.ask import _print_event

    running = {"kind": "decision", "step": 4, "rule": "max_steps", "stop": False,
               "reason": "running to the step limit (5/40)"}
    limit = {"kind": "decision", "step": 39, "rule": "max_steps", "stop": True,
             "reason": "step limit reached (40 steps)"}
    _print_event(running, task=True)
    _print_event(limit, task=True)
    _print_event(running, task=False)  # a question run to its budget (eqa ask --stop-rule max_steps) says it
    out = capsys.readouterr().out.splitlines()
    assert out == ["  step  39: step limit reached (40 steps)", "  step   4: running to the step limit (5/40)"]


def test_a_step_sent_again_is_printed_once(capsys: pytest.CaptureFixture[str]) -> None:
    from eqa_app.ask import StepPrinter

    goal = {"kind": "goal", "step": 6, "phase": "looking", "skill": "stop", "reason": "trusting: acts on a detection"}
    frame = {"kind": "frame", "step": 7, "skill": {"skill": "stop", "success": False, "reason": "not near"}}
    printer = StepPrinter(task=True)
    for event in (goal, frame, goal, frame, {**goal, "step": 7}):  # step 6's goal and step 7's frame resent
        printer(event)
    out = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0].strip() for line in out] == ["step   6", "stop failed", "step   7"], out


# ---- what the HELIOS agent decided ------------------------------------------------------------------------


def _table(S: float = 0.8, ig: float = 50.0) -> SeenObject:
    gaze = (Gaze(3.0, 1.0, 0.0), Gaze(1.0, 1.0, 0.0), Gaze(2.0, 2.5, 0.0))
    return SeenObject(10, "table", {"table": (S, 0.1, S - 0.1)}, 2.0, 1.0, ig, gaze)


FRONTIERS = [FrontierOption(0, 5.0, 0.0, 0.2), FrontierOption(1, -5.0, 0.0, 0.9)]


def test_a_search_step_says_the_global_objective_s_choice_and_values() -> None:
    m = TaskMachine("pick_place", "mug", "table", "counter")
    a = m.step((0.0, 0.0, 0.0), FRONTIERS, [])
    assert a.kind == "frontier" and a.reason.startswith("global search (Eq. 10): frontier V 0.895"), a.reason
    assert "no candidate" in a.reason
    a = TaskMachine("pick_place", "mug", "table", "counter").step((0.0, 0.0, 0.0), FRONTIERS, [_table()])
    assert a.phase == "local_search" and a.reason.startswith("global search (Eq. 10): candidate 10 V 40"), a.reason
    assert "best frontier V 0.895" in a.reason and "local search of table 10: a gaze point (2 more)" in a.reason
    weak = TaskMachine("pick_place", "mug", "table", "counter").step((0.0, 0.0, 0.0), FRONTIERS, [_table(0.35, 0.1)])
    assert weak.kind == "frontier" and "best candidate V 0.0328" in weak.reason, weak.reason


def test_a_goal_receptacle_search_step_prints_its_frontier_value() -> None:
    from services.planner.task_fsm import SkillOutcome

    m = TaskMachine("pick_place", "mug", "table", "counter")
    mug = SeenObject(20, "mug", {"mug": (0.7, 0.1, 0.6)}, 2.0, 1.2, 1.0, (Gaze(1.5, 1.2, 0.0),))
    m.step((0.0, 0.0, 0.0), FRONTIERS, [mug])
    a = m.step((0.0, 0.0, 0.0), FRONTIERS, [], SkillOutcome("pick", True, 20))
    assert m.holding and a.kind == "frontier"
    assert re.search(r"goal receptacle search: frontier of highest value: V 0\.895$", a.reason), a.reason


def test_a_frontier_step_of_a_task_does_not_print_the_path_planner_s_sampling_label() -> None:
    from services.planner.task_step import task_step

    grid = GridSpec(origin_x=0.0, origin_y=0.0, resolution=0.1, rows=100, cols=100)
    occ = np.zeros((100, 100), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    far = Frontier(x=8.0, y=2.0, nx=1.0, ny=0.0, size=5, sv=0.6)
    m = TaskMachine("pick_place", "mug", "table", "counter")
    st = task_step(m, grid, ~occ, occ, Pose2D(x=2.0, y=2.0), [far], [], None, Memory(), np.random.default_rng(0))
    assert st.plan.kind == "move"
    assert "uniform over reachable frontiers" not in st.plan.reason and "fbe" not in st.plan.reason, st.plan.reason
    want = (r"global search \(Eq\. 10\): frontier V 0\.594; no candidate; heads for the frontier at "
            r"\(8\.0, 2\.0\) moving 3\.0 of 6\.\d m \(clearance 0\.\d\d m\)")
    assert re.fullmatch(want, st.plan.reason), st.plan.reason
    assert math.isclose(st.plan.pose.x, 5.0, abs_tol=0.3)


# ---- repeatable runs through the fleet, as eqa task runs them -----------------------------------------------


def _steps(stdout: str) -> list[str]:
    return [line for line in stdout.splitlines() if line.startswith(("  step", "      "))]


@pytest.mark.timeout(600)
def test_seed_repeats_a_run_step_for_step_through_the_fleet(tmp_path: Path) -> None:
    """The help's ``--seed`` example, run twice (each run its own fleet and fresh episode id): the same steps,
    one line per step in step order, and the end and exit code the help states."""
    argv, said = next((a, s) for a, s in _examples(_task_help()) if "--seed" in a)
    stated = re.search(r"stops at step (\d+).*exit (\d)", said)
    assert stated, said
    env = {**os.environ, "EQA_DATA_DIR": str(tmp_path), "PYTHONPATH": str(REPO), "COLUMNS": "200"}
    cmd = [sys.executable, "-m", "eqa_app", *argv, "--no-record"]
    runs = [subprocess.run(cmd, capture_output=True, text=True, timeout=280, env=env, cwd=REPO) for _ in range(2)]
    ids = [re.search(r"episode (ep-\w+) on", r.stdout) for r in runs]
    assert all(ids) and ids[0].group(1) != ids[1].group(1), [r.stdout for r in runs]  # type: ignore[union-attr]
    first, second = (_steps(r.stdout) for r in runs)
    assert first == second, "\n".join([*first, "---", *second])
    numbers = [int(m.group(1)) for line in first if (m := re.match(r"  step +(\d+):", line))]
    assert numbers == sorted(set(numbers)), first  # one line a step, in step order
    ends = [re.search(r"outcome: .* at step (\d+)", r.stdout) for r in runs]
    assert all(e is not None and int(e.group(1)) == int(stated.group(1)) for e in ends), runs[0].stdout
    assert [r.returncode for r in runs] == [int(stated.group(2))] * 2, runs[0].stdout + runs[0].stderr


# ---- the demo: a typical task of the tuning seed, by a rule -------------------------------------------------


def test_the_demo_is_the_rules_pick_on_the_committed_runs_and_its_help_says_their_outcome(tmp_path: Path) -> None:
    from eqa_app.task import DEMO_OUTCOME, DEMO_SUCCESSES, DEMO_TASK_ID, demo_task
    from eqa_app.task_demo import DEMO_POOL, RESULTS, load_runs, pick_demo

    runs = load_runs(RESULTS)
    assert len(runs) == DEMO_POOL
    demo = pick_demo(runs)
    assert (demo.task_id, demo.text) == (DEMO_TASK_ID, DEMO_OUTCOME), "re-run python -m eqa_app.task_demo"
    assert (sum(r.success for r in runs), len(runs)) == DEMO_SUCCESSES
    assert demo_task(tmp_path).id == DEMO_TASK_ID
    assert DEMO_TASK_ID in _task_help() and DEMO_OUTCOME in " ".join(_task_help().split())


def test_the_rule_takes_the_majority_outcome_its_commonest_cause_and_a_typical_budget() -> None:
    from eqa_app.task_demo import DemoRun, pick_demo, typical_outcome

    runs = [DemoRun("a", 145, False, "object not found: out of steps"), DemoRun("b", 60, True, "success"),
            DemoRun("c", 60, False, "place failed"), DemoRun("d", 100, False, "object not found: out of steps"),
            DemoRun("e", 80, False, "object not found: out of steps")]
    assert typical_outcome(runs) == (False, "object not found: out of steps")
    assert pick_demo(runs).task_id == "e"  # a, d: budgets above the median (80)
    wins = [DemoRun("a", 60, True, "success"), DemoRun("b", 60, True, "success"), DemoRun("c", 60, False, "x")]
    assert pick_demo(wins).task_id == "a"
    tie = [DemoRun("a", 60, True, "success"), DemoRun("b", 60, False, "x")]
    assert typical_outcome(tie) == (False, "x")
