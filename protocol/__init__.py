"""Codec for the Reach / Blueprint Lab (BPL) serial packet protocol, version 1. No I/O.

Clean-room implementation from the published protocol facts summarised in docs/protocol.md.
`protocol.alpha5` holds the arm's facts that the driver and the simulator both need
(`protocol.bravo7` the same for the Reach Bravo 7), and
`protocol.viewer` their live Rerun viewer plumbing (not imported here: it is not codec).
"""

from . import alpha5, bravo7, commands, payload
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
    "payload",
]
