"""Codec for the Reach / Blueprint Lab (BPL) serial packet protocol, version 1. No I/O.

Clean-room implementation from the project's fact sheet (shared/reference/bpl-protocol.md).
"""

from . import commands, payload
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
from .ids import JOINT_ORDER, DeviceID, HardwareStatus, Mode, PacketID
from .packet import Packet, decode_packet

__all__ = [
    "JOINT_ORDER",
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
    "commands",
    "crc8",
    "decode_packet",
    "encode_packet",
    "payload",
]
