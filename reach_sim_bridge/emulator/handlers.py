"""What each packet from the host does to the devices it is for (`PacketHandlers`), and how a
packet is refused (`Rejected`, counted in `Firmware.errors` and flagged SERIAL_ERROR).

`PacketHandlers` is a part of `Firmware` (`reach_sim_bridge.emulator.firmware`), which maps
packet ids to these handlers; kept apart because they are the firmware's answer to the wire,
while the firmware itself runs the control loops, the monitor, heartbeats and end-effector
moves. The state the handlers use is the firmware's, declared below.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from protocol import DeviceID, HardwareStatus, Mode, Packet, PacketID
from protocol.commands import HEARTBEAT_SLOTS, MAX_REQUEST_IDS
from protocol.ids import UNDOCUMENTED_MODES
from reach_sim_bridge.emulator.devices import (
    HOLDING_MODES,
    Device,
    ErrorReason,
    FirmwareConfig,
    Ignored,
    Limits,
    Saved,
)
from reach_sim_bridge.emulator.events import EventLog
from reach_sim_bridge.model.arm import MotorArm

# Control packets that switch the mode implicitly; DISABLE and PASSIVE ignore them.
_LOCKED_MODES = frozenset({Mode.DISABLE, Mode.PASSIVE})


class Rejected(Exception):
    """A well-framed packet refused, and why."""

    def __init__(self, reason: ErrorReason, message: str) -> None:
        super().__init__(message)
        self.reason = reason


Handler = Callable[[list[Device], Packet], list[Packet]]


class PacketHandlers:
    """The packet handlers of `Firmware` (see the module docstring)."""

    arm: MotorArm
    config: FirmwareConfig
    errors: EventLog
    ignored: EventLog
    _reporters: dict[int, Callable[[Device], bytes | None]]
    _other_reporters: dict[int, Callable[[Device], bytes | None]]

    if TYPE_CHECKING:

        def _position(self, d: Device) -> float: ...

        def report(self, device_id: int, packet_id: int) -> Packet | None: ...

    def _reportable(self, packet_id: int) -> bool:
        """Whether some device of the arm can report `packet_id`."""
        return packet_id in self._reporters or packet_id in self._other_reporters

    # -- errors -----------------------------------------------------------------------------
    def _error(
        self, targets: Sequence[Device], reason: ErrorReason, message: str, flag: bool = True
    ) -> None:
        self.errors.record(reason.value, message)
        if flag:
            self._raise_flag(targets, HardwareStatus.SERIAL_ERROR)

    def _raise_flag(self, targets: Sequence[Device], flag: HardwareStatus) -> None:
        now = self.arm.time
        for d in targets:
            if not d.status:
                d.status_phase = self.config.status_period_s  # report at the next step
            d.status |= flag
            d.last_error_time = now

    # -- packet handlers --------------------------------------------------------------------
    def _set_mode(self, d: Device, mode: Mode) -> None:
        if mode == d.mode:
            return
        if mode in HOLDING_MODES:
            d.position_target = self._position(d)
        d.velocity_target = 0.0
        d.current_target = 0.0
        # Bumpless: the velocity loop's integral starts at the current already applied.
        d.integral = d.applied_mA / d.spec.gains.velocity_i
        d.mode = mode

    def _on_mode(self, targets: list[Device], packet: Packet) -> list[Packet]:
        data = packet.data
        if len(data) != 1:
            hint = " (an empty MODE: a sender using bytes(Mode.X)?)" if not data else ""
            raise Rejected(
                ErrorReason.BAD_PAYLOAD, f"MODE payload must be 1 byte, got {len(data)}{hint}"
            )
        if data[0] in UNDOCUMENTED_MODES:
            # Sent by a widely used client library; undocumented, so not emulated: the device
            # keeps its mode, and nothing is flagged.
            self.ignored.record(
                Ignored.UNIMPLEMENTED_MODE.value,
                f"mode 0x{data[0]:02X} is not documented in protocol V1.12.1; mode kept",
            )
            return []
        try:
            mode = Mode(data[0])
        except ValueError:
            raise Rejected(
                ErrorReason.UNKNOWN_MODE, f"mode 0x{data[0]:02X} is not one this firmware runs"
            ) from None
        for d in targets:
            self._set_mode(d, mode)
        return []

    def _control(self, targets: list[Device], name: str) -> list[Device]:
        """The targets that accept a control packet (the others are counted as ignored)."""
        accepted = [d for d in targets if d.mode not in _LOCKED_MODES]
        if len(accepted) < len(targets):
            locked = " ".join(d.spec.letter for d in targets if d.mode in _LOCKED_MODES)
            self.ignored.record(
                Ignored.LOCKED.value, f"{name} ignored by {locked}: DISABLE/PASSIVE mode"
            )
        return accepted

    def _on_position(self, targets: list[Device], packet: Packet) -> list[Packet]:
        value = one_float(packet, "POSITION")
        for d in self._control(targets, "POSITION"):
            self._command_position(d, value)
        return []

    def _on_relative(self, targets: list[Device], packet: Packet) -> list[Packet]:
        delta = one_float(packet, "relative POSITION")
        for d in self._control(targets, "relative POSITION"):
            base = d.position_target if d.mode == Mode.POSITION else self._position(d)
            value = base + delta
            if d.continuous:
                value %= 2.0 * math.pi
            self._command_position(d, value)
        return []

    def _command_position(self, d: Device, value: float) -> None:
        if not d.position_limits.contains(value):
            self.ignored.record(
                Ignored.OUT_OF_LIMITS.value,
                f"device {d.spec.letter}: position {value:.4f} {d.spec.unit} outside "
                f"[{d.position_limits.lo:.4f}, {d.position_limits.hi:.4f}]; ignored",
            )
            return
        self._set_mode(d, Mode.POSITION)
        d.position_target = value

    def _on_velocity(self, targets: list[Device], packet: Packet) -> list[Packet]:
        value = one_float(packet, "VELOCITY")
        for d in self._control(targets, "VELOCITY"):
            self._set_mode(d, Mode.VELOCITY)
            rate = d.spec.rate_limit
            d.velocity_target = max(min(d.velocity_limits.clamp(value), rate), -rate)
        return []

    def _on_current(self, targets: list[Device], packet: Packet) -> list[Packet]:
        value = one_float(packet, "CURRENT")
        for d in self._control(targets, "CURRENT"):
            self._set_mode(d, Mode.CURRENT)
            d.current_target = d.current_limits.clamp(value)
        return []

    def _on_limits(self, targets: list[Device], packet: Packet) -> list[Packet]:
        """Limits are refused (counted, changing nothing) when they are not [max, min], but no
        status flag is raised: a client sending them once at start-up has no link fault."""
        try:
            return self._set_limits(targets, packet)
        except Rejected as rejected:
            self._error(targets, rejected.reason, f"{packet!r}: {rejected}", flag=False)
            return []

    def _set_limits(self, targets: list[Device], packet: Packet) -> list[Packet]:
        pid = PacketID(int(packet.packet_id))
        if len(packet.data) == 16:
            raise Rejected(
                ErrorReason.LIMITS_16_BYTES,
                f"{pid.name} payload of 16 bytes (8 zero bytes then [min, max]?) refused: the "
                "payload is 8 bytes, [max, min] (protocol V1.12.1)",
            )
        if len(packet.data) != 8:
            raise Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"{pid.name} payload must be 8 bytes [max, min], got {len(packet.data)}",
            )
        hi, lo = packet.floats()
        if not (math.isfinite(hi) and math.isfinite(lo)):
            raise Rejected(ErrorReason.BAD_VALUE, f"{pid.name} [{hi}, {lo}] is not finite")
        if hi < lo:
            raise Rejected(
                ErrorReason.BAD_LIMITS,
                f"{pid.name} max {hi} < min {lo}: refused (the wire order is [max, min]; "
                "[min, max] is the order of protocol V1.9 and of some client libraries)",
            )
        if pid != PacketID.POSITION_LIMITS and not lo <= 0.0 <= hi:
            raise Rejected(
                ErrorReason.BAD_LIMITS, f"{pid.name} [{hi}, {lo}] must include 0 (max >= 0 >= min)"
            )
        for d in targets:
            if pid == PacketID.POSITION_LIMITS:
                d.position_limits = Limits(lo, hi)
            elif pid == PacketID.VELOCITY_LIMITS:
                d.velocity_limits = Limits(lo, hi)
            else:
                d.current_limits = Limits(lo, hi)
                self._apply_drive_limit(d)
        return []

    def _apply_drive_limit(self, d: Device) -> None:
        """The motor drive's symmetric limit follows the firmware's widest bound."""
        limit = max(abs(d.current_limits.lo), abs(d.current_limits.hi))
        if not d.is_actuator:
            return
        if d.is_jaw:
            self.arm.jaw_current_limit_mA = limit
        else:
            limits = self.arm.current_limits_mA.copy()
            limits[d.index] = limit
            self.arm.current_limits_mA = limits

    def _on_save(self, targets: list[Device], packet: Packet) -> list[Packet]:
        for d in targets:
            d.saved = Saved(
                (d.position_limits.lo, d.position_limits.hi),
                (d.velocity_limits.lo, d.velocity_limits.hi),
                (d.current_limits.lo, d.current_limits.hi),
                d.heartbeat_hz,
            )
        return []

    def _on_reset(self, targets: list[Device], packet: Packet) -> list[Packet]:
        for d in targets:
            saved = d.saved
            d.position_limits = Limits(*saved.position)
            d.velocity_limits = Limits(*saved.velocity)
            d.current_limits = Limits(*saved.current)
            self._apply_drive_limit(d)
            d.heartbeat_hz = saved.heartbeat_hz
            d.heartbeat_ids = ()  # not saved across power cycles
            d.status = d.injected = HardwareStatus.NONE
            d.last_error_time = -math.inf
            if d.is_actuator:
                self._set_mode(d, Mode.STANDBY)
                d.position_target = self._position(d)
        return []

    def _on_request(self, targets: list[Device], packet: Packet) -> list[Packet]:
        ids = packet.data
        if not 1 <= len(ids) <= MAX_REQUEST_IDS:
            raise Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"REQUEST takes 1 to {MAX_REQUEST_IDS} packet ids, got {len(ids)}",
            )
        if 0 in ids:
            # A pre-sized list appended to (`00 00 00 03 02 05`): real arms answer the real
            # ids and raise nothing, so padding is only counted, once per packet.
            self.ignored.record(
                Ignored.PADDING.value,
                f"REQUEST {list(ids)}: 0x00 is padding, not a packet id; skipped",
            )
        broadcast = int(packet.device_id) == DeviceID.BROADCAST
        out: list[Packet] = []
        for d in targets:
            for pid in ids:
                if pid == 0:
                    continue
                reply = self.report(int(d.spec.device_id), pid)
                if reply is not None:
                    out.append(reply)
                elif not broadcast or not self._reportable(pid):
                    self.ignored.record(
                        Ignored.UNSUPPORTED_REQUEST.value,
                        f"device {d.spec.letter} has no 0x{pid:02X} to report",
                    )
        if broadcast and self.config.half_duplex and len({p.device_id for p in out}) > 1:
            self.ignored.record(
                Ignored.COLLISION.value,
                f"broadcast REQUEST {list(ids)}: {len(out)} answers from several devices "
                "collided on the half-duplex line",
            )
            return []
        return out

    def _on_heartbeat_set(self, targets: list[Device], packet: Packet) -> list[Packet]:
        if len(packet.data) > HEARTBEAT_SLOTS:
            raise Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"HEARTBEAT_SET takes at most {HEARTBEAT_SLOTS} ids, got {len(packet.data)}",
            )
        ids = tuple(pid for pid in packet.data if pid)
        if bytes(ids) + bytes(len(packet.data) - len(ids)) != bytes(packet.data):
            # Zeros are the slots' filler; one before an id is a client's pre-sized list.
            self.ignored.record(
                Ignored.PADDING.value,
                f"HEARTBEAT_SET {list(packet.data)}: zeros before ids skipped",
            )
        unknown = [pid for pid in ids if not self._reportable(pid)]
        if unknown:
            self.ignored.record(
                Ignored.UNSUPPORTED_REQUEST.value,
                f"HEARTBEAT_SET ids {[f'0x{p:02X}' for p in unknown]} cannot "
                "be reported; they will be skipped",
            )
        for d in targets:
            d.heartbeat_ids = ids
            d.heartbeat_phase = 0.0
        return []

    def _on_heartbeat_frequency(self, targets: list[Device], packet: Packet) -> list[Packet]:
        if len(packet.data) != 1:
            raise Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"HEARTBEAT_FREQUENCY payload must be 1 byte, got {len(packet.data)}",
            )
        for d in targets:
            d.heartbeat_hz = packet.data[0]
            d.heartbeat_phase = 0.0
        return []


def one_float(packet: Packet, name: str) -> float:
    if len(packet.data) != 4:
        raise Rejected(
            ErrorReason.BAD_PAYLOAD,
            f"{name} payload must be one float32 (4 bytes), got {len(packet.data)}",
        )
    value = packet.floats()[0]
    if not math.isfinite(value):
        raise Rejected(ErrorReason.BAD_VALUE, f"{name} value {value} is not finite")
    return value
