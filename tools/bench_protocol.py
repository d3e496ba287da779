"""Encode/decode throughput of `protocol` against a straightforward baseline, same process.

The baseline is what public BPL implementations do: per frame `cobs.cobs.encode/decode` (the
`cobs` package, a C extension) plus a CRC-8 computed bit by bit for each byte, and a stream
split on 0x00. A second, stronger baseline uses a 256-entry CRC table with the same C COBS, to
show where the speed comes from. Every implementation's output is checked against ours before
anything is timed.

    python tools/bench_protocol.py [--frames N] [--chunk BYTES] [--repeat K] [--seed S]
"""

from __future__ import annotations

import argparse
import platform
import random
import struct
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cobs import cobs  # noqa: E402  (the baseline's COBS, dev/bench extra)

from protocol import Packet, PacketDecoder, PacketID, encode_packet  # noqa: E402
from protocol.crc import TABLE  # noqa: E402

Frame = tuple[int, int, bytes]


def mixed_frames(n: int, seed: int) -> list[Frame]:
    """(device, packet, data) mix of a control session: mostly float commands and replies,
    requests, version replies, and zero-heavy payloads (0.0 floats, padded heartbeat sets)."""
    rng = random.Random(seed)
    f32 = struct.Struct("<f").pack
    out: list[Frame] = []
    for _ in range(n):
        dev = rng.choice((1, 2, 3, 4, 5))
        kind = rng.random()
        if kind < 0.35:
            out.append((dev, PacketID.POSITION, f32(rng.uniform(0.0175, 6.14))))
        elif kind < 0.60:
            out.append((dev, PacketID.VELOCITY, f32(rng.uniform(-1.0, 1.0))))
        elif kind < 0.75:
            ids = rng.sample((1, 2, 3, 5, 0x68, 0x90), rng.randint(1, 3))
            out.append((rng.choice((dev, 0xFF)), PacketID.REQUEST, bytes(ids)))
        elif kind < 0.85:
            out.append((dev, PacketID.SOFTWARE_VERSION, bytes(rng.randint(0, 9) for _ in "abc")))
        elif kind < 0.93:
            out.append((dev, rng.choice((PacketID.VELOCITY, PacketID.CURRENT)), bytes(4)))
        elif kind < 0.97:
            out.append((0xFF, PacketID.HEARTBEAT_SET, bytes((3, 2)) + bytes(8)))
        else:
            limit = rng.choice((300.0, 600.0))
            out.append((dev, PacketID.CURRENT_LIMITS, f32(limit) + f32(0.0)))
    return out


def crc8_bitwise(data: bytes) -> int:
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xB2 if crc & 1 else crc >> 1
    return crc ^ 0xFF


def crc8_table(data: bytes) -> int:
    crc = 0
    for byte in data:
        crc = TABLE[crc ^ byte]
    return crc ^ 0xFF


def baseline_encode(crc: Callable[[bytes], int]) -> Callable[[int, int, bytes], bytes]:
    def encode(device_id: int, packet_id: int, data: bytes) -> bytes:
        raw = data + bytes((packet_id, device_id, len(data) + 4))
        return cobs.encode(raw + bytes((crc(raw),))) + b"\x00"

    return encode


class BaselineDecoder:
    """Split on 0x00, keep the tail, COBS-decode, check length and CRC, hand out tuples."""

    def __init__(self, crc: Callable[[bytes], int]) -> None:
        self.crc = crc
        self.buf = b""
        self.bad = 0

    def feed(self, chunk: bytes) -> list[Frame]:
        pieces = (self.buf + chunk).split(b"\x00")
        self.buf = pieces.pop()
        out: list[Frame] = []
        for piece in pieces:
            if not piece:
                continue
            try:
                raw = cobs.decode(piece)
            except cobs.DecodeError:
                self.bad += 1
                continue
            if len(raw) < 4 or raw[-2] != len(raw) or self.crc(raw[:-1]) != raw[-1]:
                self.bad += 1
                continue
            out.append((raw[-3], raw[-4], raw[:-4]))
        return out


def best_of(repeat: int, fn: Callable[[], object]) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=(
            "Throughput of protocol.encode_packet and protocol.PacketDecoder on a mixed "
            "stream, printed next to a baseline (cobs package + bitwise CRC, and cobs "
            "package + table CRC) timed in the same process, as frames/s, us/frame and ratio."
        )
    )
    parser.add_argument("--frames", type=int, default=100_000, help="frames in the stream")
    parser.add_argument(
        "--chunk", type=int, default=256, help="bytes per feed() call when decoding (256)"
    )
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure; best is kept")
    parser.add_argument("--seed", type=int, default=1, help="seed of the frame mix")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.chunk < 1 or args.repeat < 1:
        parser.error("--frames, --chunk and --repeat must be positive")

    frames = mixed_frames(args.frames, args.seed)
    wire = [encode_packet(*f) for f in frames]
    stream = b"".join(wire)
    chunks = [stream[i : i + args.chunk] for i in range(0, len(stream), args.chunk)]
    baselines = {"cobs+bitwise CRC": crc8_bitwise, "cobs+table CRC": crc8_table}

    # Same bytes and the same packets from every implementation, or no figures at all.
    expected = [Packet(*f) for f in frames]
    dec = PacketDecoder()
    got = [p for c in chunks for p in dec.feed(c)]
    if got != expected or dec.stats.bad_total:
        raise SystemExit("protocol decoder does not reproduce the stream")
    for name, crc in baselines.items():
        enc = baseline_encode(crc)
        if [enc(*f) for f in frames] != wire:
            raise SystemExit(f"baseline {name} encodes differently")
        bdec = BaselineDecoder(crc)
        if [Packet(*t) for c in chunks for t in bdec.feed(c)] != expected:
            raise SystemExit(f"baseline {name} decodes differently")

    n = len(frames)
    print(
        f"{n} frames, {len(stream)} bytes ({len(stream) / n:.1f} B/frame), feed chunks of "
        f"{args.chunk} B, best of {args.repeat}; Python {platform.python_version()}"
    )

    def ours_encode() -> None:
        for f in frames:
            encode_packet(*f)

    def ours_decode() -> None:
        d = PacketDecoder()
        for c in chunks:
            d.feed(c)

    t_enc = best_of(args.repeat, ours_encode)
    t_dec = best_of(args.repeat, ours_decode)
    header = f"{'':24} {'frames/s':>10} {'us/frame':>9}"
    print(header)
    print(f"{'protocol encode':24} {n / t_enc:10.0f} {t_enc / n * 1e6:9.2f}")
    print(f"{'protocol decode':24} {n / t_dec:10.0f} {t_dec / n * 1e6:9.2f}")
    for name, crc in baselines.items():
        enc = baseline_encode(crc)

        def base_encode(enc: Callable[[int, int, bytes], bytes] = enc) -> None:
            for f in frames:
                enc(*f)

        def base_decode(crc: Callable[[bytes], int] = crc) -> None:
            d = BaselineDecoder(crc)
            for c in chunks:
                d.feed(c)

        b_enc = best_of(args.repeat, base_encode)
        b_dec = best_of(args.repeat, base_decode)
        print(
            f"{name + ' encode':24} {n / b_enc:10.0f} {b_enc / n * 1e6:9.2f}"
            f"   protocol is {b_enc / t_enc:.2f}x"
        )
        print(
            f"{name + ' decode':24} {n / b_dec:10.0f} {b_dec / n * 1e6:9.2f}"
            f"   protocol is {b_dec / t_dec:.2f}x"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
