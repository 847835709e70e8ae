"""Wire codec: pydantic messages <-> msgpack bytes, numpy arrays as raw bytes + dtype + shape.

Arrays never travel as JSON lists. A field typed :data:`NDArray` goes out as msgpack extension 1
(``dtype``, ``shape``, raw C-order bytes); a field typed :data:`ZNDArray` as extension 2, the same with the
bytes zlib-compressed (maps: large and mostly constant). In JSON mode (HTTP, logs) an array becomes
``{"dtype", "shape", "b64"}`` and validates back from that form.
"""

from __future__ import annotations

import base64
import zlib
from typing import Annotated, Any

import msgpack
import numpy as np
from pydantic import PlainSerializer, PlainValidator, SerializationInfo

_EXT_RAW = 1
_EXT_ZLIB = 2
_ALLOWED_KINDS = set("biufc")  # bool, int, uint, float, complex: never object arrays


class CodecError(ValueError):
    """A payload that cannot be decoded into the expected message."""


class _Compressed:
    """Marker that asks the encoder to compress one array."""

    __slots__ = ("array",)

    def __init__(self, array: np.ndarray) -> None:
        self.array = array


def _check_dtype(dtype: np.dtype) -> np.dtype:
    if dtype.kind not in _ALLOWED_KINDS:
        raise CodecError(f"array dtype {dtype} is not allowed on the wire")
    return dtype


def _pack_header(array: np.ndarray) -> bytes:
    return msgpack.packb([array.dtype.str, list(array.shape)])


def _encode_array(array: np.ndarray, compress: bool) -> msgpack.ExtType:
    array = np.ascontiguousarray(array)
    _check_dtype(array.dtype)
    header = _pack_header(array)
    # The array's own buffer (as bytes, no copy) goes straight into zlib / the one join below, so a large
    # image is copied once here instead of twice (``tobytes`` + concatenation).
    raw = array.reshape(-1).view(np.uint8)
    body: Any = zlib.compress(raw, 1) if compress else raw
    return msgpack.ExtType(
        _EXT_ZLIB if compress else _EXT_RAW, b"".join((len(header).to_bytes(4, "little"), header, body))
    )


def _decode_array(code: int, data: bytes) -> Any:
    if code not in (_EXT_RAW, _EXT_ZLIB):
        return msgpack.ExtType(code, data)
    try:
        hlen = int.from_bytes(data[:4], "little")
        dtype_str, shape = msgpack.unpackb(data[4 : 4 + hlen])
        dtype = _check_dtype(np.dtype(dtype_str))
        body: Any = memoryview(data)[4 + hlen :]  # a view: the array below shares ``data``, no copy
        if code == _EXT_ZLIB:
            body = zlib.decompress(body)
        count = int(np.prod(shape, dtype=np.int64)) if shape else 1
        if count * dtype.itemsize != len(body):
            need = count * dtype.itemsize
            raise CodecError(f"array body has {len(body)} bytes, shape {shape} of {dtype} needs {need}")
        return np.frombuffer(body, dtype=dtype).reshape(shape)
    except CodecError:
        raise
    except Exception as exc:  # malformed header, bad zlib stream, bad dtype string
        raise CodecError(f"malformed array: {exc}") from exc


def _default(obj: Any) -> Any:
    if isinstance(obj, _Compressed):
        return _encode_array(obj.array, compress=True)
    if isinstance(obj, np.ndarray):
        return _encode_array(obj, compress=False)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def packb(obj: Any) -> bytes:
    """msgpack with numpy support."""
    return msgpack.packb(obj, default=_default, use_bin_type=True)


def unpackb(data: bytes) -> Any:
    try:
        return msgpack.unpackb(data, ext_hook=_decode_array, raw=False, strict_map_key=False)
    except CodecError:
        raise
    except Exception as exc:
        raise CodecError(f"not a msgpack payload: {exc}") from exc


# ---- pydantic field types -------------------------------------------------------------------------------


def _validate_array(value: Any) -> np.ndarray:
    if isinstance(value, np.ndarray):
        _check_dtype(value.dtype)
        return value
    if isinstance(value, dict) and {"dtype", "shape", "b64"} <= set(value):
        dtype = _check_dtype(np.dtype(value["dtype"]))
        raw = base64.b64decode(value["b64"])
        return np.frombuffer(raw, dtype=dtype).reshape(value["shape"])
    raise ValueError(f"expected a numpy array, got {type(value).__name__}")


def _json_form(array: np.ndarray) -> dict[str, Any]:
    array = np.ascontiguousarray(array)
    return {"dtype": array.dtype.str, "shape": list(array.shape), "b64": base64.b64encode(array.tobytes()).decode()}


def _serialize_raw(value: np.ndarray, info: SerializationInfo) -> Any:
    return _json_form(value) if info.mode == "json" else value


def _serialize_zlib(value: np.ndarray, info: SerializationInfo) -> Any:
    return _json_form(value) if info.mode == "json" else _Compressed(value)


NDArray = Annotated[
    np.ndarray,
    PlainValidator(_validate_array),
    PlainSerializer(_serialize_raw, return_type=Any),
]
"""A numpy array field, sent as raw bytes."""

ZNDArray = Annotated[
    np.ndarray,
    PlainValidator(_validate_array),
    PlainSerializer(_serialize_zlib, return_type=Any),
]
"""A numpy array field, sent zlib-compressed (maps, masks)."""
