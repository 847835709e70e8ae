"""What the component benchmarks share: where the repository and its committed results are, the tests' helper
package some of them drive a fleet with, their argument parser and how one is started as a process.

Every benchmark is a module ``eqa_app.benches.<name>`` with ``main(argv) -> int``, run as
``python -m eqa_app.benches.<name>`` from the repository root; ``python -m eqa_app.benches`` runs the default set
(``make bench``) and ``eqa bench --help`` lists them all (:func:`catalogue`).
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import sys
from pathlib import Path

PACKAGE = "eqa_app.benches"
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
RESULTS = REPO / "bench" / "results"  # the committed figures the docs cite
TESTS = REPO / "tests"
NOT_BENCHES = frozenset({"__init__", "__main__", "harness"})


def use_test_support() -> None:
    """Make the tests' helpers (``tests/support``: a fleet of real processes, scorer servers, scenes) importable as
    ``support``: a benchmark that starts a fleet runs it exactly as the tests do, not through a second copy."""
    if str(TESTS) not in sys.path:
        sys.path.insert(0, str(TESTS))


def parser(doc: str | None) -> argparse.ArgumentParser:
    """The argument parser of a benchmark, its module docstring as the description."""
    return argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


def write_json(path: Path, results: object) -> None:
    """Write a benchmark's results as JSON (directories made) and say where, on stderr."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1))
    print(f"results: {path}", file=sys.stderr)


def command(name: str, *args: str, python: str | None = None) -> list[str]:
    """The command line that runs benchmark ``name`` in its own process (run it with :func:`environment`)."""
    return [python or sys.executable, "-m", f"{PACKAGE}.{name}", *args]


def environment(repo: Path = REPO) -> dict[str, str]:
    """The environment of a benchmark's own process: this process's, with ``repo`` first on ``PYTHONPATH`` so
    the child imports that tree's packages whatever its working directory."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(repo), env.get("PYTHONPATH", "")) if p)
    return env


def names() -> list[str]:
    """Every benchmark module of the package, sorted."""
    return sorted(p.stem for p in HERE.glob("*.py") if p.stem not in NOT_BENCHES)


def summary(name: str) -> str:
    """The first line of a benchmark's docstring, read from its source (importing it would load its models)."""
    doc = ast.get_docstring(ast.parse((HERE / f"{name}.py").read_text(encoding="utf-8"))) or ""
    return doc.strip().splitlines()[0] if doc.strip() else ""


def catalogue() -> str:
    """``name  summary`` of every benchmark, one a line (``eqa bench --help``)."""
    width = max(len(n) for n in names())
    return "\n".join(f"  {n:<{width}}  {summary(n)}" for n in names())
