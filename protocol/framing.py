"""Version-1 BPL frames: `DATA | PACKET_ID | DEVICE_ID | LENGTH | CRC8`, COBS-encoded, + 0x00.

The hot paths (every received byte goes through `decode_body`) are written for CPython speed:
one bytearray per frame, COBS undone in place, and one CRC pass over the frame including its
CRC byte (an intact frame leaves a fixed residue).
"""

from __future__ import annotations

from .cobs import cobs_encode
from .crc import RESIDUE, TABLE, XOR_OUT, crc8
from .errors import (
    CobsError,
    CrcError,
    FrameTooLongError,
    FrameTooShortError,
    InvalidPacketError,
    LengthMismatchError,
    Version2FrameError,
)

DELIMITER = b"\x00"
MAX_DATA = 58  # the vendor library buffers 64 wire bytes
HEADER_SIZE = 4  # PACKET_ID, DEVICE_ID, LENGTH, CRC8
MAX_RAW = MAX_DATA + HEADER_SIZE  # 62: largest LENGTH value
MIN_ENCODED = HEADER_SIZE + 1  # COBS adds one byte (frames this short never need 0xFF codes)
MAX_ENCODED = MAX_RAW + 1  # 63 bytes between delimiters
MAX_WIRE = MAX_ENCODED + 1  # 64 including the delimiter
_VERSION2_BIT = 0x80

_BytesLike = bytes | bytearray | memoryview


def encode_packet(device_id: int, packet_id: int, data: _BytesLike = b"") -> bytes:
    """Wire bytes of one packet, terminator included. Raises `InvalidPacketError`."""
    if not isinstance(data, bytes):
        if not isinstance(data, bytearray | memoryview):
            raise InvalidPacketError(
                f"data must be bytes-like, got {type(data).__name__}"
                " (use protocol.payload to pack floats and u8 lists)"
            )
        data = bytes(data)
    n = len(data)
    if n > MAX_DATA:
        raise InvalidPacketError(
            f"data is {n} bytes; a frame carries at most {MAX_DATA} (64 wire bytes)"
        )
    check_id("device_id", device_id)
    check_id("packet_id", packet_id)
    raw = data + bytes((packet_id, device_id, n + HEADER_SIZE))
    reg = 0
    table = TABLE
    for byte in raw:
        reg = table[reg ^ byte]
    return cobs_encode(raw + bytes((reg ^ XOR_OUT,))) + DELIMITER


def check_id(name: str, value: int) -> None:
    """Refuse anything that is not an int in 0..255 (bools too: they are a mistake here)."""
    if not isinstance(value, int) or isinstance(value, bool):
        raise InvalidPacketError(f"{name} must be an int 0..255, got {type(value).__name__}")
    if not 0 <= value <= 0xFF:
        raise InvalidPacketError(f"{name} must be 0..255, got {value}")


def decode_body(body: bytes) -> tuple[int, int, bytes]:
    """(device_id, packet_id, data) of one frame without its delimiter and without zeros.

    Callers guarantee `body` holds no 0x00 byte (the stream decoder splits on it; the
    single-frame API checks): a zero code would never advance the COBS walk.
    """
    n = len(body)
    if n > MAX_ENCODED:
        raise FrameTooLongError(
            f"frame too long: {n} encoded bytes, at most {MAX_ENCODED} "
            f"({MAX_DATA} data bytes) before the delimiter"
        )
    if n < MIN_ENCODED:
        raise FrameTooShortError(
            f"frame too short: {n} encoded bytes, a frame has at least {MIN_ENCODED} "
            "(COBS code, packet id, device id, length, CRC)"
        )
    buf = bytearray(body)
    # COBS in place: each code byte marks where a zero was; the first one is overhead and
    # becomes a leading zero, which a zero-initialised reflected CRC ignores.
    i = buf[0]
    buf[0] = 0
    while i < n:
        code = buf[i]
        buf[i] = 0
        i += code
    if i != n:
        raise CobsError(f"COBS: a code byte runs {i - n} byte(s) past the end of the frame")
    length = buf[n - 2]
    if length != n - 1:
        if length & _VERSION2_BIT:
            raise Version2FrameError(length)
        raise LengthMismatchError(length, n - 1)
    reg = 0
    table = TABLE
    for byte in buf:
        reg = table[reg ^ byte]
    if reg != RESIDUE:
        raise CrcError(expected=crc8(buf[1 : n - 1]), actual=buf[n - 1])
    return buf[n - 3], buf[n - 4], bytes(buf[1 : n - 4])


def frame_body(frame: _BytesLike) -> bytes:
    """The bytes of one frame between delimiters: drops one trailing 0x00, refuses others."""
    if not isinstance(frame, bytes | bytearray | memoryview):
        raise TypeError(f"frame must be bytes-like, got {type(frame).__name__}")
    body = bytes(frame)
    if body.endswith(DELIMITER):
        body = body[:-1]
    zero = body.find(DELIMITER)
    if zero >= 0:
        raise CobsError(
            f"COBS: zero byte at offset {zero} inside the frame (a frame has one 0x00, at its "
            "end; feed streams to PacketDecoder)"
        )
    return body
