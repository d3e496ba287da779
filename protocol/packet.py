"""The `Packet` value type and single-frame decoding."""

from __future__ import annotations

from dataclasses import dataclass

from .crc import RESIDUE, TABLE, crc8
from .errors import (
    CobsError,
    CrcError,
    FrameTooLongError,
    FrameTooShortError,
    InvalidPacketError,
    LengthMismatchError,
    PayloadError,
    Version2FrameError,
)
from .framing import (
    MAX_DATA,
    MAX_ENCODED,
    MIN_ENCODED,
    VERSION2_BIT,
    check_id,
    encode_packet,
    frame_body,
)
from .ids import DeviceID, PacketID
from .payload import unpack_floats

# Known ids as enum members, unknown ones as plain ints: decoding never fails on an id.
_PACKET_IDS: tuple[int, ...] = tuple(
    PacketID(i) if i in PacketID._value2member_map_ else i for i in range(256)
)
_DEVICE_IDS: tuple[int, ...] = tuple(
    DeviceID(i) if i in DeviceID._value2member_map_ else i for i in range(256)
)

_BytesLike = bytes | bytearray | memoryview


def _name(table: tuple[int, ...], value: int) -> str:
    known = table[value] if 0 <= value <= 0xFF else value
    return f"{type(known).__name__}.{known.name}" if hasattr(known, "name") else f"0x{value:02X}"


@dataclass(frozen=True, slots=True)
class Packet:
    """One BPL packet, validated on construction (ids 0..255, at most 58 data bytes).

    Known ids are stored as `DeviceID` / `PacketID` members, others as ints; either way a
    packet equals (and hashes like) any packet with the same numbers and data.
    """

    device_id: int
    packet_id: int
    data: bytes = b""

    def __post_init__(self) -> None:
        device_id = check_id("device_id", self.device_id)
        packet_id = check_id("packet_id", self.packet_id)
        data = self.data
        if not isinstance(data, bytes):
            if not isinstance(data, bytearray | memoryview):
                raise InvalidPacketError(
                    f"data must be bytes-like, got {type(data).__name__}"
                    " (use protocol.payload to pack floats and u8 lists)"
                )
            data = bytes(data)
            object.__setattr__(self, "data", data)
        if len(data) > MAX_DATA:
            raise InvalidPacketError(
                f"data is {len(data)} bytes; a frame carries at most {MAX_DATA}"
            )
        object.__setattr__(self, "device_id", _DEVICE_IDS[device_id])
        object.__setattr__(self, "packet_id", _PACKET_IDS[packet_id])

    def __repr__(self) -> str:
        return (
            f"Packet({_name(_DEVICE_IDS, self.device_id)}, "
            f"{_name(_PACKET_IDS, self.packet_id)}, {self.data!r})"
        )

    @property
    def key(self) -> tuple[int, int]:
        """(device_id, packet_id): what a reply must match (never the packet id alone)."""
        return (self.device_id, self.packet_id)

    def encode(self) -> bytes:
        """Wire bytes, terminator included."""
        return encode_packet(self.device_id, self.packet_id, self.data)

    def floats(self) -> list[float]:
        """The payload as little-endian float32s (`PayloadError` if not a multiple of 4)."""
        return unpack_floats(self.data)

    def u8s(self) -> list[int]:
        return list(self.data)

    def as_float(self) -> float:
        """The payload's single float32 (POSITION, VELOCITY, CURRENT, ...)."""
        if len(self.data) != 4:
            raise PayloadError(
                f"{_name(_PACKET_IDS, self.packet_id)} payload has {len(self.data)} bytes, "
                "expected one float32 (4 bytes)"
            )
        return unpack_floats(self.data)[0]

    def as_u8(self) -> int:
        """The payload's single byte (MODE, HEARTBEAT_FREQUENCY, DEVICE_ID, ...)."""
        if len(self.data) != 1:
            raise PayloadError(
                f"{_name(_PACKET_IDS, self.packet_id)} payload has {len(self.data)} bytes, "
                "expected exactly one u8"
            )
        return self.data[0]


_new = object.__new__
# Slot descriptors set fields directly, bypassing the frozen __setattr__ (decoder fast path).
_set_device = Packet.__dict__["device_id"].__set__
_set_packet = Packet.__dict__["packet_id"].__set__
_set_data = Packet.__dict__["data"].__set__


def decode_body(body: bytes) -> Packet:
    """The packet in one frame given without its delimiter and holding no 0x00 byte.

    Callers guarantee there is no zero (the stream decoder splits on it, `decode_packet`
    checks): a zero code byte would never advance the COBS walk below. Hot path: one
    bytearray per frame, COBS undone in place, one CRC pass over the frame including its CRC
    byte (an intact frame leaves a fixed residue); the exact CRC is computed only on failure.
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
    # Each COBS code byte marks where a zero was. The first is overhead: zeroed, it becomes a
    # leading zero, which leaves a zero-initialised reflected CRC register unchanged.
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
        if length & VERSION2_BIT:
            raise Version2FrameError(length)
        raise LengthMismatchError(length, n - 1)
    reg = 0
    table = TABLE
    for byte in buf:
        reg = table[reg ^ byte]
    if reg != RESIDUE:
        raise CrcError(expected=crc8(buf[1 : n - 1]), actual=buf[n - 1])
    packet: Packet = _new(Packet)
    _set_device(packet, _DEVICE_IDS[buf[n - 3]])
    _set_packet(packet, _PACKET_IDS[buf[n - 4]])
    _set_data(packet, bytes(buf[1 : n - 4]))
    return packet


def decode_packet(frame: _BytesLike) -> Packet:
    """One frame, with or without its 0x00 terminator. Raises `DecodeError` subclasses."""
    return decode_body(frame_body(frame))
