"""The checks every command passes before it is written: limits, the soft barrier, the
watchdog and the bus's broadcast rules. A refused command raises and nothing is sent.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from protocol import DeviceID, Packet, PacketID
from reach_driver.errors import LimitError, WatchdogTrippedError
from reach_driver.safety import LimitKind, SafetyGuard
from reach_driver.state import StateTable, joint_name, packet_names
from reach_driver.watchdog import Watchdog

CONTROL_PACKETS = frozenset({PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT})
CONTINUOUS: dict[int, LimitKind] = {
    PacketID.VELOCITY: LimitKind.VELOCITY,
    PacketID.CURRENT: LimitKind.CURRENT,
}
#: Packets every joint answers: broadcast on a half-duplex bus, the answers collide.
ANSWERED = (PacketID.REQUEST, PacketID.HEARTBEAT_SET, PacketID.HEARTBEAT_FREQUENCY)


class CommandGate:
    """Holds no state of its own: the guard's limits, the watchdog and the latest positions."""

    def __init__(
        self,
        guard: SafetyGuard,
        watchdog: Watchdog,
        table: StateTable,
        url: str,
        broadcast_ok: Callable[[], bool],
    ) -> None:
        self.guard = guard
        self.watchdog = watchdog
        self.table = table
        self.url = url
        self.broadcast_ok = broadcast_ok

    def check_device(self, device: int) -> None:
        if device == DeviceID.BROADCAST:
            raise LimitError(
                "refused: broadcast position/velocity/current commands bypass per-joint "
                "limits; address each joint; nothing was sent"
            )

    def check_positions(self, devices: Sequence[int], values: Sequence[float]) -> None:
        """All targets before any is sent."""
        for d, v in zip(devices, values, strict=True):
            self.check_device(int(d))
            self.guard.check(int(d), LimitKind.POSITION, v)

    def continuous(
        self, pid: PacketID, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> tuple[list[int], np.ndarray]:
        """Velocities or currents after the barrier (what may be sent), or raise."""
        tripped = self.watchdog.tripped
        if tripped is not None:
            raise WatchdogTrippedError(
                f"watchdog tripped ({tripped}); the arm was put in "
                f"{self.guard.config.safe_mode.name}; call rearm() to command again"
            )
        kind = CONTINUOUS[pid]
        devs = [int(d) for d in devices]
        vals = [float(v) for v in values]
        if len(devs) != len(vals):
            raise ValueError(f"{len(devs)} devices but {len(vals)} values")
        sent = np.empty(len(vals))
        for i, (d, v) in enumerate(zip(devs, vals, strict=True)):
            self.check_device(d)
            self.guard.check(d, kind, v)
            sent[i] = self.guard.soften(d, self._position(d), v)
        return devs, sent

    def check_packet(self, packet: Packet) -> None:
        """A raw packet: refused where a command helper would refuse it; never scaled."""
        pid, dev = packet.packet_id, int(packet.device_id)
        if pid in CONTROL_PACKETS:
            self.check_device(dev)
            value = packet.as_float()
            if pid == PacketID.POSITION:
                self.guard.check(dev, LimitKind.POSITION, value)
                return
            tripped = self.watchdog.tripped
            if tripped is not None:
                raise WatchdogTrippedError(f"watchdog tripped ({tripped}); rearm() first")
            self.guard.check(dev, CONTINUOUS[pid], value)
            if self.guard.soften(dev, self._position(dev), value) != value:
                raise LimitError(
                    f"refused: {packet_names([pid]).lower()} {value:.4g} for joint "
                    f"{joint_name(dev)} "
                    "pushes past its position limit (inside the soft barrier); use "
                    "command_currents/command_velocities to have it scaled; nothing was sent"
                )
        elif not self.broadcast_ok() and dev == DeviceID.BROADCAST and pid in ANSWERED:
            raise ValueError(
                f"broadcast {packet_names([pid])} on half-duplex {self.url}: every "
                "joint would answer at once and collide; address each device"
            )

    def _position(self, device: int) -> float | None:
        pos = self.table.get(device).position
        return None if pos is None else pos.value
