"""Reading ``.npy`` and ``.npz`` arrays without the ``ast`` module.

numpy parses every array header with ``ast.literal_eval``. In CPython 3.11 the conversion of a parse tree to
Python objects keeps its recursion depth in interpreter-wide state (python/cpython#106905): when another thread
parses at the same moment -- and 3.11 parses source lines whenever it formats a traceback, for the carets of a
logged exception -- the read fails with a spurious ``SystemError: AST constructor recursion depth mismatch``.
A simulator restoring an episode after a restart read its scene so and dropped the episode's stored state.

The header numpy writes (format versions 1.0-3.0) is a fixed dict literal, ``{'descr': '<f4', 'fortran_order':
False, 'shape': (3, 4), }``, parsed here with a regular expression; plain dtypes only (no object arrays, no
structured dtypes: nothing the services store). Every array a service reads goes through this module.
"""

from __future__ import annotations

import io
import math
import re
import struct
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

MAGIC = b"\x93NUMPY"
MAX_HEADER_BYTES = 65_536
_HEADER = re.compile(
    r"^\{\s*'descr':\s*'(?P<descr>[<>|=]?[a-zA-Z]\d*)',\s*'fortran_order':\s*(?P<fortran>True|False),\s*"
    r"'shape':\s*\((?P<shape>[\d,\s]*)\),?\s*\}$"
)


def _read(fp: BinaryIO, what: str) -> np.ndarray:
    magic = fp.read(8)
    if len(magic) != 8 or magic[:6] != MAGIC:
        raise ValueError(f"{what}: not a .npy array")
    major = magic[6]
    if major == 1:
        (length,) = struct.unpack("<H", fp.read(2))
    elif major in (2, 3):
        (length,) = struct.unpack("<I", fp.read(4))
    else:
        raise ValueError(f"{what}: .npy format version {major} is not supported")
    if length > MAX_HEADER_BYTES:
        raise ValueError(f"{what}: .npy header of {length} bytes")
    header = fp.read(length).decode("latin1" if major < 3 else "utf8").strip()
    m = _HEADER.match(header)
    if m is None:
        raise ValueError(f"{what}: unsupported .npy header {header[:120]!r}")
    dtype = np.dtype(m["descr"])
    if dtype.hasobject:
        raise ValueError(f"{what}: object arrays are not read")
    shape = tuple(int(s) for s in m["shape"].split(",") if s.strip())
    count = math.prod(shape)
    data = fp.read(count * dtype.itemsize)
    if len(data) != count * dtype.itemsize:
        raise ValueError(f"{what}: truncated .npy array ({len(data)} of {count * dtype.itemsize} bytes)")
    flat = np.frombuffer(bytearray(data), dtype=dtype, count=count)
    return flat.reshape(shape, order="F" if m["fortran"] == "True" else "C")


def load(path: str | Path) -> np.ndarray:
    """The array of a ``.npy`` file (what ``np.load`` gives, writable)."""
    with open(path, "rb") as fp:
        return _read(fp, str(path))


def loads(data: bytes) -> np.ndarray:
    """The array of ``.npy`` bytes."""
    return _read(io.BytesIO(data), ".npy bytes")


def load_npz(data: bytes) -> dict[str, np.ndarray]:
    """The arrays of ``.npz`` bytes (``np.savez`` / ``np.savez_compressed``), by name."""
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            for name in z.namelist():
                if not name.endswith(".npy"):
                    raise ValueError(f".npz member {name!r} is not an array")
                with z.open(name) as fp:
                    out[name[: -len(".npy")]] = _read(fp, f".npz member {name!r}")  # type: ignore[arg-type]
    except zipfile.BadZipFile as exc:
        raise ValueError(f"not an .npz archive ({exc})") from exc
    return out
