"""eqa.npy: .npy / .npz reads without the ast module (CPython 3.11's ast conversion is not thread-safe,
python/cpython#106905: a sim restoring an episode read its scene with np.load while another thread formatted a
traceback, and dropped the episode's stored state)."""

from __future__ import annotations

import ast
import io
import re
from pathlib import Path

import numpy as np
import pytest

from eqa import npy

ROOT = Path(__file__).resolve().parents[2]
ARRAYS = [
    np.arange(12, dtype=np.float32).reshape(3, 4),
    np.zeros((0, 3), np.int64),
    np.array(5.0),
    np.asfortranarray(np.arange(6, dtype=np.int32).reshape(2, 3)),
    np.array(["mug", "sofa", "other"]),
    np.array([True, False, True]),
    np.arange(10, dtype=">u2"),
]


@pytest.mark.parametrize("a", ARRAYS, ids=lambda a: f"{a.dtype.str}{a.shape}")
def test_reads_what_numpy_writes(a: np.ndarray, tmp_path: Path) -> None:
    path = tmp_path / "a.npy"
    np.save(path, a)
    b = npy.load(path)
    assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b)
    assert b.flags.writeable  # as np.load gives it
    buf = io.BytesIO()
    np.save(buf, a)
    assert np.array_equal(npy.loads(buf.getvalue()), a)
    for save in (np.savez, np.savez_compressed):
        buf = io.BytesIO()
        save(buf, first=a, second=a[..., None])
        z = npy.load_npz(buf.getvalue())
        assert list(z) == ["first", "second"] and np.array_equal(z["first"], a)


def test_reads_without_the_ast_module(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """With ast's parser made to fail, np.load fails and eqa.npy still reads."""
    path = tmp_path / "a.npy"
    np.save(path, np.arange(4.0))

    def broken(*args: object, **kw: object) -> None:
        raise SystemError("AST constructor recursion depth mismatch (before=51, after=165)")

    monkeypatch.setattr(ast, "parse", broken)
    monkeypatch.setattr(ast, "literal_eval", broken)
    with pytest.raises(SystemError):
        np.load(path)
    assert np.array_equal(npy.load(path), np.arange(4.0))


def test_bad_input_is_a_value_error(tmp_path: Path) -> None:
    buf = io.BytesIO()
    np.save(buf, np.arange(100.0))
    good = buf.getvalue()
    with pytest.raises(ValueError, match="truncated"):
        npy.loads(good[:-8])
    with pytest.raises(ValueError, match=r"not a \.npy"):
        npy.loads(b"PK\x03\x04 not numpy")
    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="object arrays"):
        npy.loads(buf.getvalue())
    with pytest.raises(ValueError, match=r"not an \.npz"):
        npy.load_npz(good)


def test_no_service_reads_arrays_with_np_load() -> None:
    """Services and the kernel read arrays through eqa.npy (the reference bench's worker runs in the reference's
    own venv, where eqa is not importable, and is single-threaded)."""
    found = []
    for top in ("eqa", "services", "gateway", "eqa_app"):
        for path in sorted((ROOT / top).rglob("*.py")):
            if path.relative_to(ROOT).as_posix() == "eqa_app/benches/reference.py":
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if re.search(r"\b(np|numpy)\.load\(", line):
                    found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not found, "\n".join(found)
