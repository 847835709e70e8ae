"""Every ``from <first-party module> import name`` names something the module defines, read from the source.

An import inside a function (the benchmarks import their helpers lazily, so ``--help`` stays fast) fails only
when that function runs, which may be an hour into a run; this test finds such a name without running anything.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("eqa", "eqa_app", "services", "gateway")


def _module_path(root: Path, module: str) -> Path | None:
    base = root.joinpath(*module.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _bound_names(body: list[ast.stmt]) -> set[str]:
    """Names a module body binds at its top level (also inside top-level ``if`` / ``try`` / ``with`` blocks)."""
    names: set[str] = set()
    for node in body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
        elif isinstance(node, ast.AnnAssign | ast.AugAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.If | ast.Try | ast.With):
            for block in ("body", "orelse", "finalbody"):
                names |= _bound_names(getattr(node, block, []))
            for handler in getattr(node, "handlers", []):
                names |= _bound_names(handler.body)
    return names


def missing_imports(root: Path = REPO) -> list[str]:
    defined: dict[Path, set[str]] = {}
    errors = []
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                if not isinstance(node, ast.ImportFrom) or node.level or not node.module:
                    continue
                if node.module.split(".")[0] not in PACKAGES or (target := _module_path(root, node.module)) is None:
                    continue
                if target not in defined:
                    defined[target] = _bound_names(ast.parse(target.read_text()).body)
                for alias in node.names:
                    if alias.name not in defined[target] and _module_path(root, f"{node.module}.{alias.name}") is None:
                        errors.append(f"{path.relative_to(root)}:{node.lineno}: {node.module} has no {alias.name}")
    return errors


def test_every_imported_name_exists() -> None:
    assert missing_imports() == []


def test_a_name_the_module_lacks_is_found(tmp_path: Path) -> None:
    (tmp_path / "eqa_app").mkdir()
    (tmp_path / "eqa_app" / "__init__.py").write_text("")
    (tmp_path / "eqa_app" / "a.py").write_text("def f():\n    from eqa_app.b import g, h\n")
    (tmp_path / "eqa_app" / "b.py").write_text("try:\n    import x as g\nexcept ImportError:\n    g = None\n")
    assert missing_imports(tmp_path) == ["eqa_app/a.py:2: eqa_app.b has no h"]
