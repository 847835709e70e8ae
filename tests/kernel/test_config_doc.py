"""docs/configuration.md is generated from eqa/settings.py (eqa_app/config_doc.py) and must not drift from it."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from eqa.settings import Settings, env_names
from eqa_app import config_doc

PAGE = Path(__file__).resolve().parents[2] / "docs" / "configuration.md"


def test_page_is_the_generated_one() -> None:
    assert PAGE.read_text() == config_doc.render(), (
        f"docs/configuration.md is stale (a setting was added or changed): run `{config_doc.REGENERATE}` "
        "from the repository root and commit the page"
    )


def test_every_setting_is_on_the_page_once() -> None:
    page = PAGE.read_text()
    for env in env_names():
        assert page.count(f"| `{env}` |") == 1, env
    assert len(config_doc.rows()) == len(Settings.model_fields)


REF = "issue"  # a tracker reference in a settings comment, which the page leaves out
SOURCE = f'''
class Demo(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="EQA_")

    # --- first ({REF} 99; a/b.py) ---
    alpha: int = Field(default=3, ge=1, le=9, description="how many ({REF} 98)")
    beta: str = "x"  # a trailing note
    # a group of two
    gamma: Literal["a", "b"] = "a"
    delta: list[str] = Field(default_factory=lambda: ["p", "q"])

    # --- second ---
    epsilon: float | None = None
'''


class Demo(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="EQA_")

    alpha: int = Field(default=3, ge=1, le=9, description=f"how many ({REF} 98)")
    beta: str = "x"
    gamma: Literal["a", "b"] = "a"
    delta: list[str] = Field(default_factory=lambda: ["p", "q"])
    epsilon: float | None = None


def test_rows_follow_the_sections_comments_and_fields() -> None:
    rows = {r.env: r for r in config_doc.rows(Demo, SOURCE)}
    assert list(rows) == ["EQA_ALPHA", "EQA_BETA", "EQA_GAMMA", "EQA_DELTA", "EQA_EPSILON"]
    assert rows["EQA_ALPHA"].section == "first (a/b.py)" and rows["EQA_EPSILON"].section == "second"
    assert (rows["EQA_ALPHA"].type, rows["EQA_ALPHA"].default, rows["EQA_ALPHA"].text) == (
        "integer, >= 1, <= 9", "`3`", "how many")
    assert rows["EQA_BETA"].text == "a trailing note"
    assert rows["EQA_GAMMA"].note == "a group of two" and rows["EQA_GAMMA"].type == "`a` \\| `b`"
    assert rows["EQA_DELTA"].default == "`p,q`"
    assert rows["EQA_EPSILON"].type == "number, optional" and rows["EQA_EPSILON"].default == "(unset)"
    page = config_doc.render(Demo, SOURCE)
    assert "## first\n\n*a/b.py*" in page and "\na group of two\n" in page and REF not in page


def test_check_mode_names_the_command(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    stale = tmp_path / "configuration.md"
    stale.write_text(config_doc.render().replace("EQA_LOG_LEVEL", "EQA_LOG_LEVELS"))
    assert config_doc.main(["--check", str(stale)]) == 1
    assert config_doc.REGENERATE in capsys.readouterr().err
    stale.write_text(config_doc.render())
    assert config_doc.main(["--check", str(stale)]) == 0


def test_every_setting_belongs_to_a_group() -> None:
    """Settings are declared in their groups (``eqa.settings.SettingsGroup`` subclasses), never on the flat class,
    and every group can be read on its own."""
    import eqa.settings as settings_module

    loose = [r.env for r in config_doc.rows() if not r.about]
    assert not loose, f"declare these in a settings group of eqa/settings.py, not on Settings: {loose}"
    groups = [k for k in Settings.__mro__ if k is not Settings and issubclass(k, settings_module.SettingsGroup)
              and k is not settings_module.SettingsGroup]
    assert sum(len(inspect.get_annotations(k)) for k in groups) == len(Settings.model_fields)
    for group in groups:
        assert set(group().model_dump()) <= set(Settings.model_fields)
