"""Each component reads only the settings groups it declares (eqa.settings.view).

Two checks: the narrowed object refuses a field of another group (and every test of the suite fails when a
component read one: tests/conftest.py), and a scan of each component's code (its package and the kernel modules
it imports) finds every read of a setting, including ``getattr(settings, "name", default)`` which would silently
fall back on the default, inside the component's groups.
"""

from __future__ import annotations

import ast
import pickle
from collections.abc import Iterator
from pathlib import Path

import pytest

from eqa.service import SHELL_GROUPS
from eqa.settings import (
    GROUPS,
    Groups,
    HomeSettings,
    ProcessSettings,
    Settings,
    SettingsGroup,
    SettingsView,
    SimulatorSettings,
    StoreSettings,
    view,
    view_class,
)

ROOT = Path(__file__).resolve().parents[2]
SETTINGS_NAMES = {"settings", "s", "hub_settings"}  # names that hold settings wherever they are bound
SETTINGS_TYPES = ("Settings", "SettingsGroup", "SettingsView")


def components() -> dict[str, tuple[list[Path], Groups]]:
    """Each component: the code that reads its settings (its package) and the groups it declares."""
    from eqa_app.config_doc import components as declared

    out: dict[str, tuple[list[Path], Groups]] = {}
    for name, (package, groups) in declared().items():
        if groups is None:
            continue  # the launcher reads every group (it hands the whole configuration to its children)
        out[name] = ([ROOT / package.replace(".", "/")], groups)
    return out


def _files(paths: list[Path]) -> list[Path]:
    out: list[Path] = []
    for p in paths:
        out += sorted(p.rglob("*.py")) if p.is_dir() else [p]
    return out


def _kernel_imports(files: list[Path]) -> list[Path]:
    """The modules of eqa/ that ``files`` import, and those they import in turn."""
    seen: set[str] = set()
    todo = list(files)
    while todo:
        tree = ast.parse(todo.pop().read_text())
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for name in names:
                path = ROOT / (name.replace(".", "/") + ".py")
                if name.startswith("eqa.") and path.is_file() and name not in seen:
                    seen.add(name)
                    todo.append(path)
    return [ROOT / (n.replace(".", "/") + ".py") for n in sorted(seen)]


def _is_settings(node: ast.expr, bound: set[str]) -> bool:
    if isinstance(node, ast.Name):
        return node.id in SETTINGS_NAMES or node.id in bound
    return isinstance(node, ast.Attribute) and node.attr in ("settings", "hub_settings")


def _bound(fn: ast.AST) -> set[str]:
    """Names of one function that hold settings: parameters typed as settings or of a ``from_settings``, and
    names assigned from settings."""
    out: set[str] = set()
    if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
        params = [*fn.args.posonlyargs, *fn.args.args, *fn.args.kwonlyargs]
        for i, a in enumerate(params):
            note = ast.unparse(a.annotation) if a.annotation is not None else ""
            if any(t in note for t in SETTINGS_TYPES) or (fn.name == "from_settings" and i == 1):
                out.add(a.arg)
    changed = True
    while changed:
        changed = False
        for node in ast.walk(fn):
            if isinstance(node, ast.Assign) and _is_settings(node.value, out):
                for t in node.targets:
                    if isinstance(t, ast.Name) and t.id not in out:
                        out.add(t.id)
                        changed = True
    return out


def reads(path: Path) -> Iterator[tuple[str, int]]:
    """``(setting, line)`` for each read of a setting in ``path``; a ``getattr`` with an f-string name reads
    every setting its constant prefix begins."""
    names = set(Settings.model_fields) | {n for n in dir(Settings) if not n.startswith("_")} - set(dir(SettingsView))
    tree = ast.parse(path.read_text())
    scopes = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)] + [tree]
    for scope in scopes:
        bound = _bound(scope)
        for node in ast.walk(scope):
            if isinstance(node, ast.Attribute) and node.attr in names and _is_settings(node.value, bound):
                yield node.attr, node.lineno
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr"
                  and len(node.args) >= 2 and _is_settings(node.args[0], bound)):
                key = node.args[1]
                if isinstance(key, ast.Constant) and isinstance(key.value, str):
                    yield key.value, node.lineno
                elif isinstance(key, ast.JoinedStr) and key.values and isinstance(key.values[0], ast.Constant):
                    prefix = str(key.values[0].value)
                    for name in sorted(n for n in Settings.model_fields if n.startswith(prefix)):
                        yield name, node.lineno


def test_a_view_has_its_groups_fields_and_refuses_the_others(settings_outside_groups: list[str]) -> None:
    full = Settings(sim_width=320, redis_url="redis://x:1/0")
    v = view(full, (ProcessSettings, SimulatorSettings))
    assert v.sim_width == 320 and v.scenes_path == full.scenes_path and v.recordings_path == full.recordings_path
    assert isinstance(v, SimulatorSettings) and not isinstance(v, StoreSettings)
    with pytest.raises(AttributeError, match="redis_url is a setting of StoreSettings"):
        _ = v.redis_url
    with pytest.raises(AttributeError, match="no attribute 'no_such_setting'"):
        _ = v.no_such_setting  # type: ignore[attr-defined]
    with pytest.raises(ValueError):
        v.sim_width = 640  # read-only
    assert set(v.model_dump()) == set(ProcessSettings.model_fields) | set(SimulatorSettings.model_fields)
    again = pickle.loads(pickle.dumps(v))  # to a process pool
    assert type(again) is type(v) and again == v
    # one class per set of groups, whatever their order; a view narrows further, never wider
    assert type(view(full, (SimulatorSettings, ProcessSettings))) is type(v) is view_class(
        (ProcessSettings, SimulatorSettings))
    assert view(v, (SimulatorSettings, ProcessSettings)) is v
    assert view(v, (ProcessSettings,)).instance == full.instance
    with pytest.raises(AttributeError):
        view(v, (ProcessSettings, HomeSettings))
    first_home_field = next(iter(HomeSettings.model_fields))
    assert [m.partition(" ")[0] for m in settings_outside_groups] == ["redis_url", first_home_field]  # conftest
    settings_outside_groups.clear()


def test_a_view_does_not_read_the_environment_again(monkeypatch: pytest.MonkeyPatch) -> None:
    full = Settings(sim_width=320)
    monkeypatch.setenv("EQA_SIM_WIDTH", "1024")
    assert view(full, (ProcessSettings, SimulatorSettings)).sim_width == 320


def test_every_field_is_in_one_group() -> None:
    owners = [name for g in GROUPS for name in g.model_fields]
    assert sorted(owners) == sorted(Settings.model_fields)
    assert not issubclass(SettingsView, Settings) and all(issubclass(g, SettingsGroup) for g in GROUPS)


def test_each_service_keeps_its_groups_only(tmp_path: Path) -> None:
    """A service handed the whole Settings keeps its view, and passes no whole Settings to what it builds."""
    from eqa_app.config_doc import components as declared
    from eqa_app.config_doc import service_classes

    full = Settings(data_dir=tmp_path)
    for name, cls in service_classes().items():
        groups = declared()[name][1]
        assert groups is not None and cls.settings_groups == groups
        assert set(SHELL_GROUPS) <= set(groups), name
        svc = cls(full)
        try:
            assert type(svc.settings) is view_class(groups), name
            seen: set[int] = set()
            todo: list[tuple[object, int]] = [(svc, 0)]
            while todo:
                obj, depth = todo.pop()
                if id(obj) in seen or depth > 4:
                    continue
                seen.add(id(obj))
                assert not isinstance(obj, Settings), f"{name}: whole Settings reachable from the service"
                if hasattr(obj, "__dict__") and not isinstance(obj, type) and type(obj).__module__.split(".")[0] in (
                        "eqa", "services", "gateway"):
                    todo += [(o, depth + 1) for o in vars(obj).values()]
                elif isinstance(obj, list | tuple | dict):
                    todo += [(o, depth + 1) for o in (obj.values() if isinstance(obj, dict) else obj)]
        finally:
            svc.bus.close()


@pytest.mark.parametrize("name", sorted(components()))
def test_the_code_of_a_component_reads_only_its_groups(name: str) -> None:
    paths, groups = components()[name]
    cls = view_class(groups)
    allowed = set(cls.model_fields) | set(dir(cls))
    files = _files(paths)
    outside = sorted({f"{f.relative_to(ROOT)}:{line} {setting}" for f in files + _kernel_imports(files)
                      for setting, line in reads(f) if setting not in allowed})
    assert not outside, f"{name} reads settings outside its groups {[g.__name__ for g in groups]}: {outside}"


def test_the_scan_finds_reads() -> None:
    """The scan above sees reads through self.settings, a local alias, a typed parameter and getattr."""
    src = ROOT / "tests" / "kernel" / "_scan_sample.py"
    src.write_text(
        "def f(self, cfg: Settings, other):\n"
        "    a = self.settings.sim_width\n"
        "    t = self.settings\n"
        "    b = t.redis_url + cfg.log_level + other.robots\n"
        "    return getattr(cfg, 'tau_lsv', 1.0), getattr(cfg, f'ros2_{a}_topic', None)\n")
    try:
        found = {name for name, _ in reads(src)}
    finally:
        src.unlink()
    ros2 = {n for n in Settings.model_fields if n.startswith("ros2_")}
    assert found == {"sim_width", "redis_url", "log_level", "tau_lsv"} | ros2
