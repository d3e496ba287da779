"""Stream decoder bookkeeping: bounded memory, byte accounting, resynchronisation."""

from __future__ import annotations

from protocol import DecodeReason, Packet, PacketDecoder, commands

FRAME = commands.position(1, 1.5)
WIRE = FRAME.encode()


def test_memory_bounded_without_delimiter() -> None:
    decoder = PacketDecoder()
    for _ in range(1000):
        assert decoder.feed(b"\x55" * 37) == []
        assert decoder.pending_bytes <= 63
    assert decoder.stats.bytes_discarded + decoder.pending_bytes == 37_000
    assert decoder.stats.bad_total == 0  # counted when the delimiter finally arrives
    assert decoder.feed(b"\x00" + WIRE) == [FRAME]
    assert decoder.stats.bad_frames[DecodeReason.TOO_LONG] == 1
    assert decoder.stats.bytes_discarded == 37_001
    assert decoder.stats.good_frames == 1


def test_overflow_inside_one_big_chunk() -> None:
    decoder = PacketDecoder()
    assert decoder.feed(WIRE + b"\x55" * 5000) == [FRAME]
    assert decoder.pending_bytes == 0
    assert decoder.stats.bytes_discarded == 5000
    assert decoder.feed(b"\x55" * 10 + b"\x00" + WIRE + WIRE[:3]) == [FRAME]
    assert decoder.pending_bytes == 3
    assert decoder.feed(WIRE[3:]) == [FRAME]


def test_stray_delimiters_are_discarded_not_bad() -> None:
    decoder = PacketDecoder()
    assert decoder.feed(b"\x00\x00" + WIRE + b"\x00") == [FRAME]
    assert decoder.stats.bytes_discarded == 3
    assert decoder.stats.bad_total == 0
    assert decoder.stats.bytes_received == 3 + len(WIRE)


def test_frame_split_mid_garbage_resynchronises() -> None:
    decoder = PacketDecoder()
    # A frame cut short by a delimiter, then an intact one: only the intact one comes out.
    out = decoder.feed(WIRE[:5] + b"\x00" + WIRE)
    assert out == [FRAME]
    assert decoder.stats.bad_total == 1
    assert decoder.stats.bytes_discarded == 6


def test_reset_counts_pending_as_discarded() -> None:
    decoder = PacketDecoder()
    decoder.feed(WIRE[:4])
    decoder.reset()
    assert decoder.pending_bytes == 0
    assert decoder.stats.bytes_discarded == 4
    assert decoder.feed(WIRE[4:]) == []  # the tail alone is not a frame
    assert decoder.feed(WIRE) == [FRAME]


def test_accepts_bytearray_and_memoryview() -> None:
    decoder = PacketDecoder()
    assert decoder.feed(bytearray(WIRE)) == [FRAME]
    assert decoder.feed(memoryview(WIRE + WIRE)) == [FRAME, FRAME]
    assert decoder.stats.good_frames == 3


def test_many_frames_in_one_chunk_keep_order() -> None:
    frames = [Packet(d, 3, bytes([d, 0, 0, d])) for d in range(1, 50)]
    decoder = PacketDecoder()
    assert decoder.feed(b"".join(p.encode() for p in frames)) == frames
