"""Conformance vectors (tests/data/bpl-vectors.json, see docs/protocol.md), both directions."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from protocol import Packet, PacketDecoder, crc8, decode_packet, encode_packet

VECTORS_PATH = Path(__file__).resolve().parent / "data" / "bpl-vectors.json"

VECTORS: dict[str, Any] = json.loads(VECTORS_PATH.read_text())


def _hex(text: str) -> bytes:
    return bytes.fromhex(text)


CASES = [pytest.param(v, id=v["meaning"]) for v in VECTORS["vectors"]]


def _fields(v: dict[str, str]) -> tuple[int, int, bytes]:
    return int(v["device_id"], 16), int(v["packet_id"], 16), _hex(v["data"])


def test_vector_file_has_cases() -> None:
    assert len(VECTORS["vectors"]) >= 10


@pytest.mark.parametrize("v", CASES)
def test_encode_matches_wire(v: dict[str, str]) -> None:
    assert encode_packet(*_fields(v)) == _hex(v["wire"])
    assert Packet(*_fields(v)).encode() == _hex(v["wire"])


@pytest.mark.parametrize("v", CASES)
def test_decode_matches_fields(v: dict[str, str]) -> None:
    device_id, packet_id, data = _fields(v)
    wire = _hex(v["wire"])
    for frame in (wire, wire[:-1]):  # with and without the terminator
        packet = decode_packet(frame)
        assert (packet.device_id, packet.packet_id, packet.data) == (device_id, packet_id, data)


@pytest.mark.parametrize("v", CASES)
def test_stream_decoder_on_vector(v: dict[str, str]) -> None:
    decoder = PacketDecoder()
    assert decoder.feed(_hex(v["wire"])) == [Packet(*_fields(v))]
    assert decoder.stats.good_frames == 1
    assert decoder.stats.bytes_discarded == 0


def test_crc_check_value() -> None:
    check = VECTORS["crc8_check"]
    assert crc8(check["input_ascii"].encode("ascii")) == int(check["crc"], 16) == 0x7B
    assert crc8(b"") == 0xFF


def test_crc_is_the_frame_checksum() -> None:
    for v in VECTORS["vectors"]:
        raw = _hex(v["data"]) + bytes((int(v["packet_id"], 16), int(v["device_id"], 16)))
        raw += bytes((len(raw) + 2,))
        # No vector has a zero CRC, so the CRC is the last byte before the delimiter.
        assert crc8(raw) == _hex(v["wire"])[-2]


STREAM = _hex(VECTORS["stream_example"]["wire"])
STREAM_PACKETS = [Packet(0x01, 0x03, _hex("00 00 80 3F")), Packet(0x02, 0x03, _hex("00 00 00 40"))]


def _feed_all(chunks: list[bytes]) -> tuple[list[Packet], PacketDecoder]:
    decoder = PacketDecoder()
    out = [p for chunk in chunks for p in decoder.feed(chunk)]
    return out, decoder


@pytest.mark.parametrize("cut", range(len(STREAM) + 1))
def test_stream_example_split_at_every_byte(cut: int) -> None:
    packets, decoder = _feed_all([STREAM[:cut], STREAM[cut:]])
    assert packets == STREAM_PACKETS
    assert [p.floats() for p in packets] == [[1.0], [2.0]]
    assert decoder.stats.good_frames == 2
    assert decoder.stats.bad_total == 0
    assert decoder.pending_bytes == 0


def test_stream_example_split_at_every_pair_of_points() -> None:
    n = len(STREAM)
    for a in range(n + 1):
        for b in range(a, n + 1):
            packets, _ = _feed_all([STREAM[:a], STREAM[a:b], STREAM[b:]])
            assert packets == STREAM_PACKETS, (a, b)


def test_stream_example_one_byte_at_a_time() -> None:
    packets, decoder = _feed_all([STREAM[i : i + 1] for i in range(len(STREAM))])
    assert packets == STREAM_PACKETS
    assert decoder.stats.bytes_received == len(STREAM)
