"""Errors raised by the codec.

Every decode failure has its own class and a `reason` so a stream decoder can count failures by
kind without parsing messages. All of them are `ValueError`s, so callers that only care about
"bad input" can catch that.
"""

from __future__ import annotations

from enum import Enum


class DecodeReason(str, Enum):
    """Why a received frame was dropped (the keys of `DecoderStats.bad_frames`)."""

    COBS = "cobs"
    CRC = "crc"
    LENGTH = "length"
    TOO_SHORT = "too_short"
    TOO_LONG = "too_long"
    VERSION2 = "version2"


class ProtocolError(ValueError):
    """Base class of every error raised by `protocol`."""


class InvalidPacketError(ProtocolError):
    """A packet that cannot be put on the wire (id out of range, data too long, wrong type)."""


class PayloadError(ProtocolError):
    """A payload that does not have the shape its packet needs (e.g. 3 bytes read as floats)."""


class DecodeError(ProtocolError):
    """A received frame that is not a valid version-1 BPL frame."""

    reason: DecodeReason


class CobsError(DecodeError):
    reason = DecodeReason.COBS


class CrcError(DecodeError):
    reason = DecodeReason.CRC

    def __init__(self, expected: int, actual: int) -> None:
        super().__init__(
            f"CRC mismatch: frame carries 0x{actual:02X}, its contents give 0x{expected:02X}"
        )
        self.expected = expected
        self.actual = actual


class LengthMismatchError(DecodeError):
    reason = DecodeReason.LENGTH

    def __init__(self, declared: int, actual: int) -> None:
        super().__init__(
            f"length mismatch: LENGTH byte says {declared} but the decoded frame has {actual} bytes"
        )
        self.declared = declared
        self.actual = actual


class FrameTooShortError(DecodeError):
    reason = DecodeReason.TOO_SHORT


class FrameTooLongError(DecodeError):
    reason = DecodeReason.TOO_LONG


class Version2FrameError(DecodeError):
    reason = DecodeReason.VERSION2

    def __init__(self, length_byte: int) -> None:
        super().__init__(
            f"version-2 frame (LENGTH byte 0x{length_byte:02X} has bit 7 set): not supported, "
            "only version-1 frames are decoded"
        )
        self.length_byte = length_byte
