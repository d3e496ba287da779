"""What a client asked the joints to stream as their heartbeat, kept to re-apply it after a
reconnect (a joint that lost power forgets it), whether the line carries it, and which of a
joint's streamed readings the watchdog judges."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from protocol import PacketID, commands, encode_packet
from reach_driver.errors import LimitError
from reach_driver.state import JointState

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

    def capped_to(self, wire_bytes_per_s: float | None) -> tuple[Stream, str | None]:
        """This stream at a rate the line carries, and what was capped (None: it fits as it
        is). The arm would queue what the line cannot carry and send it late, shown as fresh
        (or drop it). `LimitError` if not even 1 Hz fits."""
        wire = wire_bytes_per_s
        if wire is None or self.fits(wire):
            return self, None
        capped = self.max_hz(wire)
        if capped < 1:
            raise LimitError(
                f"the line ({wire:.0f} B/s) cannot carry {len(self.ids)} ids from "
                f"{len(self.devices)} devices even at 1 Hz ({self.bytes_per_beat()} B "
                "a beat): stream fewer ids or devices"
            )
        said = (
            f"{self.hz} Hz of {len(self.ids)} ids from {len(self.devices)} devices needs "
            f"{self.hz * self.bytes_per_beat():.0f} B/s, more than the line's {wire:.0f}: "
            f"streaming at {capped} Hz"
        )
        return replace(self, hz=capped), said

    def stop_frames(self) -> list[bytes]:
        frames = [commands.heartbeat_frequency(d, 0).encode() for d in self.devices]
        frames += [commands.heartbeat_set(d, []).encode() for d in self.devices]
        return frames


def stalest_feedback(
    joint: JointState, device: int, stream: Stream | None
) -> tuple[float | None, str]:
    """When `joint`'s feedback last arrived, and which reading that was: its position always;
    its velocity too while it is streamed to `device` (a controller uses both, and either may
    stop alone). The stalest is judged, and named."""
    pos, vel = joint.position, joint.velocity
    fed: tuple[float | None, str] = (None if pos is None else pos.t, "position")
    if (
        stream is not None
        and PacketID.VELOCITY in stream.ids
        and device in stream.devices
        and vel is not None
        and (fed[0] is None or vel.t < fed[0])
    ):
        fed = (vel.t, "velocity")
    return fed
