"""Version-1 BPL frames: `DATA | PACKET_ID | DEVICE_ID | LENGTH | CRC8`, COBS-encoded, + 0x00.

Sizes, id checks and encoding; decoding to a `Packet` lives in `packet.py`.
"""

from __future__ import annotations

import operator

from .cobs import cobs_encode
from .crc import TABLE, XOR_OUT
from .errors import CobsError, InvalidPacketError

DELIMITER = b"\x00"
MAX_DATA = 58  # the vendor library buffers 64 wire bytes
HEADER_SIZE = 4  # PACKET_ID, DEVICE_ID, LENGTH, CRC8
MAX_RAW = MAX_DATA + HEADER_SIZE  # 62: largest LENGTH value
MIN_ENCODED = HEADER_SIZE + 1  # COBS adds one byte (frames this short never need 0xFF codes)
MAX_ENCODED = MAX_RAW + 1  # 63 bytes between delimiters
MAX_WIRE = MAX_ENCODED + 1  # 64 including the delimiter
VERSION2_BIT = 0x80

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
    if type(device_id) is bool or type(packet_id) is bool:
        check_id("device_id", device_id)
        check_id("packet_id", packet_id)
    try:
        raw = data + bytes((packet_id, device_id, n + HEADER_SIZE))
    except (TypeError, ValueError):
        check_id("device_id", device_id)
        check_id("packet_id", packet_id)
        raise
    reg = 0
    table = TABLE
    for byte in raw:
        reg = table[reg ^ byte]
    return cobs_encode(raw + bytes((reg ^ XOR_OUT,))) + DELIMITER


def check_id(name: str, value: int) -> int:
    """`value` as an int 0..255: ints and integer types such as numpy's (`__index__`) pass,
    bools, floats and strings do not."""
    try:
        if isinstance(value, bool):
            raise TypeError
        number = operator.index(value)
    except TypeError:
        raise InvalidPacketError(
            f"{name} must be an int 0..255, got {type(value).__name__}"
        ) from None
    if not 0 <= number <= 0xFF:
        raise InvalidPacketError(f"{name} must be 0..255, got {number}")
    return number


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
