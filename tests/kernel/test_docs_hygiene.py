"""The README and docs/ stay a user's documentation, and the code says why rather than when: no tracker
references in README, docs or code (history belongs in CHANGELOG.md and git), every relative link leads to a
file, every function docs/equations.md names exists, and the README is short."""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
README_MAX_LINES = 220
TRACKER_REF = re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
CODE_SUFFIXES = {".py", ".sh", ".yml", ".yaml", ".js", ".html", ".css", ".toml"}
CODE_NAMES = {"Makefile", "Dockerfile"}
CODE_REF = re.compile(r"`([\w./-]+\.py):([\w.]+)`")


def pages() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def _outside_code(text: str) -> str:
    """The text without fenced code blocks (a shell comment there is not a link)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


def tracker_refs(text: str) -> list[str]:
    return [m.group(0) for m in TRACKER_REF.finditer(text)]


def broken_links(page: Path) -> list[str]:
    bad = []
    for target in LINK.findall(_outside_code(page.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # another site, or an anchor on the same page
        path = (page.parent / target.split("#", 1)[0]).resolve()
        if not path.exists():
            bad.append(target)
    return bad


def missing_code_refs(text: str) -> list[str]:
    """``file.py:name`` (or ``file.py:Class.method``) references whose file or definition does not exist."""
    bad = []
    for file, name in CODE_REF.findall(text):
        path = REPO / file
        if not path.is_file():
            bad.append(f"{file}:{name}")
            continue
        body: list[ast.stmt] = ast.parse(path.read_text()).body
        for part in name.split("."):
            found = [n for n in body if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)
                     and n.name == part]
            if not found:
                bad.append(f"{file}:{name}")
                break
            body = found[0].body
    return bad


def test_no_tracker_references_in_readme_or_docs() -> None:
    found = {p.relative_to(REPO).as_posix(): refs for p in pages() if (refs := tracker_refs(p.read_text()))}
    assert not found, f"history belongs in CHANGELOG.md and commit messages, not in the docs: {found}"


def test_every_relative_link_resolves() -> None:
    found = {p.relative_to(REPO).as_posix(): bad for p in pages() if (bad := broken_links(p))}
    assert not found, f"links to files that do not exist: {found}"


def test_no_tracker_references_in_the_code() -> None:
    """Comments and docstrings say why the code is as it is; its history is in CHANGELOG.md and git."""
    files = subprocess.run(["git", "-C", str(REPO), "ls-files"], capture_output=True, text=True, check=True)
    bad = []
    for rel in files.stdout.split():
        path = REPO / rel
        if rel.startswith("bench/results/") or not (path.suffix in CODE_SUFFIXES or path.name in CODE_NAMES):
            continue
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError):
            continue
        bad += [f"{rel}:{i}" for i, line in enumerate(text.splitlines(), 1) if TRACKER_REF.search(line)]
    assert not bad, f"tracker references in code (say why, not which ticket): {bad[:20]}"


def test_equations_page_names_existing_functions() -> None:
    text = (REPO / "docs" / "equations.md").read_text()
    assert len(CODE_REF.findall(text)) > 30
    assert not missing_code_refs(text), "docs/equations.md names code that does not exist"


def test_readme_is_short() -> None:
    n = len((REPO / "README.md").read_text().splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines; move detail into docs/ (at most {README_MAX_LINES})"


def test_the_checks_can_fail(tmp_path: Path) -> None:
    word = "issue"  # spelled apart so that this file holds no tracker reference itself
    assert tracker_refs(f"see {word} 12 and {word.title()} #3; {word}20") == [
        f"{word} 12", f"{word.title()} #3", f"{word}20"]
    assert tracker_refs(f"an {word} with 12 robots") == []
    page = tmp_path / "p.md"
    (tmp_path / "there.md").write_text("")
    page.write_text("[ok](there.md#x) [web](https://x.org) [self](#y) [gone](missing.md)\n"
                    "```\n[code](not-a-link.md)\n```\n![pic](gone.png)\n")
    assert broken_links(page) == ["missing.md", "gone.png"]
    assert missing_code_refs("`eqa/grid.py:cell_of` `eqa/grid.py:nope` `no/such.py:f`") == [
        "eqa/grid.py:nope", "no/such.py:f"]
    assert missing_code_refs("`services/planner/task_fsm.py:TaskMachine.step`") == []
