"""The import direction of the layers, read from the source (AST only: no module is imported or executed).

* kernel ``eqa/``: imports only the kernel;
* a service ``services/<name>/``: the kernel and its own package, never another service, the gateway or the app;
* the gateway ``gateway/``: the kernel and itself, never a service or the app;
* the application layer ``eqa_app/`` and the process entry point that wire the layers together
  (:data:`COMPOSITION_ROOTS`): anything.

Every import counts, at module level or inside a function, under ``if TYPE_CHECKING:`` too: a lazy or type-only
import is still a dependency. No import cycles among first-party modules either.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("eqa", "eqa_app", "services", "gateway")
# Process entry points that hand one layer's parts to another (python -m eqa_app, python -m gateway): application layer.
COMPOSITION_ROOTS = frozenset({"eqa.__main__", "gateway.__main__"})


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def first_party_modules(root: Path) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            out[module_name(root, path)] = path
    return out


def layer_of(module: str) -> str:
    """``kernel``, ``app``, ``gateway``, ``services`` (the namespace package itself) or ``service:<name>``."""
    parts = module.split(".")
    if module in COMPOSITION_ROOTS or parts[0] == "eqa_app":
        return "app"
    if parts[0] == "eqa":
        return "kernel"
    if parts[0] == "gateway":
        return "gateway"
    if parts[0] == "services":
        return "services" if len(parts) == 1 else f"service:{parts[1]}"
    raise ValueError(module)


def allowed(src: str, dst: str) -> bool:
    if src == "app":
        return True
    if dst == "kernel":
        return True
    if src == "kernel":
        return False
    if src.startswith("service:"):
        return dst in (src, "services")
    if src == "gateway":
        return dst == "gateway"
    return dst == src


def imports_of(module: str, path: Path, known: dict[str, Path]) -> list[tuple[int, str]]:
    """(line, first-party module) for every import in the file; ``from a import b`` names module ``a.b`` when
    that is a module, else ``a``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in PACKAGES:
                    out.append((node.lineno, alias.name))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_pkg else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] not in PACKAGES:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                out.append((node.lineno, sub if sub in known else target))
    return sorted(set(out))


def layer_violations(root: Path) -> list[str]:
    known = first_party_modules(root)
    errors = []
    for module, path in known.items():
        src = layer_of(module)
        for line, target in imports_of(module, path, known):
            dst = layer_of(target)
            if not allowed(src, dst):
                errors.append(f"{path.relative_to(root)}:{line}: {module} ({src}) imports {target} ({dst})")
    return errors


def import_cycles(root: Path) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    known = first_party_modules(root)
    graph = {m: sorted({t for _, t in imports_of(m, p, known) if t in known and t != m}) for m, p in known.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


def test_layers_of_this_repository() -> None:
    errors = layer_violations(REPO)
    assert not errors, "imports against the layer direction:\n" + "\n".join(errors)


def test_no_import_cycles() -> None:
    cycles = import_cycles(REPO)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def _write(root: Path, rel: str, text: str = "") -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


@pytest.fixture()
def tree(tmp_path: Path) -> Path:
    """A small clean tree of the same shape."""
    for rel in ("eqa/__init__.py", "eqa_app/__init__.py", "services/__init__.py", "services/sim/__init__.py",
                "services/mapper/__init__.py", "gateway/__init__.py"):
        _write(tmp_path, rel)
    _write(tmp_path, "eqa/keys.py", "import json\n")
    _write(tmp_path, "eqa/bus.py", "from eqa import keys\nfrom . import keys as k\n")
    _write(tmp_path, "services/sim/scene.py", "from eqa.bus import Bus\n")
    _write(tmp_path, "services/mapper/tsdf.py", "import numpy\nfrom services.mapper import frontiers\n")
    _write(tmp_path, "services/mapper/frontiers.py", "from eqa import keys\n")
    _write(tmp_path, "gateway/manager.py", "from eqa.bus import Bus\n")
    _write(tmp_path, "gateway/__main__.py", "from services.sim import scene\n")
    _write(tmp_path, "eqa_app/cli.py", "import gateway.manager\nfrom services.sim.scene import x\n")
    return tmp_path


def test_clean_tree_passes(tree: Path) -> None:
    assert layer_violations(tree) == []
    assert import_cycles(tree) == []


@pytest.mark.parametrize(
    ("rel", "text", "expected"),
    [
        ("eqa/store.py", "def f():\n    from services.sim.scene import Scene\n",
         "eqa/store.py:2: eqa.store (kernel) imports services.sim.scene (service:sim)"),
        ("eqa/recording.py", "import gateway.manager\n",
         "eqa/recording.py:1: eqa.recording (kernel) imports gateway.manager (gateway)"),
        ("eqa/settings.py", "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from eqa_app import cli\n",
         "eqa/settings.py:3: eqa.settings (kernel) imports eqa_app.cli (app)"),
        ("services/mapper/service.py", "from services.sim import scene\n",
         "services/mapper/service.py:1: services.mapper.service (service:mapper) imports services.sim.scene "
         "(service:sim)"),
        ("services/sim/cli.py", "from eqa_app import cli\n",
         "services/sim/cli.py:1: services.sim.cli (service:sim) imports eqa_app.cli (app)"),
        ("gateway/app.py", "from services.sim.scene import Scene\n",
         "gateway/app.py:1: gateway.app (gateway) imports services.sim.scene (service:sim)"),
        ("services/sim/util.py", "from ...gateway import manager\n",
         "services/sim/util.py:1: services.sim.util (service:sim) imports gateway.manager (gateway)"),
    ],
)
def test_planted_violation_is_named(tree: Path, rel: str, text: str, expected: str) -> None:
    _write(tree, rel, text)
    assert layer_violations(tree) == [expected]


def test_planted_cycle_is_named(tree: Path) -> None:
    _write(tree, "services/mapper/frontiers.py", "def f():\n    from services.mapper.tsdf import g\n")
    assert import_cycles(tree) == [["services.mapper.frontiers", "services.mapper.tsdf"]]
