"""A benchmark's question or task set as one JSON file (readable, diffable, stable key order)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def save_json(data: dict[str, Any], path: Path) -> Path:
    """Write ``data`` to ``path`` (parent folders made); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    return path


def load_json(path: Path) -> dict[str, Any]:
    """The object a :func:`save_json` file holds."""
    data = json.loads(Path(path).read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a benchmark file (a JSON object expected)")
    return data
