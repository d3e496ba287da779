"""The `Packet` value type and single-frame decoding."""

from __future__ import annotations

from dataclasses import dataclass

from .errors import InvalidPacketError, PayloadError
from .framing import MAX_DATA, check_id, decode_body, encode_packet, frame_body
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
    """One BPL packet. Equal to any packet with the same ids (enum or int) and data."""

    device_id: int
    packet_id: int
    data: bytes = b""

    def __post_init__(self) -> None:
        check_id("device_id", self.device_id)
        check_id("packet_id", self.packet_id)
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
        object.__setattr__(self, "device_id", _DEVICE_IDS[self.device_id])
        object.__setattr__(self, "packet_id", _PACKET_IDS[self.packet_id])

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
_set = object.__setattr__


def packet_from_fields(device_id: int, packet_id: int, data: bytes) -> Packet:
    """A `Packet` from already-validated fields (decoder fast path, skips __post_init__)."""
    packet: Packet = _new(Packet)
    _set(packet, "device_id", _DEVICE_IDS[device_id])
    _set(packet, "packet_id", _PACKET_IDS[packet_id])
    _set(packet, "data", data)
    return packet


def decode_packet(frame: _BytesLike) -> Packet:
    """One frame, with or without its 0x00 terminator. Raises `DecodeError` subclasses."""
    return packet_from_fields(*decode_body(frame_body(frame)))
