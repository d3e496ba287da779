"""The live picture of the arm the reader thread keeps: every value with its arrival time.

Snapshots are immutable, so the control loop, the monitor and the watchdog can each hold one
while the reader thread moves on.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np

from protocol import DeviceID, HardwareStatus, Mode, Packet, PacketID, ProtocolError

T = TypeVar("T")

#: The four controlled joints, in the project's fixed order (docs/architecture.md).
JOINTS: tuple[DeviceID, ...] = (DeviceID.E, DeviceID.D, DeviceID.C, DeviceID.B)
JAW = DeviceID.A
ALL_DEVICES: tuple[DeviceID, ...] = (*JOINTS, JAW)

#: Packets whose value the state table keeps (replies and heartbeats alike).
TRACKED: frozenset[int] = frozenset(
    {
        PacketID.MODE,
        PacketID.VELOCITY,
        PacketID.POSITION,
        PacketID.CURRENT,
        PacketID.POSITION_LIMITS,
        PacketID.VELOCITY_LIMITS,
        PacketID.CURRENT_LIMITS,
        PacketID.HARDWARE_STATUS,
        PacketID.SOFTWARE_VERSION,
        PacketID.SERIAL_NUMBER,
        PacketID.MODEL_NUMBER,
        PacketID.TEMPERATURE,
        PacketID.VOLTAGE,
        PacketID.HEARTBEAT_FREQUENCY,
    }
)


def joint_name(device: int) -> str:
    """'E (0x05)' for messages people read."""
    try:
        return f"{DeviceID(device).name} (0x{device:02X})"
    except ValueError:
        return f"0x{device:02X}"


@dataclass(frozen=True)
class Reading(Generic[T]):
    """A value and the host's monotonic time its packet arrived."""

    value: T
    t: float

    def age(self, now: float) -> float:
        return now - self.t


Range = tuple[float, float]  # (minimum, maximum)


@dataclass(frozen=True)
class JointState:
    """Everything known about one device; None until the arm has reported it."""

    device: int
    position: Reading[float] | None = None
    velocity: Reading[float] | None = None
    current: Reading[float] | None = None
    mode: Reading[Mode | int] | None = None
    position_limits: Reading[Range] | None = None
    velocity_limits: Reading[Range] | None = None
    current_limits: Reading[Range] | None = None
    status: Reading[HardwareStatus] | None = None
    software_version: Reading[str] | None = None
    serial_number: Reading[float] | None = None
    model_number: Reading[float] | None = None
    temperature: Reading[float] | None = None
    voltage: Reading[float] | None = None
    heartbeat_hz: Reading[int] | None = None

    @property
    def name(self) -> str:
        return joint_name(self.device)

    @property
    def fault_names(self) -> list[str]:
        return self.status.value.flag_names() if self.status is not None else []


_FIELD_OF: dict[int, str] = {
    PacketID.MODE: "mode",
    PacketID.VELOCITY: "velocity",
    PacketID.POSITION: "position",
    PacketID.CURRENT: "current",
    PacketID.POSITION_LIMITS: "position_limits",
    PacketID.VELOCITY_LIMITS: "velocity_limits",
    PacketID.CURRENT_LIMITS: "current_limits",
    PacketID.HARDWARE_STATUS: "status",
    PacketID.SOFTWARE_VERSION: "software_version",
    PacketID.SERIAL_NUMBER: "serial_number",
    PacketID.MODEL_NUMBER: "model_number",
    PacketID.TEMPERATURE: "temperature",
    PacketID.VOLTAGE: "voltage",
    PacketID.HEARTBEAT_FREQUENCY: "heartbeat_hz",
}


def packet_value(packet: Packet) -> object:
    """The typed value a tracked packet carries; `ProtocolError` if its payload is malformed."""
    pid = packet.packet_id
    if pid in (
        PacketID.POSITION,
        PacketID.VELOCITY,
        PacketID.CURRENT,
        PacketID.SERIAL_NUMBER,
        PacketID.MODEL_NUMBER,
        PacketID.TEMPERATURE,
        PacketID.VOLTAGE,
    ):
        return packet.as_float()
    if pid == PacketID.MODE:
        raw = packet.as_u8()
        return Mode(raw) if raw in Mode._value2member_map_ else raw
    if pid == PacketID.HEARTBEAT_FREQUENCY:
        return packet.as_u8()
    if pid in (PacketID.POSITION_LIMITS, PacketID.VELOCITY_LIMITS, PacketID.CURRENT_LIMITS):
        values = packet.floats()
        if len(values) != 2:
            raise ProtocolError(f"limits payload holds {len(values)} floats, expected 2")
        # [max, min] in protocol 1.12, [min, max] in 1.9: sorting reads both correctly.
        lo, hi = sorted(values)
        return (lo, hi)
    if pid == PacketID.HARDWARE_STATUS:
        return HardwareStatus.from_bytes(packet.data)
    if pid == PacketID.SOFTWARE_VERSION:
        if len(packet.data) != 3:
            raise ProtocolError(f"SOFTWARE_VERSION holds {len(packet.data)} bytes, expected 3")
        return ".".join(str(b) for b in packet.data)
    raise ProtocolError(f"packet id 0x{int(pid):02X} is not tracked")


@dataclass(frozen=True)
class ArmState:
    """A snapshot of every device; arrays are in joint order E D C B (NaN when unknown)."""

    joints: Mapping[int, JointState]
    taken_at: float

    def joint(self, device: int) -> JointState:
        return self.joints.get(device) or JointState(device)

    def _array(self, name: str) -> np.ndarray:
        out = np.full(len(JOINTS), np.nan)
        for i, dev in enumerate(JOINTS):
            reading = getattr(self.joint(dev), name)
            if reading is not None:
                out[i] = reading.value
        return out

    @property
    def q(self) -> np.ndarray:
        return self._array("position")

    @property
    def qdot(self) -> np.ndarray:
        return self._array("velocity")

    @property
    def current(self) -> np.ndarray:
        return self._array("current")

    @property
    def jaw_mm(self) -> float:
        reading = self.joint(JAW).position
        return float("nan") if reading is None else reading.value

    @property
    def faults(self) -> dict[int, list[str]]:
        """Devices reporting any hardware status flag, with the flag names."""
        return {dev: js.fault_names for dev, js in self.joints.items() if js.fault_names}


@dataclass
class StateTable:
    """Thread-safe store the reader thread updates; counts updates per (device, packet)."""

    _joints: dict[int, JointState] = field(default_factory=dict)
    counts: dict[tuple[int, int], int] = field(default_factory=dict)
    bad_payloads: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def update(self, packet: Packet, t: float) -> bool:
        """Record a packet's value; False (and counted) if its payload is malformed."""
        name = _FIELD_OF.get(packet.packet_id)
        if name is None:
            return False
        try:
            value = packet_value(packet)
        except ProtocolError:
            self.bad_payloads += 1
            return False
        dev = int(packet.device_id)
        with self._lock:
            old = self._joints.get(dev) or JointState(dev)
            self._joints[dev] = _replace(old, name, Reading(value, t))
            key = (dev, int(packet.packet_id))
            self.counts[key] = self.counts.get(key, 0) + 1
        return True

    def count_snapshot(self) -> dict[tuple[int, int], int]:
        """Packets received per (device, packet id) so far (for update rates)."""
        with self._lock:
            return dict(self.counts)

    def get(self, device: int) -> JointState:
        with self._lock:
            return self._joints.get(device) or JointState(device)

    def snapshot(self, now: float) -> ArmState:
        with self._lock:
            return ArmState(dict(self._joints), now)

    def forget(self, device: int, packet_id: int) -> None:
        """Drop one value (e.g. limits before re-reading them, so stale ones cannot answer)."""
        name = _FIELD_OF.get(packet_id)
        if name is None:
            return
        with self._lock:
            old = self._joints.get(device)
            if old is not None:
                self._joints[device] = _replace(old, name, None)


def _replace(state: JointState, name: str, reading: Reading[Any] | None) -> JointState:
    changes: dict[str, Any] = {name: reading}
    return dataclasses.replace(state, **changes)
