"""The component benchmarks are modules of eqa_app.benches with main(argv), listed by ``eqa bench --help`` and run
by ``eqa bench component NAME`` (read from the source; only --help is run)."""

from __future__ import annotations

import ast

import pytest

from eqa_app.benches import harness
from eqa_app.cli import main


def test_every_benchmark_is_a_module_with_main() -> None:
    from eqa_app.benches.__main__ import DEFAULT

    assert len(harness.names()) >= 20 and "harness" not in harness.names() and set(DEFAULT) <= set(harness.names())
    for name in harness.names():
        tree = ast.parse((harness.HERE / f"{name}.py").read_text(encoding="utf-8"))
        mains = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main"]
        assert mains and mains[0].args.args[0].arg == "argv", name
        assert harness.summary(name), f"{name} has no docstring"


def test_no_benchmark_edits_sys_path_but_the_harness() -> None:
    for name in harness.names():
        src = (harness.HERE / f"{name}.py").read_text(encoding="utf-8")
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", "") == "sys":
                # the reference benchmark imports the reference's own checkout, given on its command line
                assert name == "reference" and "sys.path.insert(0, str(ref_dir))" in src, name


def test_eqa_bench_help_lists_them_and_component_runs_one(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in harness.names():
        assert f"  {name} " in out, name
    with pytest.raises(SystemExit) as exc:
        main(["bench", "component", "planner", "--help"])
    assert exc.value.code == 0 and harness.summary("planner") in capsys.readouterr().out
    assert main(["bench", "component", "no-such-bench"]) == 2
    assert harness.command("sim")[1:] == ["-m", "eqa_app.benches.sim"]
