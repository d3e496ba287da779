"""Codec for the Reach / Blueprint Lab (BPL) serial packet protocol, version 1. No I/O.

Clean-room implementation from the published protocol facts summarised in docs/protocol.md.
`protocol.models` holds the arm models both the driver and the simulator need, one
`ArmModel` per arm (`ALPHA5`, `BRAVO7`), built from each arm's facts in `protocol.alpha5` and
`protocol.bravo7`; `protocol.viewer` their live Rerun viewer plumbing (not imported here: it
is not codec).
"""

from . import alpha5, bravo7, commands, models, payload
from .crc import crc8
from .decoder import DecoderStats, PacketDecoder
from .errors import (
    CobsError,
    CrcError,
    DecodeError,
    DecodeReason,
    FrameTooLongError,
    FrameTooShortError,
    InvalidPacketError,
    LengthMismatchError,
    PayloadError,
    ProtocolError,
    Version2FrameError,
)
from .framing import MAX_DATA, MAX_WIRE, encode_packet
from .ids import DeviceID, HardwareStatus, Mode, PacketID
from .packet import Packet, decode_packet

__all__ = [
    "MAX_DATA",
    "MAX_WIRE",
    "CobsError",
    "CrcError",
    "DecodeError",
    "DecodeReason",
    "DecoderStats",
    "DeviceID",
    "FrameTooLongError",
    "FrameTooShortError",
    "HardwareStatus",
    "InvalidPacketError",
    "LengthMismatchError",
    "Mode",
    "Packet",
    "PacketDecoder",
    "PacketID",
    "PayloadError",
    "ProtocolError",
    "Version2FrameError",
    "alpha5",
    "bravo7",
    "commands",
    "crc8",
    "decode_packet",
    "encode_packet",
    "models",
    "payload",
]
