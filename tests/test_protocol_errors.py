"""Every ProtocolError reason is reachable, says what is wrong, and is counted by the decoder."""

from __future__ import annotations

import pytest

from protocol import (
    CobsError,
    CrcError,
    DecodeError,
    DecodeReason,
    FrameTooLongError,
    FrameTooShortError,
    InvalidPacketError,
    LengthMismatchError,
    Packet,
    PacketDecoder,
    PayloadError,
    ProtocolError,
    Version2FrameError,
    crc8,
    decode_packet,
    encode_packet,
)
from protocol.cobs import cobs_encode

POSITION_1_5 = bytes.fromhex("01 01 07 C0 3F 03 01 08 CB 00")  # POSITION 1.5 rad to 0x01


def _frame(raw_without_crc: bytes) -> bytes:
    """A wire frame for arbitrary raw contents, with a correct CRC."""
    return cobs_encode(raw_without_crc + bytes((crc8(raw_without_crc),))) + b"\x00"


BAD_FRAMES = {
    # code 0x20 claims 31 more bytes, the frame has 5
    DecodeReason.COBS: (bytes.fromhex("20 01 02 03 04 05 00"), ["COBS", "past the end"]),
    DecodeReason.CRC: (POSITION_1_5[:-2] + b"\xcc\x00", ["CRC", "0xCC", "0xCB"]),
    DecodeReason.LENGTH: (_frame(b"\x00\x00\xc0\x3f\x03\x01\x09"), ["length", "9", "8"]),
    DecodeReason.TOO_SHORT: (bytes.fromhex("04 03 01 04 00"), ["too short", "4"]),
    DecodeReason.TOO_LONG: (_frame(bytes(range(1, 60)) + b"\x03\x01\x3f"), ["too long", "58"]),
    # version 2: option byte before PACKET_ID, LENGTH with bit 7 set
    DecodeReason.VERSION2: (_frame(b"\x01\x02\x07\x03\x01\x86"), ["version-2", "0x86"]),
}


def test_every_reason_has_a_case() -> None:
    assert set(BAD_FRAMES) == set(DecodeReason)


@pytest.mark.parametrize("reason", list(DecodeReason), ids=lambda r: r.value)
def test_reason_reachable_and_named(reason: DecodeReason) -> None:
    frame, words = BAD_FRAMES[reason]
    with pytest.raises(DecodeError) as info:
        decode_packet(frame)
    err = info.value
    assert err.reason is reason
    assert isinstance(err, ProtocolError)
    assert isinstance(err, ValueError)
    for word in words:
        assert word in str(err), (word, str(err))


@pytest.mark.parametrize("reason", list(DecodeReason), ids=lambda r: r.value)
def test_decoder_counts_reason_and_recovers(reason: DecodeReason) -> None:
    frame, _ = BAD_FRAMES[reason]
    seen: list[tuple[DecodeError, bytes]] = []
    decoder = PacketDecoder(on_error=lambda err, body: seen.append((err, body)))
    out = decoder.feed(frame + POSITION_1_5)
    assert out == [decode_packet(POSITION_1_5)]  # the frame after the bad one survives
    assert decoder.stats.bad_frames[reason] == 1
    assert decoder.stats.bad_total == 1
    assert decoder.stats.bytes_discarded == len(frame)
    assert [(e.reason, body) for e, body in seen] == [(reason, frame[:-1])]
    assert decoder.last_error is seen[0][0]


def test_crc_error_carries_values() -> None:
    with pytest.raises(CrcError) as info:
        decode_packet(BAD_FRAMES[DecodeReason.CRC][0])
    assert (info.value.expected, info.value.actual) == (0xCB, 0xCC)


def test_length_error_carries_values() -> None:
    with pytest.raises(LengthMismatchError) as info:
        decode_packet(BAD_FRAMES[DecodeReason.LENGTH][0])
    assert (info.value.declared, info.value.actual) == (9, 8)


def test_version2_is_not_misparsed_as_length_error() -> None:
    with pytest.raises(Version2FrameError) as info:
        decode_packet(BAD_FRAMES[DecodeReason.VERSION2][0])
    assert info.value.length_byte == 0x86


def test_every_single_bit_flip_is_rejected() -> None:
    for i in range(len(POSITION_1_5) - 1):
        for bit in range(8):
            corrupt = bytearray(POSITION_1_5)
            corrupt[i] ^= 1 << bit
            if 0 in corrupt[:-1]:
                with pytest.raises(CobsError):
                    decode_packet(bytes(corrupt))
            else:
                with pytest.raises(DecodeError):
                    decode_packet(bytes(corrupt))


@pytest.mark.parametrize("frame", [b"", b"\x00", b"\x01\x00", b"\x02\x05"])
def test_empty_and_tiny_frames(frame: bytes) -> None:
    with pytest.raises(FrameTooShortError, match="too short"):
        decode_packet(frame)


def test_zero_inside_frame() -> None:
    with pytest.raises(CobsError, match="zero byte at offset 9"):
        decode_packet(POSITION_1_5 + POSITION_1_5)


def test_too_long_counted_when_split_across_chunks() -> None:
    frame, _ = BAD_FRAMES[DecodeReason.TOO_LONG]
    decoder = PacketDecoder()
    for i in range(0, len(frame), 7):
        assert decoder.feed(frame[i : i + 7]) == []
        assert decoder.pending_bytes <= 63
    assert decoder.stats.bad_frames[DecodeReason.TOO_LONG] == 1
    assert decoder.stats.bytes_discarded == len(frame)
    assert decoder.feed(POSITION_1_5) == [decode_packet(POSITION_1_5)]


def test_decode_refuses_non_bytes() -> None:
    with pytest.raises(TypeError, match="bytes-like"):
        decode_packet("01 01 07")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="bytes-like"):
        PacketDecoder().feed("abc")  # type: ignore[arg-type]


def test_encode_refuses_oversize_data() -> None:
    assert len(encode_packet(1, 3, bytes(58))) == 64
    with pytest.raises(InvalidPacketError, match="59 bytes.*at most 58"):
        encode_packet(1, 3, bytes(59))
    with pytest.raises(InvalidPacketError, match="at most 58"):
        Packet(1, 3, bytes(59))


@pytest.mark.parametrize(
    ("device_id", "packet_id", "words"),
    [
        (256, 3, "device_id must be 0..255, got 256"),
        (1, -1, "packet_id must be 0..255, got -1"),
        (True, 3, "device_id must be an int"),
        (1.0, 3, "device_id must be an int"),
        (1, "3", "packet_id must be an int"),
    ],
)
def test_encode_refuses_bad_ids(device_id: object, packet_id: object, words: str) -> None:
    with pytest.raises(InvalidPacketError, match=words):
        encode_packet(device_id, packet_id, b"")  # type: ignore[arg-type]
    with pytest.raises(InvalidPacketError, match=words):
        Packet(device_id, packet_id)  # type: ignore[arg-type]


def test_encode_refuses_non_bytes_data() -> None:
    for bad in ([1, 2], "ab", 1.5):
        with pytest.raises(InvalidPacketError, match="bytes-like"):
            encode_packet(1, 3, bad)  # type: ignore[arg-type]
        with pytest.raises(InvalidPacketError, match="bytes-like"):
            Packet(1, 3, bad)  # type: ignore[arg-type]


def test_payload_errors_name_the_problem() -> None:
    with pytest.raises(PayloadError, match="3-byte payload is not a list of float32"):
        Packet(1, 3, b"abc").floats()
    with pytest.raises(PayloadError, match="expected one float32"):
        Packet(1, 3, bytes(8)).as_float()
    # The known defect: MODE sent as bytes(Mode.STANDBY) == b'' is caught when read.
    with pytest.raises(PayloadError, match="MODE payload has 0 bytes, expected exactly one u8"):
        decode_packet(encode_packet(5, 1, b"")).as_u8()


def test_error_classes() -> None:
    for cls in (CobsError, CrcError, LengthMismatchError, FrameTooShortError, FrameTooLongError):
        assert issubclass(cls, DecodeError)
    assert issubclass(Version2FrameError, DecodeError)
    for base in (DecodeError, InvalidPacketError, PayloadError):
        assert issubclass(base, ProtocolError)
