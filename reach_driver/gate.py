"""The checks every command passes before it is written: limits, the soft barrier, the
watchdog and the bus's broadcast rules. A refused command raises and nothing is sent.

Raw packets go through an allow-list: requests, heartbeat set-up and MODE pass; motion and
limit writes are checked; anything else (presets, RESET, SAVE, end-effector commands, ids
the protocol does not name) is refused, because a packet not known to be harmless may move
the arm or widen a limit. `ArmClient.send_unchecked` is the one way round.

A joint whose last HARDWARE_STATUS carries a blocking flag (`reach_driver.faults`) gets no
motion command (POSITION, VELOCITY, CURRENT, relative moves, a MODE that drives it): the
gate raises `ArmFaultError` naming the flag and why it blocks. Safe modes still go out.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from protocol import DeviceID, Mode, Packet, PacketID, ProtocolError
from reach_driver.errors import ArmFaultError, LimitError, WatchdogTrippedError
from reach_driver.faults import FaultFlags, flag_labels, why_blocking
from reach_driver.safety import LimitKind, SafetyGuard, as_range, envelope_problem
from reach_driver.state import StateTable, joint_name, packet_names
from reach_driver.watchdog import Watchdog

CONTROL_PACKETS = frozenset({PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT})
CONTINUOUS: dict[int, LimitKind] = {
    PacketID.VELOCITY: LimitKind.VELOCITY,
    PacketID.CURRENT: LimitKind.CURRENT,
}
LIMIT_KIND_OF: dict[int, LimitKind] = {kind.packet_id: kind for kind in LimitKind}
#: Packets every joint answers: broadcast on a half-duplex bus, the answers collide.
ANSWERED = (PacketID.REQUEST, PacketID.HEARTBEAT_SET, PacketID.HEARTBEAT_FREQUENCY)
#: Packets that neither move the arm nor change a limit.
HARMLESS = frozenset(ANSWERED)
#: Modes in which a joint holds still or goes limp; these may go to every device at once.
SAFE_MODES = frozenset({Mode.STANDBY, Mode.DISABLE, Mode.ZERO_VELOCITY, Mode.POSITION_HOLD})
END_EFFECTOR = frozenset({PacketID.KM_END_POS, PacketID.KM_END_VEL})
NOTHING_SENT = "nothing was sent"


class CommandGate:
    """Holds no state of its own: the guard's limits, the watchdog and the latest positions."""

    def __init__(
        self,
        guard: SafetyGuard,
        watchdog: Watchdog,
        table: StateTable,
        url: str,
        broadcast_ok: Callable[[], bool],
        devices: Sequence[int] = (),
        faults: FaultFlags | None = None,
    ) -> None:
        self.guard = guard
        self.watchdog = watchdog
        self.table = table
        self.url = url
        self.broadcast_ok = broadcast_ok
        self.devices = frozenset(int(d) for d in devices)
        self.faults = faults

    def check_device(self, device: int, what: str = "position/velocity/current") -> None:
        """A motion or limit packet goes to one joint of this arm, never to all at once."""
        if device == DeviceID.BROADCAST:
            raise LimitError(
                f"refused: broadcast {what} commands bypass per-joint "
                f"limits; address each joint; {NOTHING_SENT}"
            )
        known = self.guard.present_limit(device, LimitKind.POSITION) is not None
        if not known or (self.devices and device not in self.devices):
            raise LimitError(
                f"refused: {what} for {joint_name(device)}: not a device of this arm "
                f"(no limits to check it against); {NOTHING_SENT}"
            )

    def check_not_faulted(self, device: int, what: str = "motion commands") -> None:
        """Refuse `what` to a joint whose last status carries a blocking flag."""
        if self.faults is None:
            return
        flags = self.faults.flags(device)
        reasons = why_blocking(flags)
        if reasons:
            raise ArmFaultError(
                f"refused: {what} for {joint_name(device)}: it reports {reasons}; the joint "
                f"is blocked until its status clears (read_status() re-reads it; reported: "
                f"{', '.join(flag_labels(flags))}); {NOTHING_SENT}"
            )

    def check_positions(self, devices: Sequence[int], values: Sequence[float]) -> None:
        """All targets before any is sent."""
        for d, v in zip(devices, values, strict=True):
            self.check_device(int(d))
            self.guard.check(int(d), LimitKind.POSITION, v)
            self.check_not_faulted(int(d), "position")

    def continuous(
        self, pid: PacketID, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> tuple[list[int], np.ndarray]:
        """Velocities or currents after the barrier (what may be sent), or raise."""
        self._check_not_tripped()
        kind = CONTINUOUS[pid]
        devs = [int(d) for d in devices]
        vals = [float(v) for v in values]
        if len(devs) != len(vals):
            raise ValueError(f"{len(devs)} devices but {len(vals)} values")
        sent = np.empty(len(vals))
        for i, (d, v) in enumerate(zip(devs, vals, strict=True)):
            self.check_device(d)
            self.guard.check(d, kind, v)
            self.check_not_faulted(d, kind.value)
            sent[i] = self.guard.soften(d, self._position(d), v)
        return devs, sent

    def check_packet(self, packet: Packet) -> None:
        """A raw packet: refused where a command helper would refuse it; never scaled."""
        pid, dev = int(packet.packet_id), int(packet.device_id)
        try:
            if pid in HARMLESS:
                if not self.broadcast_ok() and dev == DeviceID.BROADCAST:
                    raise ValueError(
                        f"broadcast {packet_names([pid])} on half-duplex {self.url}: every "
                        "joint would answer at once and collide; address each device"
                    )
            elif pid == PacketID.MODE:
                self.check_mode(dev, packet.data)
            elif pid in CONTROL_PACKETS:
                self._check_control(packet)
            elif pid == PacketID.RELATIVE_POSITION:
                self._check_relative(dev, packet.as_float())
            elif pid == PacketID.INDEXED_POSITION:
                self._check_indexed(dev, packet.as_float())
            elif pid in END_EFFECTOR:
                raise LimitError(
                    f"refused: {packet_names([pid])} (end-effector motion) is solved by the "
                    "arm's own firmware, so its joint targets cannot be checked against the "
                    "limits first; command_xyz() solves it with the driver's inverse "
                    "kinematics and sends checked joint positions (or use command_positions); "
                    f"{NOTHING_SENT}"
                )
            elif pid in LIMIT_KIND_OF:
                values = packet.floats()
                if len(values) != 2:
                    raise LimitError(f"refused: limits need 2 floats; {NOTHING_SENT}")
                self.check_limit_write(dev, LIMIT_KIND_OF[pid], (values[0], values[1]))
            else:
                raise LimitError(
                    f"refused: {packet_names([pid])} to {joint_name(dev)} is not a packet the "
                    "driver knows to be harmless (it may move the arm or change a limit); "
                    f"send_unchecked() writes it as it is; {NOTHING_SENT}"
                )
        except ProtocolError as exc:
            raise LimitError(
                f"refused: malformed {packet_names([pid])} for {joint_name(dev)}: {exc}; "
                f"{NOTHING_SENT}"
            ) from None

    def check_mode(self, device: int, data: bytes) -> None:
        """A documented mode; to every device at once only if it is a safe one."""
        if len(data) != 1 or data[0] not in Mode._value2member_map_:
            raise LimitError(
                f"refused: MODE payload {data.hex() or 'empty'} for {joint_name(device)} is "
                f"not a documented mode; {NOTHING_SENT}"
            )
        mode = Mode(data[0])
        if device == DeviceID.BROADCAST and mode in SAFE_MODES:
            return
        self.check_device(device, f"MODE {mode.name}")
        if mode not in SAFE_MODES:
            self.check_not_faulted(device, f"MODE {mode.name}")

    def check_limit_write(
        self, device: int, kind: LimitKind, values: tuple[float, float], *, widen: bool = False
    ) -> None:
        """Finite, inside the factory envelope, and (unless `widen`) inside the present limit."""
        self.check_device(device, f"{kind.value} limits")
        problem = envelope_problem(device, kind, values, self.guard.model)
        if problem is not None:
            raise LimitError(f"refused: {problem}; {NOTHING_SENT}")
        if widen:
            return
        lo, hi = as_range(kind, values)
        present = self.guard.present_limit(device, kind)
        assert present is not None  # check_device: the device has limits
        plo, phi = present
        if lo < plo - 1e-6 * max(1.0, abs(plo)) or hi > phi + 1e-6 * max(1.0, abs(phi)):
            unit = kind.unit(device, self.guard.model)
            raise LimitError(
                f"refused: {kind.value} limits [{lo:.4g}, {hi:.4g}] {unit} for "
                f"{joint_name(device)} are wider than the present [{plo:.4g}, {phi:.4g}] "
                f"{unit}; widen_limits() widens them on purpose; {NOTHING_SENT}"
            )

    def _check_control(self, packet: Packet) -> None:
        pid, dev = int(packet.packet_id), int(packet.device_id)
        self.check_device(dev)
        value = packet.as_float()
        self.check_not_faulted(dev, packet_names([pid]))
        if pid == PacketID.POSITION:
            self.guard.check(dev, LimitKind.POSITION, value)
            return
        self._check_not_tripped()
        self.guard.check(dev, CONTINUOUS[pid], value)
        if self.guard.soften(dev, self._position(dev), value) != value:
            raise LimitError(
                f"refused: {packet_names([pid]).lower()} {value:.4g} for joint "
                f"{joint_name(dev)} "
                "pushes past its position limit (inside the soft barrier); use "
                f"command_currents/command_velocities to have it scaled; {NOTHING_SENT}"
            )

    def _check_relative(self, device: int, delta: float) -> None:
        """A relative move lands at the present position plus `delta`: check that target."""
        self.check_device(device, "relative position")
        self.check_not_faulted(device, "relative position")
        if not math.isfinite(delta):
            raise LimitError(
                f"refused: relative position {delta} for {joint_name(device)} is not finite; "
                f"{NOTHING_SENT}"
            )
        here = self._position(device)
        if here is None or not math.isfinite(here):
            raise LimitError(
                f"refused: relative position for {joint_name(device)}: its position is "
                f"unknown, so the target cannot be checked; read or stream POSITION first; "
                f"{NOTHING_SENT}"
            )
        try:
            self.guard.check(device, LimitKind.POSITION, here + delta)
        except LimitError as exc:
            raise LimitError(
                f"refused: relative position {delta:+.4g} from {here:.4g}: {exc}"
            ) from None

    def _check_indexed(self, device: int, value: float) -> None:
        self.check_device(device, "indexed position")
        self.check_not_faulted(device, "indexed position")
        if not self.guard.config.allow_indexed_position:
            raise LimitError(
                f"refused: INDEXED_POSITION to {joint_name(device)}: the protocol does not say "
                "what it is relative to, so its target cannot be checked against the "
                "position limits; use command_position or RELATIVE_POSITION (both checked), "
                f"or SafetyConfig(allow_indexed_position=True); {NOTHING_SENT}"
            )
        if not math.isfinite(value):
            raise LimitError(f"refused: indexed position {value} is not finite; {NOTHING_SENT}")

    def _check_not_tripped(self) -> None:
        tripped = self.watchdog.tripped
        if tripped is not None:
            raise WatchdogTrippedError(
                f"watchdog tripped ({tripped}); the arm was put in "
                f"{self.guard.config.safe_mode.name}; call rearm() to command again"
            )

    def _position(self, device: int) -> float | None:
        pos = self.table.get(device).position
        return None if pos is None else pos.value
