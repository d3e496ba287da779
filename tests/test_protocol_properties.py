"""Property tests of the codec: round trips, arbitrary chunking, garbage, zero-heavy data."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import (
    MAX_DATA,
    MAX_WIRE,
    DecodeError,
    Packet,
    PacketDecoder,
    crc8,
    decode_packet,
    encode_packet,
)
from protocol.cobs import cobs_decode, cobs_encode

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

ids = st.integers(0, 255)
zero_heavy = st.lists(st.sampled_from([0, 0, 0, 1, 0xFF]), max_size=MAX_DATA).map(bytes)
data = st.one_of(st.binary(max_size=MAX_DATA), zero_heavy)
packets = st.builds(Packet, ids, ids, data)


def _crc8_reference(message: bytes) -> int:
    """Textbook Rocksoft model, MSB-first with explicit reflections (independent of the table)."""

    def reflect(value: int, width: int) -> int:
        return int(f"{value:0{width}b}"[::-1], 2)

    reg = 0x00
    for byte in message:
        reg ^= reflect(byte, 8)
        for _ in range(8):
            reg = ((reg << 1) ^ 0x4D) & 0xFF if reg & 0x80 else (reg << 1) & 0xFF
    return reflect(reg, 8) ^ 0xFF


@SETTINGS
@given(st.binary(max_size=80))
def test_crc_matches_textbook_model(message: bytes) -> None:
    assert crc8(message) == _crc8_reference(message)


@SETTINGS
@given(ids, ids, data)
def test_round_trip(device_id: int, packet_id: int, payload: bytes) -> None:
    wire = encode_packet(device_id, packet_id, payload)
    assert wire.index(0) == len(wire) - 1  # exactly one zero, the terminator
    assert len(wire) <= MAX_WIRE
    assert len(wire) == len(payload) + 6  # COBS adds one byte to frames this short
    packet = decode_packet(wire)
    assert (packet.device_id, packet.packet_id, packet.data) == (device_id, packet_id, payload)
    assert decode_packet(wire[:-1]) == packet


@SETTINGS
@given(zero_heavy)
def test_zero_heavy_data(payload: bytes) -> None:
    packet = Packet(0x05, 0x02, payload)
    decoder = PacketDecoder()
    wire = packet.encode()
    assert decoder.feed(wire + wire) == [packet, packet]
    assert decoder.stats.bytes_discarded == 0


@SETTINGS
@given(st.lists(packets, max_size=12), st.lists(st.integers(0, 10_000), max_size=12))
def test_stream_cut_anywhere(frames: list[Packet], cuts: list[int]) -> None:
    stream = b"".join(p.encode() for p in frames)
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    decoder = PacketDecoder()
    out: list[Packet] = []
    for a, b in zip(points, points[1:], strict=False):
        out += decoder.feed(stream[a:b])
    assert out == frames
    assert decoder.stats.good_frames == len(frames)
    assert decoder.stats.bad_total == 0
    assert decoder.pending_bytes == 0


def _oracle(segments: list[bytes]) -> list[Packet]:
    """What a stream decoder must output: every delimited piece decoded on its own."""
    out: list[Packet] = []
    for piece in b"".join(segments).split(b"\x00")[:-1]:
        if piece:
            try:
                out.append(decode_packet(piece))
            except DecodeError:
                pass
    return out


garbage = st.one_of(st.binary(max_size=90), st.binary(min_size=60, max_size=200))


@SETTINGS
@given(st.lists(st.tuples(garbage, packets), max_size=8), garbage, st.integers(1, 70))
def test_garbage_between_frames(
    pairs: list[tuple[bytes, Packet]], trailing: bytes, chunk: int
) -> None:
    # Garbage, then a delimiter, then an intact frame: the frame must come out.
    segments = []
    for junk, packet in pairs:
        segments += [junk, b"\x00", packet.encode()]
    segments.append(trailing)
    stream = b"".join(segments)
    decoder = PacketDecoder()
    out: list[Packet] = []
    for i in range(0, len(stream), chunk):
        out += decoder.feed(stream[i : i + chunk])  # never raises
    assert out == _oracle(segments)
    it = iter(out)
    assert all(any(p == q for q in it) for _, p in pairs)  # intact frames, in order
    stats = decoder.stats
    good_bytes = sum(len(p.encode()) for p in out)
    assert stats.bytes_received == len(stream)
    assert stats.bytes_received == good_bytes + stats.bytes_discarded + decoder.pending_bytes
    assert stats.good_frames == len(out)
    assert decoder.pending_bytes <= 63


@SETTINGS
@given(st.lists(st.one_of(garbage, packets.map(Packet.encode)), max_size=10), st.data())
def test_stats_do_not_depend_on_chunking(parts: list[bytes], draw: st.DataObject) -> None:
    stream = b"".join(parts) + b"\x00"
    whole = PacketDecoder()
    expected = whole.feed(stream)
    sizes = draw.draw(st.lists(st.integers(1, 80), min_size=1, max_size=20))
    chunked = PacketDecoder()
    out: list[Packet] = []
    i = k = 0
    while i < len(stream):
        out += chunked.feed(stream[i : i + sizes[k % len(sizes)]])
        i += sizes[k % len(sizes)]
        k += 1
    assert out == expected
    assert chunked.stats == whole.stats


long_runs = st.binary(min_size=250, max_size=600).map(lambda b: b.replace(b"\x00", b"\x01"))
cobs_inputs = st.one_of(
    st.binary(max_size=600),
    st.lists(st.sampled_from([0, 1]), max_size=300).map(bytes),
    st.tuples(long_runs, st.binary(max_size=3), long_runs).map(b"\x00".join),
)


@SETTINGS
@given(cobs_inputs)
def test_cobs_matches_reference_package(raw: bytes) -> None:
    """Our COBS against the `cobs` package, including 0xFF blocks (runs of 254+ non-zeros)."""
    cobs_pkg = pytest.importorskip("cobs.cobs")
    encoded = cobs_encode(raw)
    assert 0 not in encoded
    assert cobs_decode(encoded) == raw
    assert cobs_decode(cobs_pkg.encode(raw)) == raw
    assert cobs_pkg.decode(encoded) == raw
