"""``docs/configuration.md``, generated from the settings class (:class:`eqa.settings.Settings`).

The settings class is the one home of every ``EQA_*`` variable; this page is derived from it so that it cannot
drift: ``tests/kernel/test_config_doc.py`` regenerates it and compares. Sections follow the ``# --- name ---`` comments
of the settings groups (a group's docstring says what it is for, and :func:`components` which components read
it); a setting's text is its ``description=``, else the comment on its line or the comment block right above it.

    python -m eqa_app.config_doc > docs/configuration.md     # regenerate
    python -m eqa_app.config_doc --check docs/configuration.md   # exit 1 when the page is stale
"""

from __future__ import annotations

import argparse
import ast
import importlib
import inspect
import re
import sys
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

REGENERATE = "python -m eqa_app.config_doc > docs/configuration.md"
SECTION = re.compile(r"^\s*#\s*---\s*(.+?)\s*---\s*$")
# references to the project's tracker are history, not documentation: kept out of the page
TRACKER_REF = re.compile(r"(?:[\w/ -]+=\s*)?\bissues?\s+#?\d+(?:\s+item\s+\d+)?(?:\s*\(\w+\))?", re.IGNORECASE)


# the services, by the name their shells have (each declares its settings groups: Service.settings_groups)
SERVICES = {
    "sim": "services.sim.service:SimService",
    "mapper": "services.mapper.service:MapperService",
    "planner": "services.planner.service:PlannerService",
    "stopper": "services.stopper.service:StopperService",
    "vlm_scorer": "services.vlm_scorer.service:ScorerService",
    "ros2_bridge": "services.ros2_bridge.service:Ros2BridgeService",
}


def service_classes() -> dict[str, Any]:
    """The service classes of :data:`SERVICES`."""
    out = {}
    for name, ref in SERVICES.items():
        module, _, attr = ref.partition(":")
        out[name] = getattr(importlib.import_module(module), attr)
    return out


def components() -> dict[str, tuple[str, tuple[type, ...] | None]]:
    """Each component: its package and the settings groups it reads; ``None``: every group (the launcher hands
    the whole configuration to the processes it starts)."""
    from gateway.app import SETTINGS_GROUPS

    out: dict[str, tuple[str, tuple[type, ...] | None]] = {
        name: (SERVICES[name].partition(":")[0].rpartition(".")[0], cls.settings_groups)
        for name, cls in service_classes().items()
    }
    out["gateway"] = ("gateway", SETTINGS_GROUPS)
    out["launcher"] = ("eqa.launcher", None)
    return out


def readers(group: type) -> list[str]:
    """The components that declare ``group`` (the launcher, which holds every group, is left out)."""
    return [name for name, (_, groups) in components().items() if groups is not None and group in groups]


@dataclass(frozen=True)
class Row:
    section: str
    note: str  # the comment block above the field: it opens a group of settings within the section
    env: str
    type: str
    default: str
    text: str
    about: str = ""  # the docstring of the settings group that declares the field
    group: str = ""  # the settings group that declares the field


def clean(text: str) -> str:
    """``text`` without tracker references (and session tags such as ``(h12a)``) and the punctuation they leave."""
    out = re.sub(r"\s*\(h\d+[a-z]?\)", "", TRACKER_REF.sub("", text))
    out = re.sub(r"\(\s*[;,]\s*", "(", out)
    out = re.sub(r"\s*[;,]\s*\)", ")", out)
    out = re.sub(r"\(\s*\)", "", out)
    out = re.sub(r"\s+([;,.:])", r"\1", out)
    out = re.sub(r"([;,])(?=[;,])", "", out)
    out = re.sub(r"\s{2,}", " ", out).strip()
    return out.strip(" ;,:")


def _type_name(annotation: Any) -> str:
    if annotation is None or annotation is type(None):
        return "none"
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin is typing.Literal:
        return " \\| ".join(f"`{a}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        names = [_type_name(a) for a in args if a is not type(None)]
        return " \\| ".join(names) + (", optional" if type(None) in args else "")
    if origin is list:
        return "comma-separated list"
    if isinstance(annotation, type):
        return {"str": "text", "Path": "path", "float": "number", "int": "integer", "bool": "true/false"}.get(
            annotation.__name__, annotation.__name__)
    return str(annotation)


def _limits(info: FieldInfo) -> str:
    parts = []
    for meta in info.metadata:
        for attr, sign in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
            value = getattr(meta, attr, None)
            if value is not None:
                parts.append(f"{sign} {value:_}" if isinstance(value, int) else f"{sign} {value}")
    return ", ".join(parts)


def _default(info: FieldInfo) -> str:
    factory: Callable[[], Any] | None = info.default_factory  # type: ignore[assignment]
    if factory is not None:
        if factory in (list, dict):
            return "(empty)"
        if getattr(factory, "__name__", "") != "<lambda>":
            doc = inspect.getdoc(factory)
            return clean(doc.splitlines()[0]) if doc else f"computed at start (`{factory.__name__}`)"
        value = factory()
    else:
        value = info.default
    if value is PydanticUndefined:
        return "(required)"
    if value is None:
        return "(unset)"
    if isinstance(value, list):
        return f"`{','.join(map(str, value))}`" if value else "(empty)"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, int):
        return f"`{value}`"
    return f"`{value}`"


def _comments(source: str) -> tuple[dict[int, str], dict[int, str], dict[int, str]]:
    """For each line: the section it is in, the comment block right above it, the comment at its end."""
    lines = source.splitlines()
    sections: dict[int, str] = {}
    current = ""
    for i, line in enumerate(lines, start=1):
        if m := SECTION.match(line):
            current = clean(m.group(1))
        sections[i] = current
    above: dict[int, str] = {}
    inline: dict[int, str] = {}
    for i, line in enumerate(lines, start=1):
        block: list[str] = []
        j = i - 2
        while j >= 0 and lines[j].strip().startswith("#") and not SECTION.match(lines[j]):
            block.insert(0, lines[j].strip().lstrip("#").strip())
            j -= 1
        above[i] = clean(" ".join(block))
        code, _, trailing = line.partition("  # ")
        inline[i] = clean(trailing) if trailing and "=" in code else ""
    return sections, above, inline


def rows(cls: type | None = None, source: str | None = None) -> list[Row]:
    """One row per field of ``cls`` (default :class:`eqa.settings.Settings`), in the class's order."""
    if cls is None:
        from eqa.settings import Settings

        cls = Settings
    src = source if source is not None else Path(inspect.getsourcefile(cls) or "").read_text()
    sections, above, inline = _comments(src)
    tree = ast.parse(src)
    classes = {k.__name__ for k in cls.__mro__}  # the class and the settings groups it is made of
    lineno: dict[str, int] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef) and node.name in classes:
            for stmt in node.body:
                if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
                    lineno[stmt.target.id] = stmt.lineno
    prefix = str(getattr(cls, "model_config", {}).get("env_prefix", "")).upper()
    out = []
    for name, info in sorted(cls.model_fields.items(),  # type: ignore[attr-defined]
                             key=lambda item: lineno.get(item[0], 0)):
        line = lineno.get(name, 0)
        kind = _type_name(info.annotation)
        if limits := _limits(info):
            kind = f"{kind}, {limits}"
        text = clean(info.description or "") or inline.get(line, "")
        owner = next((k for k in cls.__mro__ if name in inspect.get_annotations(k)), cls)
        about = clean(" ".join((inspect.getdoc(owner) or "").split())) if owner is not cls else ""
        out.append(Row(section=sections.get(line, "") or "other", note=above.get(line, ""),
                       env=f"{prefix}{name.upper()}", type=kind, default=_default(info), text=text, about=about,
                       group=owner.__name__ if owner is not cls else ""))
    return out


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ") if "\\|" not in text else text.replace("\n", " ")


def render(cls: type | None = None, source: str | None = None) -> str:
    """The whole page, Markdown."""
    table = rows(cls, source)
    out = [
        "# Configuration",
        "",
        "Every setting is an `EQA_*` environment variable, read once by `eqa.settings.Settings` and handed to each",
        "service (nothing deeper reads the environment). Lists are comma-separated. `eqa up` passes its own",
        "settings to the processes it starts; `docker-compose.yml` sets the same variables. The settings come in",
        "groups (one class each in `eqa/settings.py`, one section each below); the simulated perception models'",
        "knobs are groups of their own: benchmark settings, not deployment settings. Each component declares",
        "the groups it reads and keeps only those (`eqa.settings.view`: a setting of another group is an",
        "`AttributeError` there); each section says which components read it (`eqa up`, the launcher, holds",
        "every group: it hands the whole configuration to the processes it starts).",
        "",
        f"This page is generated from `eqa/settings.py`: `{REGENERATE}`",
        "(`tests/kernel/test_config_doc.py` fails when it is stale).",
        "",
    ]
    order: list[str] = []
    for r in table:
        if r.section not in order:
            order.append(r.section)
    titles = [s.partition(" (")[0] for s in order]
    out += ["Sections: " + ", ".join(f"[{t}](#{_anchor(t)})" for t in titles) + ".", ""]
    header = ["| variable | type | default | what |", "|---|---|---|---|"]
    for section in order:
        title, _, remark = section.partition(" (")
        out += [f"## {title}", ""]
        about = next((r.about for r in table if r.section == section and r.about), "")
        if remark := clean(remark.rstrip(")")) or about:
            out += [f"*{remark}*", ""]
        groups = list(dict.fromkeys(r.group for r in table if r.section == section and r.group))
        if groups and (names := _readers(groups)):
            out += [f"Read by: {', '.join(names)}.", ""]
        out += header
        for r in (r for r in table if r.section == section):
            if r.note:
                if out[-1] != header[-1]:
                    out += ["", r.note, "", *header]
                else:
                    out[-2:] = [r.note, "", *header]
            out.append(f"| `{r.env}` | {_cell(r.type)} | {_cell(r.default)} | {_cell(r.text)} |")
        out.append("")
    return "\n".join(out)


def _readers(groups: list[str]) -> list[str]:
    """The components reading any of the settings groups named ``groups`` (of eqa.settings; others: none)."""
    import eqa.settings

    names: list[str] = []
    for name in groups:
        group = getattr(eqa.settings, name, None)
        if isinstance(group, type):
            names += [n for n in readers(group) if n not in names]
    return names


def _anchor(title: str) -> str:
    """GitHub's heading anchor: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", title.lower()).replace(" ", "-")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m eqa_app.config_doc",
        description="Print docs/configuration.md, generated from eqa/settings.py; --check FILE compares instead.",
    )
    p.add_argument("--check", type=Path, metavar="FILE", help="exit 1 (with the command to run) when FILE is stale")
    args = p.parse_args(argv)
    page = render()
    if args.check is None:
        sys.stdout.write(page)
        return 0
    if not args.check.is_file() or args.check.read_text() != page:
        print(f"{args.check} is stale: regenerate it with `{REGENERATE}`", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
