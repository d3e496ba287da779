"""The live picture of the arm the reader thread keeps: every value with its arrival time.

Snapshots are immutable, so the control loop, the monitor and the watchdog can each hold one
while the reader thread moves on.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, NamedTuple, TypeVar

import numpy as np

from protocol import DeviceID, HardwareStatus, Mode, Packet, PacketID, ProtocolError
from protocol.models import ALPHA5, ArmModel, Range

T = TypeVar("T")


def joint_name(device: int) -> str:
    """'E (0x05)' for messages people read."""
    try:
        return f"{DeviceID(device).name} (0x{device:02X})"
    except ValueError:
        return f"0x{device:02X}"


def packet_names(ids: Iterable[int]) -> str:
    """'POSITION/VELOCITY' (hex for ids the protocol does not name) for messages."""
    names = []
    for p in ids:
        try:
            names.append(PacketID(p).name)
        except ValueError:
            names.append(f"0x{p:02X}")
    return "/".join(names)


@dataclass(frozen=True)
class Reading(Generic[T]):
    """A value and the host's monotonic time its packet arrived."""

    value: T
    t: float

    def age(self, now: float) -> float:
        return now - self.t


# Payload parsers of the tracked packets.


def _float(packet: Packet) -> float:
    return packet.as_float()


def _mode(packet: Packet) -> Mode | int:
    raw = packet.as_u8()
    return Mode(raw) if raw in Mode._value2member_map_ else raw


def _u8(packet: Packet) -> int:
    return packet.as_u8()


def _limits(packet: Packet) -> Range:
    values = packet.floats()
    if len(values) != 2:
        raise ProtocolError(f"limits payload holds {len(values)} floats, expected 2")
    # [max, min] in protocol 1.12, [min, max] in 1.9: sorting reads both correctly.
    lo, hi = sorted(values)
    return (lo, hi)


class Climate(NamedTuple):
    """FACTORY_CLIMATE (0x28): the housing's climate when it was sealed at assembly."""

    temperature_c: float
    pressure_bar: float
    humidity_pct: float


def _climate(packet: Packet) -> Climate:
    values = packet.floats()
    if len(values) != 3:
        raise ProtocolError(f"FACTORY_CLIMATE holds {len(values)} floats, expected 3")
    return Climate(*values)


def _status(packet: Packet) -> HardwareStatus:
    return HardwareStatus.from_bytes(packet.data)


def _version(packet: Packet) -> str:
    if len(packet.data) != 3:
        raise ProtocolError(f"SOFTWARE_VERSION holds {len(packet.data)} bytes, expected 3")
    return ".".join(str(b) for b in packet.data)


def _tracked(packet_id: PacketID, parse: Callable[[Packet], object]) -> Any:
    """A `JointState` field the state table fills from `packet_id`, parsed by `parse` (which
    raises `ProtocolError` on a malformed payload)."""
    return field(default=None, metadata={"packet_id": packet_id, "parse": parse})


@dataclass(frozen=True)
class JointState:
    """Everything known about one device; None until the arm has reported it.

    Each field is also the state table's row for its packet: tracking a new value is one
    line here.
    """

    device: int
    position: Reading[float] | None = _tracked(PacketID.POSITION, _float)
    velocity: Reading[float] | None = _tracked(PacketID.VELOCITY, _float)
    current: Reading[float] | None = _tracked(PacketID.CURRENT, _float)
    mode: Reading[Mode | int] | None = _tracked(PacketID.MODE, _mode)
    position_limits: Reading[Range] | None = _tracked(PacketID.POSITION_LIMITS, _limits)
    velocity_limits: Reading[Range] | None = _tracked(PacketID.VELOCITY_LIMITS, _limits)
    current_limits: Reading[Range] | None = _tracked(PacketID.CURRENT_LIMITS, _limits)
    status: Reading[HardwareStatus] | None = _tracked(PacketID.HARDWARE_STATUS, _status)
    software_version: Reading[str] | None = _tracked(PacketID.SOFTWARE_VERSION, _version)
    serial_number: Reading[float] | None = _tracked(PacketID.SERIAL_NUMBER, _float)
    model_number: Reading[float] | None = _tracked(PacketID.MODEL_NUMBER, _float)
    # The "Monitor" packets (docs/protocol.md section 3a), each from the device's own housing.
    #: INTERNAL_TEMPERATURE (0x66), degC.
    temperature: Reading[float] | None = _tracked(PacketID.INTERNAL_TEMPERATURE, _float)
    #: INTERNAL_HUMIDITY (0x65), % relative humidity.
    humidity: Reading[float] | None = _tracked(PacketID.INTERNAL_HUMIDITY, _float)
    #: INTERNAL_PRESSURE (0x67), bar, as protocol V1.12.1 documents it. The newest vendor SDK
    #: reuses 0x67 as DEVICE_TYPE (and reports pressure as 0x6E): firmware that follows it
    #: answers a type code here, which would read as a nonsense pressure. The virtual arm
    #: answers 0x67 and 0x6E with the same pressure.
    internal_pressure: Reading[float] | None = _tracked(PacketID.INTERNAL_PRESSURE, _float)
    #: PRESSURE (0x6E), bar: where the newest vendor SDK reports the pressure. Kept apart from
    #: 0x67 so that firmware answering only one of them, or 0x67 as a type code, shows as such.
    pressure: Reading[float] | None = _tracked(PacketID.PRESSURE, _float)
    #: FACTORY_CLIMATE (0x28): [temperature degC, pressure bar, humidity %] at assembly; a
    #: leak shows as live humidity and pressure above these.
    factory_climate: Reading[Climate] | None = _tracked(PacketID.FACTORY_CLIMATE, _climate)
    #: VOLTAGE (0x90), V: the supply as the device sees it.
    voltage: Reading[float] | None = _tracked(PacketID.VOLTAGE, _float)
    heartbeat_hz: Reading[int] | None = _tracked(PacketID.HEARTBEAT_FREQUENCY, _u8)

    @property
    def name(self) -> str:
        return joint_name(self.device)

    @property
    def fault_names(self) -> list[str]:
        return self.status.value.flag_names() if self.status is not None else []


class MonitorReading(NamedTuple):
    """One Monitor reading as people and files see it: `info`/`monitor` columns, `--json`
    keys and recordings' entities all come from `MONITOR_READINGS`."""

    field: str  # the JointState field holding it
    key: str  # its name with its unit: the JSON key and the recording's entity
    column: str  # a short title with the unit, for tables
    title: str  # a long title with the unit, for a recording's view
    digits: int  # decimals shown in tables


#: The Monitor readings (docs/protocol.md 3a) in the order every table and file shows them.
MONITOR_READINGS: tuple[MonitorReading, ...] = (
    MonitorReading("voltage", "voltage_v", "supply V", "supply voltage (V)", 2),
    MonitorReading("temperature", "temperature_c", "temp degC", "internal temperature (degC)", 1),
    MonitorReading("humidity", "humidity_pct", "RH %", "internal relative humidity (%)", 1),
    MonitorReading(
        "internal_pressure",
        "internal_pressure_bar",
        "0x67 bar",
        "internal pressure, 0x67 as V1.12.1 has it (bar)",
        3,
    ),
    MonitorReading(
        "pressure", "pressure_0x6e_bar", "0x6E bar", "pressure, 0x6E as newer SDKs have it (bar)", 3
    ),
)


@dataclass(frozen=True)
class _Tracked:
    field: str  # the JointState field holding the value
    parse: Callable[[Packet], object]


#: Packet id -> where its value goes, read off JointState's fields.
_TRACKED: dict[int, _Tracked] = {
    int(f.metadata["packet_id"]): _Tracked(f.name, f.metadata["parse"])
    for f in dataclasses.fields(JointState)
    if "packet_id" in f.metadata
}


def packet_value(packet: Packet) -> object:
    """The typed value a tracked packet carries; `ProtocolError` if its payload is malformed."""
    tracked = _TRACKED.get(packet.packet_id)
    if tracked is None:
        raise ProtocolError(f"packet id 0x{int(packet.packet_id):02X} is not tracked")
    return tracked.parse(packet)


@dataclass(frozen=True)
class ArmState:
    """A snapshot of every device; arrays are in the model's joint order (E D C B on the
    Alpha 5; NaN when unknown)."""

    joints: Mapping[int, JointState]
    taken_at: float
    model: ArmModel = ALPHA5

    def joint(self, device: int) -> JointState:
        return self.joints.get(device) or JointState(device)

    def _array(self, name: str) -> np.ndarray:
        joints = self.model.joints
        out = np.full(len(joints), np.nan)
        for i, dev in enumerate(joints):
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
        reading = self.joint(self.model.jaw).position
        return float("nan") if reading is None else reading.value

    @property
    def faults(self) -> dict[int, list[str]]:
        """Devices reporting any hardware status flag, with the flag names."""
        return {dev: js.fault_names for dev, js in self.joints.items() if js.fault_names}


@dataclass
class StateTable:
    """Thread-safe store the reader thread updates; counts updates per (device, packet).
    Its snapshots read the arrays in `model`'s joint order."""

    model: ArmModel = ALPHA5
    _joints: dict[int, JointState] = field(default_factory=dict)
    counts: dict[tuple[int, int], int] = field(default_factory=dict)
    bad_payloads: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def update(self, packet: Packet, t: float) -> bool:
        """Record a packet's value; False (and counted) if its payload is malformed."""
        tracked = _TRACKED.get(packet.packet_id)
        if tracked is None:
            return False
        try:
            value = tracked.parse(packet)
        except ProtocolError:
            self.bad_payloads += 1
            return False
        dev = int(packet.device_id)
        with self._lock:
            old = self._joints.get(dev) or JointState(dev)
            self._joints[dev] = _replace(old, tracked.field, Reading(value, t))
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
            return ArmState(dict(self._joints), now, self.model)

    def clear(self) -> None:
        """Forget everything (a different arm answers: none of it describes this one)."""
        with self._lock:
            self._joints.clear()

    def forget(self, device: int, packet_id: int) -> None:
        """Drop one value (e.g. limits before re-reading them, so stale ones cannot answer)."""
        tracked = _TRACKED.get(packet_id)
        if tracked is None:
            return
        with self._lock:
            old = self._joints.get(device)
            if old is not None:
                self._joints[device] = _replace(old, tracked.field, None)


def _replace(state: JointState, name: str, reading: Reading[Any] | None) -> JointState:
    changes: dict[str, Any] = {name: reading}
    return dataclasses.replace(state, **changes)
