"""The hardware status flags each device last reported, and which of them must stop a joint.

HARDWARE_STATUS is four bytes A B C D (docs/protocol.md section 8). Every named flag has a
verdict here (`FLAG_POLICY`): a *blocking* flag says the joint cannot be driven safely, so
the gate (`reach_driver.gate`) refuses motion commands to that joint (POSITION, VELOCITY,
CURRENT, relative moves, a MODE that drives it) with `ArmFaultError`, and the control loop
stops; a safe mode (STANDBY, DISABLE, ZERO_VELOCITY, POSITION_HOLD) always goes out. An
*informational* flag is shown (info, monitor, events) and never refuses anything.

The rule behind the verdicts: a flag blocks when it says the joint's feedback is not to be
trusted (encoder, calibration, position report), its drive may fail or be damaged (motor,
driver, temperature, supply below the rated range, water in the housing), or commands may not
reach the right joint (device id conflicts, the internal bus, firmware). It is informational
when it is a reminder or a setting that says nothing about this motion (service due, read
protection), when clearing it needs the joint to move (jaw zeroing), or when it only reports
noise on the host's line, which the arm clears by itself (serial and CRC errors).

A bit without a name (reserved in the document) blocks: its meaning is not known, and a
flag not known to be harmless is treated like a packet not known to be harmless by the gate.
"""

from __future__ import annotations

import threading

from protocol import HardwareStatus, Packet, ProtocolError
from reach_driver.link import EventKind
from reach_driver.state import joint_name

_HS = HardwareStatus

#: Flags that only say the arm saw noise on the line; they clear by themselves.
LINK_ERROR_FLAGS = _HS.SERIAL_ERROR | _HS.CRC_ERROR

_ENCODER = "the joint's position feedback is not to be trusted, so no target can be held"
_DRIVE = "the motor or its driver may fail or be damaged if driven"
_LEAK = "water or gas in the housing: the electronics may short; recover the arm"

#: flag -> (blocks the joint, why). Every named flag of `HardwareStatus` is here
#: (tests/test_driver_diagnostics.py checks it).
FLAG_POLICY: dict[HardwareStatus, tuple[bool, str]] = {
    # byte A
    _HS.FLASH_READ_FAILED: (True, "settings (limits, calibration) may not have loaded"),
    _HS.OVER_HUMIDITY: (True, _LEAK),
    _HS.OVER_TEMPERATURE: (True, "the housing is too hot: more current heats it further"),
    _HS.SERIAL_ERROR: (False, "noise on the host's line; the arm clears it by itself"),
    _HS.CRC_ERROR: (False, "noise on the host's line; the arm clears it by itself"),
    _HS.MOTOR_DRIVER_FAULT: (True, _DRIVE),
    _HS.ENCODER_POSITION_ERROR: (True, _ENCODER),
    _HS.ENCODER_NOT_DETECTED: (True, _ENCODER),
    # byte B
    _HS.AXIS_CONFLICT: (True, "two devices claim one axis: commands may move the wrong one"),
    _HS.MOTOR_NOT_CONNECTED: (True, "no motor to drive: the joint would not follow"),
    _HS.MOTOR_OVER_CURRENT: (True, _DRIVE),
    _HS.INNER_ENCODER_ERROR: (True, _ENCODER),
    _HS.DEVICE_ID_CONFLICT: (True, "two devices answer one id: a command reaches both"),
    _HS.OVER_PRESSURE: (True, _LEAK),
    _HS.DRIVER_OVER_CURRENT_UNDER_VOLTAGE: (True, _DRIVE),
    _HS.DRIVER_OVER_TEMPERATURE: (True, _DRIVE),
    # byte C
    _HS.JAW_ZERO_REQUIRED: (
        False,
        "the jaw needs zeroing, which is done by driving it to its stop; the current limit "
        "bounds its force meanwhile",
    ),
    _HS.JOINT_SERVICE_DUE: (False, "a maintenance reminder; the joint works as before"),
    _HS.READ_PROTECTION_ENABLED: (
        False,
        "a firmware setting (flash read-out protection), nothing about motion",
    ),
    _HS.ENCODER_FAULT: (True, _ENCODER + " (backlash)"),
    # byte D
    _HS.ENCODER_POSITION_INVALID: (True, _ENCODER + " (factory calibration lost)"),
    _HS.LOW_SUPPLY_VOLTAGE: (
        True,
        "the supply is below the rated 18..30 V: the motor drivers may cut out mid-move and "
        "drop a load; the sag comes from the motors' own current, so stopping is what "
        "brings it back",
    ),
    _HS.INVALID_FIRMWARE: (True, "the firmware's behaviour is not known"),
    _HS.CAN_BUS_ERROR: (True, "the arm's internal bus may lose commands and feedback"),
    _HS.POSITION_REPORT_NOT_RECEIVED: (True, "positions are missing: " + _ENCODER),
}

#: Everything that blocks, named.
BLOCKING_FLAGS = HardwareStatus.NONE
for _flag, (_blocks, _why) in FLAG_POLICY.items():
    if _blocks:
        BLOCKING_FLAGS |= _flag
#: Named flags that never block.
INFORMATIONAL_FLAGS = HardwareStatus.NONE
for _flag, (_blocks, _why) in FLAG_POLICY.items():
    if not _blocks:
        INFORMATIONAL_FLAGS |= _flag

_BYTES = ("A", "B", "C", "D")


def blocking_flags(flags: HardwareStatus) -> HardwareStatus:
    """The flags of `flags` that block the joint: the blocking named ones and any bit
    without a name."""
    return HardwareStatus(int(flags) & ~int(INFORMATIONAL_FLAGS))


def flag_labels(flags: HardwareStatus) -> list[str]:
    """Names of the set flags, in bit order from byte A's top bit, an unnamed bit as
    'bit 0x..' of its byte."""
    out = []
    for bit in range(31, -1, -1):
        value = 1 << bit
        if int(flags) & value:
            try:
                name = HardwareStatus(value).name
            except ValueError:
                name = None
            out.append(name or f"bit 0x{value >> (8 * (bit // 8)):02X}")
    return out


def status_bytes(flags: HardwareStatus) -> dict[str, list[str]]:
    """The set flags by byte: {'A': [...], 'B': [...], 'C': [...], 'D': [...]}."""
    out: dict[str, list[str]] = {}
    for i, letter in enumerate(_BYTES):
        shift = 8 * (3 - i)
        out[letter] = flag_labels(HardwareStatus(int(flags) & (0xFF << shift)))
    return out


def why_blocking(flags: HardwareStatus) -> str:
    """'ENCODER_FAULT (why it blocks); ...' for each blocking flag of `flags`."""
    parts = []
    for label in flag_labels(blocking_flags(flags)):
        member = HardwareStatus.__members__.get(label)
        policy = FLAG_POLICY.get(member) if member is not None else None
        parts.append(f"{label} ({policy[1] if policy else 'meaning not documented'})")
    return "; ".join(parts)


class FaultFlags:
    """Fed HARDWARE_STATUS packets by the reader thread; read from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._flags: dict[int, HardwareStatus] = {}

    def note(self, packet: Packet) -> tuple[EventKind, str, int] | None:
        """Record a status packet; the event to report when a device's flags changed."""
        try:
            flags = HardwareStatus.from_bytes(packet.data)
        except ProtocolError:
            return None
        dev = int(packet.device_id)
        with self._lock:
            before = self._flags.get(dev, HardwareStatus.NONE)
            if flags == before:
                return None
            self._flags[dev] = flags
        if flags:
            names = ", ".join(flag_labels(flags))
            serious = blocking_flags(flags)
            verdict = f" (blocks the joint: {', '.join(flag_labels(serious))})" if serious else ""
            return EventKind.FAULT, f"{joint_name(dev)} reports {names}{verdict}", dev
        return EventKind.FAULT_CLEARED, f"{joint_name(dev)} status clear", dev

    def flags(self, device: int) -> HardwareStatus:
        """The flags `device` last reported (NONE if it never did)."""
        with self._lock:
            return self._flags.get(int(device), HardwareStatus.NONE)

    def blocking(self) -> dict[int, list[str]]:
        """Flags, by device, that say a joint must not be driven (`FLAG_POLICY`)."""
        with self._lock:
            faults = dict(self._flags)
        out: dict[int, list[str]] = {}
        for dev, flags in faults.items():
            serious = blocking_flags(flags)
            if serious:
                out[dev] = flag_labels(serious)
        return out
