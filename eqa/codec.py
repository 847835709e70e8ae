"""Wire codec: pydantic messages <-> msgpack bytes, numpy arrays as raw bytes + dtype + shape.

Arrays never travel as JSON lists. A field typed :data:`NDArray` goes out as msgpack extension 1
(``dtype``, ``shape``, raw C-order bytes); a field typed :data:`ZNDArray` as extension 2, the same with the
bytes zlib-compressed (maps: large and mostly constant). In JSON mode (HTTP, logs) an array becomes
``{"dtype", "shape", "b64"}`` and validates back from that form.
"""

from __future__ import annotations

import base64
import math
import zlib
from typing import Annotated, Any

import msgpack
import numpy as np
from pydantic import PlainSerializer, PlainValidator, SerializationInfo

_EXT_RAW = 1
_EXT_ZLIB = 2
_ALLOWED_KINDS = set("biufc")  # bool, int, uint, float, complex: never object arrays
MAX_ARRAY_BYTES = 4096 * 4096 * 8
"""Largest decoded array (bytes): a 4096x4096 float64 layer (EQA_SIM_WIDTH/HEIGHT are at most 4096; a depth
image of that size is half of it). A header that declares more is refused before anything is allocated."""
MAX_DECODED_BYTES = 2 * MAX_ARRAY_BYTES
"""Largest sum of the decoded arrays of one message: a 1 MB payload whose compressed arrays would expand to
1 GB is refused before it is decompressed (it raised five services to 2.5 GB each)."""
MAX_NDIM = 8


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


def packed_array(array: np.ndarray, compress: bool = True) -> msgpack.ExtType:
    """``array`` encoded now, as the msgpack extension a message field uses (zlib-compressed when ``compress``):
    put it anywhere in a :func:`packb` payload and :func:`unpackb` gives the array back. For state written to
    the store (a mapper snapshot) whose arrays are encoded ahead of the rest."""
    return _encode_array(array, compress)


class _Budget:
    """Decoded bytes left for the arrays of one message."""

    __slots__ = ("left",)

    def __init__(self, limit: int) -> None:
        self.left = limit


def _declared_size(dtype: np.dtype, shape: Any) -> int:
    """Bytes of an array of ``shape`` (exact Python integers: no int64 overflow), checked against the caps."""
    if not isinstance(shape, list) or len(shape) > MAX_NDIM or not all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape
    ):
        raise CodecError(f"array shape {str(shape)[:80]} must be at most {MAX_NDIM} non-negative integers")
    need = math.prod(shape) * dtype.itemsize
    if need > MAX_ARRAY_BYTES:
        raise CodecError(f"array of shape {shape} ({need} bytes) is over the cap of {MAX_ARRAY_BYTES} bytes")
    return need


def _decode_array(code: int, data: bytes, budget: _Budget | None = None) -> Any:
    if code not in (_EXT_RAW, _EXT_ZLIB):
        return msgpack.ExtType(code, data)
    try:
        hlen = int.from_bytes(data[:4], "little")
        if not 0 < hlen <= min(len(data) - 4, 4096):
            raise CodecError(f"malformed array: header length {hlen} is not valid")
        dtype_str, shape = msgpack.unpackb(data[4 : 4 + hlen])
        dtype = _check_dtype(np.dtype(dtype_str))
        need = _declared_size(dtype, shape)
        if budget is not None:
            if need > budget.left:
                raise CodecError(f"the arrays of one message decode to over {MAX_DECODED_BYTES} bytes")
            budget.left -= need
        body: Any = memoryview(data)[4 + hlen :]  # a view: the array below shares ``data``, no copy
        if code == _EXT_ZLIB:
            # Never inflate past what the header declared: a zlib bomb stops at need + 1 bytes.
            inflater = zlib.decompressobj()
            body = inflater.decompress(body, need + 1)
            if inflater.unconsumed_tail or not inflater.eof:
                raise CodecError(f"compressed array body does not inflate to the {need} bytes its header declares")
        if need != len(body):
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


def unpackb(data: bytes, max_decoded: int = MAX_DECODED_BYTES) -> Any:
    """msgpack with numpy support; the arrays of one payload decode to at most ``max_decoded`` bytes."""
    budget = _Budget(max_decoded)
    try:
        return msgpack.unpackb(
            data, ext_hook=lambda code, raw: _decode_array(code, raw, budget), raw=False, strict_map_key=False
        )
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
        shape = value["shape"]
        need = _declared_size(dtype, list(shape) if isinstance(shape, list | tuple) else shape)
        if len(value["b64"]) > 4 * (need // 3 + 1):
            raise ValueError(f"array text is longer than its shape {value['shape']} of {dtype} needs")
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
