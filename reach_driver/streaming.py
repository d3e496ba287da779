"""What a client asked the joints to stream as their heartbeat, kept to re-apply it after a
reconnect (a joint that lost power forgets it)."""

from __future__ import annotations

from dataclasses import dataclass

from protocol import commands


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

    def stop_frames(self) -> list[bytes]:
        frames = [commands.heartbeat_frequency(d, 0).encode() for d in self.devices]
        frames += [commands.heartbeat_set(d, []).encode() for d in self.devices]
        return frames
