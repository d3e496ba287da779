"""Consistent Overhead Byte Stuffing, pure Python, for any length.

Both directions work block by block (one Python step per zero byte, not per byte): encoding
splits on zeros with `bytes.split`, decoding walks the chain of code bytes in a bytearray.
"""

from __future__ import annotations

from .errors import CobsError

_CODE = [bytes((i,)) for i in range(256)]
_MAX_BLOCK = 254  # data bytes after a 0xFF code, which implies no zero


def cobs_encode(raw: bytes | bytearray | memoryview) -> bytes:
    """COBS-encode `raw`; the result has no zero byte and no terminator."""
    raw = bytes(raw)
    if len(raw) < _MAX_BLOCK:
        if 0 not in raw:
            return _CODE[len(raw) + 1] + raw
        out: list[bytes] = []
        append = out.append
        for block in raw.split(b"\x00"):
            append(_CODE[len(block) + 1])
            append(block)
        return b"".join(out)
    return _encode_long(raw)


def _encode_long(raw: bytes) -> bytes:
    out: list[bytes] = []
    for block in raw.split(b"\x00"):
        # A zero-free run of 254 or more bytes is cut into 0xFF blocks, which carry no zero.
        while len(block) >= _MAX_BLOCK:
            out.append(b"\xff")
            out.append(block[:_MAX_BLOCK])
            block = block[_MAX_BLOCK:]
        out.append(_CODE[len(block) + 1])
        out.append(block)
    return b"".join(out)


def cobs_decode(encoded: bytes | bytearray | memoryview) -> bytes:
    """Decode one COBS block sequence (no terminator). Raises `CobsError`."""
    buf = bytearray(encoded)
    n = len(buf)
    if n == 0:
        raise CobsError("COBS: empty input")
    if 0 in buf:
        raise CobsError(f"COBS: zero byte at offset {buf.index(0)} inside an encoded frame")
    if n <= _MAX_BLOCK:
        # Without a 0xFF code every code byte stands for one zero: decoding is zeroing the
        # code positions and dropping the first byte.
        i = buf[0]
        while i < n:
            code = buf[i]
            buf[i] = 0
            i += code
        if i != n:
            raise CobsError(f"COBS: code byte runs {i - n} byte(s) past the end of the frame")
        return bytes(buf[1:])
    return _decode_long(buf)


def _decode_long(buf: bytearray) -> bytes:
    out: list[bytes] = []
    n = len(buf)
    i = 0
    while i < n:
        code = buf[i]
        end = i + code
        if end > n:
            raise CobsError(f"COBS: code byte runs {end - n} byte(s) past the end of the frame")
        out.append(bytes(buf[i + 1 : end]))
        if code != 0xFF and end < n:
            out.append(b"\x00")
        i = end
    return b"".join(out)
