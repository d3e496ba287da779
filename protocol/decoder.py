"""Incremental stream decoding: bytes in any chunking -> packets, with every loss counted."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from .errors import DecodeError, DecodeReason, FrameTooLongError
from .framing import MAX_ENCODED
from .packet import Packet, decode_body


def _zero_counts() -> dict[DecodeReason, int]:
    return dict.fromkeys(DecodeReason, 0)


@dataclass
class DecoderStats:
    """Counters of one decoder.

    Every byte received is in exactly one place: a good frame (with its delimiter),
    `bytes_discarded` (bad frames with their delimiters, stray delimiters, overflow), or
    the decoder's pending partial frame.
    """

    bytes_received: int = 0
    good_frames: int = 0
    bytes_discarded: int = 0
    bad_frames: dict[DecodeReason, int] = field(default_factory=_zero_counts)

    @property
    def bad_total(self) -> int:
        return sum(self.bad_frames.values())


ErrorCallback = Callable[[DecodeError, bytes], None]


class PacketDecoder:
    """Splits a byte stream on 0x00 and decodes each frame; drops (and counts) bad ones.

    Decoding resumes at the next delimiter after any garbage. A partial frame longer than the
    largest valid frame is dropped at once (so memory stays bounded when no delimiter ever
    comes) and the rest of it, up to the next delimiter, is discarded as it arrives.
    `on_error(error, frame_bytes)` is called for each dropped frame, e.g. to log it; it must
    not raise (packets already decoded from the same chunk would be lost with the exception).
    """

    __slots__ = ("stats", "_pending", "_overflowing", "_on_error", "last_error")

    def __init__(self, on_error: ErrorCallback | None = None) -> None:
        self.stats = DecoderStats()
        self._pending = b""
        self._overflowing = False
        self._on_error = on_error
        self.last_error: DecodeError | None = None

    @property
    def pending_bytes(self) -> int:
        """Bytes held for a frame whose delimiter has not arrived (at most 63)."""
        return len(self._pending)

    def reset(self) -> None:
        """Forget any partial frame (counted as discarded); statistics are kept."""
        self.stats.bytes_discarded += len(self._pending)
        self._pending = b""
        self._overflowing = False

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[Packet]:
        """Packets completed by `chunk`, in stream order. Never raises on stream content."""
        if not isinstance(chunk, bytes):
            if not isinstance(chunk, bytearray | memoryview):
                raise TypeError(f"feed() takes bytes-like data, got {type(chunk).__name__}")
            chunk = bytes(chunk)
        stats = self.stats
        stats.bytes_received += len(chunk)
        if self._overflowing:
            end = chunk.find(0)
            if end < 0:
                stats.bytes_discarded += len(chunk)
                return []
            self._overflowing = False
            self._drop(FrameTooLongError(_too_long_message()), chunk[:end], end + 1)
            chunk = chunk[end + 1 :]
        pieces = (self._pending + chunk if self._pending else chunk).split(b"\x00")
        tail = pieces.pop()
        if len(tail) > MAX_ENCODED:
            stats.bytes_discarded += len(tail)
            tail = b""
            self._overflowing = True
        self._pending = tail
        packets: list[Packet] = []
        append = packets.append
        for body in pieces:
            if body:
                try:
                    append(decode_body(body))
                except DecodeError as err:
                    self._drop(err, body, len(body) + 1)
            else:
                stats.bytes_discarded += 1  # a delimiter with no frame before it
        stats.good_frames += len(packets)
        return packets

    def _drop(self, err: DecodeError, body: bytes, size: int) -> None:
        stats = self.stats
        stats.bad_frames[err.reason] += 1
        stats.bytes_discarded += size
        self.last_error = err
        if self._on_error is not None:
            self._on_error(err, body)


def _too_long_message() -> str:
    return (
        f"frame too long: more than {MAX_ENCODED} bytes without a delimiter "
        "(dropped while it arrived)"
    )
