"""What a client asked the joints to stream as their heartbeat, kept to re-apply it after a
reconnect (a joint that lost power forgets it)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol import PacketID, commands, encode_packet

#: Payload bytes of a streamed reply, by packet id (a float unless listed).
_PAYLOAD_BYTES: dict[int, int] = {
    PacketID.MODE: 1,
    PacketID.HARDWARE_STATUS: 4,
    PacketID.SOFTWARE_VERSION: 3,
}
_FLOAT = 4


@dataclass(frozen=True)
class Stream:
    """`ids` sent by each of `devices` at `hz`; each device is addressed on its own."""

    ids: tuple[int, ...]
    hz: int
    devices: tuple[int, ...]

    def start_frames(self) -> list[bytes]:
        frames = [commands.heartbeat_set(d, self.ids).encode() for d in self.devices]
        frames += [commands.heartbeat_frequency(d, self.hz).encode() for d in self.devices]
        return frames

    def bytes_per_beat(self) -> int:
        """Wire bytes of one heartbeat of every device (the arm's replies, delimiters included)."""
        return sum(
            len(encode_packet(d, i, bytes(_PAYLOAD_BYTES.get(i, _FLOAT))))
            for d in self.devices
            for i in self.ids
        )

    def fits(self, wire_bytes_per_s: float | None) -> bool:
        """Whether the line carries this stream (None: a link without a rate limit)."""
        return wire_bytes_per_s is None or self.hz * self.bytes_per_beat() <= wire_bytes_per_s

    def max_hz(self, wire_bytes_per_s: float) -> int:
        """The highest whole rate the line carries for these ids and devices (0: none)."""
        return min(255, math.floor(wire_bytes_per_s / self.bytes_per_beat()))

    def stop_frames(self) -> list[bytes]:
        frames = [commands.heartbeat_frequency(d, 0).encode() for d in self.devices]
        frames += [commands.heartbeat_set(d, []).encode() for d in self.devices]
        return frames
