"""The five devices of the emulated firmware: what each one is (`DeviceSpec`, the Alpha 5's
`ALPHA5_DEVICES`), how the firmware is configured (`FirmwareConfig`), what each keeps while it
runs (`Device`, its `Limits` and what SAVE stored), and the reasons a packet is refused or
ignored (`ErrorReason`, `Ignored`). Plain data: the behaviour is `Firmware`'s
(`reach_sim_bridge.emulator.firmware`) and its packet handlers'
(`reach_sim_bridge.emulator.handlers`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from protocol import DeviceID, HardwareStatus, Mode, alpha5
from reach_sim_bridge.emulator.derating import CurrentDerating
from reach_sim_bridge.emulator.faults import Leak, StuckReading
from reach_sim_bridge.emulator.monitor import MonitorConfig
from reach_sim_bridge.model.sensors import SensorNoise

#: Modes whose loop servoes to `position_target`.
HOLDING_MODES = frozenset({Mode.POSITION, Mode.POSITION_HOLD, Mode.STANDBY, Mode.DISABLE})


class ErrorReason(str, Enum):
    """Why a well-framed packet was rejected (keys of `Firmware.errors`)."""

    BAD_PAYLOAD = "bad_payload"  # wrong payload size for the packet (e.g. an empty MODE)
    BAD_VALUE = "bad_value"  # NaN or infinite float
    UNKNOWN_MODE = "unknown_mode"
    BAD_LIMITS = "bad_limits"  # max < min, or a velocity/current range excluding 0
    LIMITS_16_BYTES = "limits_16_bytes"  # 8 zero bytes then [min, max]: a client library's form
    UNKNOWN_PACKET = "unknown_packet"  # a packet id this firmware does not implement


class Ignored(str, Enum):
    """Valid packets the arm deliberately does nothing with (keys of `Firmware.ignored`)."""

    OUT_OF_LIMITS = "position_out_of_limits"
    LOCKED = "control_while_disabled"  # control packet in DISABLE or PASSIVE
    READ_ONLY = "read_only"  # e.g. a host sending TEMPERATURE
    UNSUPPORTED_REQUEST = "unsupported_request"  # REQUEST/HEARTBEAT of an id we cannot report
    OTHER_DEVICE = "other_device"  # addressed to a device this arm does not have
    UNIMPLEMENTED_MODE = "unimplemented_mode"  # a mode value V1.12.1 does not document
    UNREACHABLE = "unreachable_pose"  # KM_END_POS the arm cannot reach: no motion
    NOT_BASE = "not_the_base_device"  # KM_END_POS/KM_END_VEL to a device other than E
    END_VELOCITY_STOPPED = "end_velocity_at_joint_limit"  # a Cartesian move ran into a limit
    COLLISION = "broadcast_collision"  # half duplex: several devices answered at once
    PADDING = "request_padding"  # 0x00 slots in a REQUEST (or misplaced in a HEARTBEAT_SET)


@dataclass(frozen=True)
class LoopGains:
    """Cascade gains; currents in mA, positions in the device's unit (rad or mm)."""

    position: float  # 1/s: position error -> velocity demand
    velocity_p: float  # mA per unit/s
    velocity_i: float  # mA per unit (integral of the velocity error)


@dataclass(frozen=True)
class DeviceSpec:
    """What differs between the five devices' firmware."""

    device_id: DeviceID
    letter: str
    unit: str  # "rad" or "mm"
    rate_limit: float  # firmware limit in position/velocity modes (unit/s)
    gains: LoopGains
    serial_number: float


def _rate(device: DeviceID) -> float:
    """The factory velocity limit: the firmware's rate limit in position and velocity modes."""
    return alpha5.FACTORY_VELOCITY_LIMITS[device][1]


# Gains tuned against Alpha5Arm (tools/ and tests/test_sim_firmware.py check the result):
# E/D/C have ~0.13 kg m^2 reflected inertia and 20.2 N m/A; B 0.008 kg m^2 and 7.1 N m/A;
# the jaw ~725 kg reflected mass and 914 N/A (units mm, so mA per mm).
ALPHA5_DEVICES: tuple[DeviceSpec, ...] = (
    DeviceSpec(DeviceID.A, "A", "mm", _rate(DeviceID.A), LoopGains(3.0, 20.0, 150.0), 4101.0),
    DeviceSpec(DeviceID.B, "B", "rad", _rate(DeviceID.B), LoopGains(5.0, 100.0, 2000.0), 4102.0),
    DeviceSpec(DeviceID.C, "C", "rad", _rate(DeviceID.C), LoopGains(5.0, 1e3, 2e4), 4103.0),
    DeviceSpec(DeviceID.D, "D", "rad", _rate(DeviceID.D), LoopGains(5.0, 1e3, 2e4), 4104.0),
    DeviceSpec(DeviceID.E, "E", "rad", _rate(DeviceID.E), LoopGains(5.0, 1e3, 2e4), 4105.0),
)


@dataclass(frozen=True)
class FirmwareConfig:
    """Identity and environment the firmware reports, and its error-reporting timing."""

    devices: tuple[DeviceSpec, ...] = ALPHA5_DEVICES
    software_version: tuple[int, int, int] = (0, 1, 0)  # the emulator's own version
    model_number: float = 5005.0  # emulator's own number: the vendor's are not published
    temperature_c: float = 20.0  # the water's: each housing starts at it (monitor model)
    humidity_pct: float = 10.0  # in each housing at power-on
    monitor: MonitorConfig = MonitorConfig()  # climate and supply model, factory levels
    leaks: tuple[Leak, ...] = ()  # housings taking in water from the start
    stuck: tuple[StuckReading, ...] = ()  # readings that stop changing (fault injection)
    # Thermal derating of each device's current limit (assumed constants; None: off).
    derating: CurrentDerating | None = CurrentDerating()
    # RS-485: one shared wire. A broadcast REQUEST that more than one device answers
    # collides on it; the host gets none of the answers (counted as `broadcast_collision`).
    half_duplex: bool = False
    status_period_s: float = 1.0  # HARDWARE_STATUS while an error flag is set
    error_hold_s: float = 5.0  # link error flags clear after this long without errors
    sensor_noise: SensorNoise | None = None
    seed: int | None = None  # noise generator


@dataclass
class Limits:
    """Stored as (lo, hi); the wire order is [max, min]."""

    lo: float
    hi: float

    def contains(self, value: float) -> bool:
        return self.lo <= value <= self.hi

    def clamp(self, value: float) -> float:
        return self.hi if value > self.hi else (self.lo if value < self.lo else value)


@dataclass
class Saved:
    """What SAVE stores and RESET restores."""

    position: tuple[float, float]
    velocity: tuple[float, float]
    current: tuple[float, float]
    heartbeat_hz: int


@dataclass
class Device:
    """One device's live firmware state."""

    spec: DeviceSpec
    index: int  # 0..3 in E D C B for the joints, -1 for the jaw
    continuous: bool
    position_limits: Limits
    velocity_limits: Limits
    current_limits: Limits
    saved: Saved
    mode: Mode = Mode.STANDBY
    position_target: float = 0.0
    velocity_target: float = 0.0
    current_target: float = 0.0
    integral: float = 0.0  # of the velocity error, in units (so i = ki * integral)
    applied_mA: float = 0.0
    status: HardwareStatus = HardwareStatus.NONE
    injected: HardwareStatus = HardwareStatus.NONE  # by inject_fault: the monitor keeps these
    last_error_time: float = -math.inf
    status_phase: float = 0.0
    heartbeat_ids: tuple[int, ...] = ()
    heartbeat_hz: int = 0
    heartbeat_phase: float = 0.0
    slot: int = 0  # index in the firmware's device list (and the monitor's)
    peak_mA: float = 0.0  # the factory current limit, the derating's full limit
    thermal_load: float = 0.0  # the derating's I^2 t estimate (1: the rated rise)
    ceiling_mA: float = math.inf  # the derated current limit, either sign (inf: none)
