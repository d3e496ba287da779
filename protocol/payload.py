"""Payload packing: little-endian float32 lists and u8 lists (BPL v1 has no other types)."""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable

from .errors import PayloadError

_FLOAT_SIZE = 4
# One precompiled Struct per count a frame can hold (58 data bytes -> at most 14 floats).
_FLOATS = [struct.Struct(f"<{k}f") for k in range(58 // _FLOAT_SIZE + 1)]

_BytesLike = bytes | bytearray | memoryview


def pack_floats(*values: float) -> bytes:
    """Little-endian f32s. Refuses non-numbers and values that overflow float32."""
    k = len(values)
    packer = _FLOATS[k] if k < len(_FLOATS) else struct.Struct(f"<{k}f")
    try:
        return packer.pack(*values)
    except (struct.error, TypeError) as exc:
        raise PayloadError(f"cannot pack {values!r} as float32: {exc}") from None
    except OverflowError:
        raise PayloadError(f"value out of float32 range in {values!r}") from None


def unpack_floats(data: _BytesLike) -> list[float]:
    """The f32s of a payload; its length must be a multiple of 4."""
    n = len(data)
    if n % _FLOAT_SIZE:
        raise PayloadError(f"{n}-byte payload is not a list of float32 (needs a multiple of 4)")
    k = n // _FLOAT_SIZE
    unpacker = _FLOATS[k] if k < len(_FLOATS) else struct.Struct(f"<{k}f")
    return list(unpacker.unpack(data))


def pack_u8s(*values: int) -> bytes:
    """Bytes from ints 0..255; refuses anything else (bools and floats included)."""
    for v in values:
        if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= 0xFF:
            raise PayloadError(f"u8 values must be ints 0..255, got {v!r}")
    return bytes(values)


def unpack_u8s(data: _BytesLike) -> list[int]:
    return list(bytes(data))


def finite(name: str, value: float) -> float:
    """`value` as a float if it is a finite real number (commands never carry NaN or inf)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PayloadError(f"{name} must be a number, got {type(value).__name__}")
    f = float(value)
    if not math.isfinite(f):
        raise PayloadError(f"{name} must be finite, got {value!r}")
    return f


def checked_ids(name: str, ids: Iterable[int], lo: int, hi: int) -> list[int]:
    """Packet ids for REQUEST / HEARTBEAT_SET: between `lo` and `hi` of them, each 1..255.

    Zero is refused: it is the padding value, and a list with leading zeros is a known defect.
    """
    if isinstance(ids, str | bytes | bytearray):
        raise PayloadError(f"{name} takes a list of packet ids, got {type(ids).__name__}")
    out = list(ids)
    if not lo <= len(out) <= hi:
        raise PayloadError(f"{name} takes {lo} to {hi} packet ids, got {len(out)}")
    for v in out:
        if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 0xFF:
            raise PayloadError(f"{name}: packet ids are ints 1..255 (0 is padding), got {v!r}")
    return out
