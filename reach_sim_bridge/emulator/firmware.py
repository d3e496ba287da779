"""Emulation of the Alpha 5's joint firmware on top of the MuJoCo arm.

Each device (A jaws 0x01 .. E base 0x05) keeps the state the real firmware keeps: mode,
setpoints, [max, min] limits, identity, hardware status flags and a heartbeat. Its control
loops run once per physics step in sim time, cascaded like the arm's: position error ->
velocity demand (clamped to the firmware rate limit and the velocity limits) -> PI velocity
loop -> current (clamped to the current limits) -> motor. Current mode goes straight to the
motor. The integral term of the velocity loop is what holds D and C against gravity.

Modes: STANDBY and DISABLE hold the joint where it was ("the device will not move"; the
real 1754:1 gearbox barely back-drives, the model's soft friction creeps, so holding is
emulated with the position loop). PASSIVE puts no current through the motor. Control
packets switch STANDBY and the active modes implicitly; DISABLE and PASSIVE ignore them.

Bad input never stops the firmware: each bad packet is counted, logged (rate-limited) and
raises the SERIAL_ERROR (or CRC_ERROR) flag, which is reported with HARDWARE_STATUS at 1 Hz
until `error_hold_s` passes without a new error (or a RESET). Padding (0x00 in a REQUEST) is
counted, never an error: real clients send it at 100 Hz and real arms answer the rest.

Every device also reports its housing's climate and the supply voltage (the "Monitor"
packets) from `reach_sim_bridge.emulator.monitor`, whose OVER_TEMPERATURE, OVER_HUMIDITY,
OVER_PRESSURE and LOW_SUPPLY_VOLTAGE flags are conditions: they hold while the reading is
past its level. Any flag set is reported with HARDWARE_STATUS at 1 Hz.
"""

from __future__ import annotations

import logging
import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum

import numpy as np

from protocol import (
    DecodeError,
    DecodeReason,
    DeviceID,
    HardwareStatus,
    Mode,
    Packet,
    PacketID,
    alpha5,
)
from protocol.alpha5 import JOINT_LETTERS
from protocol.commands import HEARTBEAT_SLOTS, MAX_REQUEST_IDS
from protocol.ids import UNDOCUMENTED_MODES
from protocol.payload import pack_floats, pack_u8s
from reach_sim_bridge.emulator.events import EventLog
from reach_sim_bridge.emulator.faults import Leak
from reach_sim_bridge.emulator.monitor import MONITOR_FLAGS, Monitor, MonitorConfig
from reach_sim_bridge.model import ik
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.sensors import SensorNoise

log = logging.getLogger(__name__)

LINK_ERROR_FLAGS = HardwareStatus.SERIAL_ERROR | HardwareStatus.CRC_ERROR
_MONITOR_STEPS = 5  # physics steps per monitor update (10 ms at the default 2 ms)

# Control packets that switch the mode implicitly; DISABLE and PASSIVE ignore them.
_LOCKED_MODES = frozenset({Mode.DISABLE, Mode.PASSIVE})
# Packets that give a joint its own command, ending a Cartesian velocity (KM_END_VEL).
_JOINT_COMMANDS = frozenset(
    {
        PacketID.MODE,
        PacketID.POSITION,
        PacketID.VELOCITY,
        PacketID.CURRENT,
        PacketID.INDEXED_POSITION,
        PacketID.RELATIVE_POSITION,
        PacketID.RESET,
        PacketID.KM_END_POS,
    }
)
# Modes whose loop servoes to `position_target`.
_HOLDING_MODES = frozenset({Mode.POSITION, Mode.POSITION_HOLD, Mode.STANDBY, Mode.DISABLE})


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


class _Rejected(Exception):
    def __init__(self, reason: ErrorReason, message: str) -> None:
        super().__init__(message)
        self.reason = reason


Handler = Callable[[list[Device], Packet], list[Packet]]


class Firmware:
    """All five devices of one arm. Not thread-safe: one owner calls handle() and tick()."""

    def __init__(self, arm: Alpha5Arm, config: FirmwareConfig | None = None) -> None:
        self.arm = arm
        self.config = config if config is not None else FirmwareConfig()
        self._rng = random.Random(self.config.seed)
        self._noise = self.config.sensor_noise
        self._step = arm.dt
        self._pending = 0.0
        self.errors = EventLog(log, logging.WARNING)
        self.ignored = EventLog(log, logging.INFO)
        self.packets_handled = 0
        self._devices: list[Device] = []
        self._by_id: dict[int, Device] = {}
        self._joints: list[Device] = [None] * 4  # type: ignore[list-item]
        self._jaw: Device | None = None
        continuous = bool(arm.params.wrist_continuous)
        arm_limits = arm.position_limits
        arm_currents = arm.current_limits_mA
        for spec in sorted(self.config.devices, key=lambda s: int(s.device_id)):
            if spec.letter == "A":
                index = -1
                lo, hi = arm.jaw_limits_mm
                imax = arm.jaw_current_limit_mA
            elif spec.letter in JOINT_LETTERS:
                index = JOINT_LETTERS.index(spec.letter)
                lo, hi = float(arm_limits[index, 0]), float(arm_limits[index, 1])
                imax = float(arm_currents[index])
            else:
                raise ValueError(f"device letter must be one of A B C D E, got {spec.letter!r}")
            saved = Saved((lo, hi), (-spec.rate_limit, spec.rate_limit), (-imax, imax), 0)
            dev = Device(
                spec=spec,
                index=index,
                continuous=continuous and spec.letter == "B",
                position_limits=Limits(lo, hi),
                velocity_limits=Limits(-spec.rate_limit, spec.rate_limit),
                current_limits=Limits(-imax, imax),
                saved=saved,
            )
            self._devices.append(dev)
            self._by_id[int(spec.device_id)] = dev
            if index >= 0:
                self._joints[index] = dev
            else:
                self._jaw = dev
        if any(d is None for d in self._joints):
            raise ValueError("the firmware needs devices for all of E D C B")
        for slot, dev in enumerate(self._devices):
            dev.position_target = self._position(dev)
            dev.slot = slot
        resistances = [
            float(arm.jaw_motor.resistance[0])
            if d.index < 0
            else float(arm.motor.resistance[d.index])
            for d in self._devices
        ]
        self.monitor = Monitor(
            self.config.monitor,
            resistances,
            self.config.temperature_c,
            arm.motor.supply_voltage,
            self.config.humidity_pct,
        )
        self._monitor_countdown = 0
        for leak in self.config.leaks:
            self.inject_leak(leak)
        self._handlers: dict[int, Handler] = {
            PacketID.MODE: self._on_mode,
            PacketID.POSITION: self._on_position,
            PacketID.VELOCITY: self._on_velocity,
            PacketID.CURRENT: self._on_current,
            PacketID.INDEXED_POSITION: self._on_relative,
            PacketID.RELATIVE_POSITION: self._on_relative,
            PacketID.POSITION_LIMITS: self._on_limits,
            PacketID.VELOCITY_LIMITS: self._on_limits,
            PacketID.CURRENT_LIMITS: self._on_limits,
            PacketID.SAVE: self._on_save,
            PacketID.REQUEST: self._on_request,
            PacketID.HEARTBEAT_SET: self._on_heartbeat_set,
            PacketID.HEARTBEAT_FREQUENCY: self._on_heartbeat_frequency,
            PacketID.RESET: self._on_reset,
            PacketID.KM_END_POS: self._on_end_pos,
            PacketID.KM_END_VEL: self._on_end_vel,
        }
        # A Cartesian velocity being followed: (linear m/s, angular rad/s), base frame.
        self._end_velocity: tuple[np.ndarray, np.ndarray] | None = None
        self._end_velocity_countdown = 0
        self._reporters: dict[int, Callable[[Device], bytes | None]] = {
            PacketID.MODE: lambda d: bytes((int(d.mode),)),
            PacketID.POSITION: lambda d: pack_floats(self._noisy_position(d)),
            PacketID.VELOCITY: lambda d: pack_floats(self._noisy_velocity(d)),
            PacketID.CURRENT: lambda d: pack_floats(self._current(d)),
            PacketID.POSITION_LIMITS: lambda d: _limits_payload(d.position_limits),
            PacketID.VELOCITY_LIMITS: lambda d: _limits_payload(d.velocity_limits),
            PacketID.CURRENT_LIMITS: lambda d: _limits_payload(d.current_limits),
            PacketID.SERIAL_NUMBER: lambda d: pack_floats(d.spec.serial_number),
            PacketID.MODEL_NUMBER: lambda d: pack_floats(self.config.model_number),
            PacketID.DEVICE_ID: lambda d: bytes((int(d.spec.device_id),)),
            PacketID.HUMIDITY: lambda d: pack_floats(self.monitor.humidity_pct[d.slot]),
            PacketID.TEMPERATURE: lambda d: pack_floats(self.monitor.temperature_c[d.slot]),
            # 0x67 is INTERNAL_PRESSURE in V1.12.1 (newer SDKs: DEVICE_TYPE); 0x6E the newer
            # PRESSURE. Both answer the internal pressure in bar (docs/protocol.md, 3a).
            PacketID.INTERNAL_PRESSURE: lambda d: pack_floats(self.monitor.pressure_bar(d.slot)),
            PacketID.PRESSURE: lambda d: pack_floats(self.monitor.pressure_bar(d.slot)),
            PacketID.FACTORY_CLIMATE: lambda d: pack_floats(*self.config.monitor.factory_climate),
            PacketID.HARDWARE_STATUS: lambda d: d.status.to_bytes(),
            PacketID.SOFTWARE_VERSION: lambda d: pack_u8s(*self.config.software_version),
            PacketID.VOLTAGE: lambda d: pack_floats(self.monitor.voltage_v),
            PacketID.HEARTBEAT_SET: lambda d: _heartbeat_payload(d.heartbeat_ids),
            PacketID.HEARTBEAT_FREQUENCY: lambda d: bytes((d.heartbeat_hz,)),
            PacketID.KM_END_POS: self._end_pose,
            PacketID.KM_END_VEL: self._end_twist,
        }

    # -- public -----------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Sim time (s) of the arm the firmware drives."""
        return self.arm.time

    @property
    def devices(self) -> tuple[int, ...]:
        return tuple(self._by_id)

    def mode(self, device_id: int) -> Mode:
        return self._by_id[device_id].mode

    def status(self, device_id: int) -> HardwareStatus:
        return self._by_id[device_id].status

    def inject_fault(self, device_id: int, flag: HardwareStatus) -> None:
        """Set a hardware status flag as a failing joint would (fault-injection tests); it is
        reported with HARDWARE_STATUS at 1 Hz like any other fault, and stays until a RESET
        (the monitor model does not clear an injected over-temperature, say)."""
        device = self._by_id[device_id]
        device.injected |= flag
        self._raise_flag([device], flag)

    def inject_leak(self, leak: Leak) -> None:
        """Let water into one device's housing (replaces a leak already there): its humidity
        and pressure drift up and raise OVER_HUMIDITY and OVER_PRESSURE (monitor model)."""
        self.monitor.leak(self._by_id[int(leak.device_id)].slot, leak)

    def stop_leak(self, device_id: int) -> None:
        """The housing is sealed again; what got in stays (readings stop drifting)."""
        self.monitor.leak(self._by_id[device_id].slot, None)

    def setpoints(self, device_id: int) -> tuple[Mode, float, float]:
        """(mode, position target, current applied in mA) of one device, for recordings."""
        d = self._by_id[device_id]
        return d.mode, d.position_target, d.applied_mA

    def handle(self, packet: Packet) -> list[Packet]:
        """Act on one packet from the host; the replies it causes, in order."""
        self.packets_handled += 1
        target = int(packet.device_id)
        if target == DeviceID.BROADCAST:
            targets = self._devices
        else:
            dev = self._by_id.get(target)
            if dev is None:
                self.ignored.record(
                    Ignored.OTHER_DEVICE.value,
                    f"packet 0x{int(packet.packet_id):02X} for device "
                    f"0x{target:02X}, which this arm does not have",
                )
                return []
            targets = [dev]
        pid = int(packet.packet_id)
        if (
            self._end_velocity is not None
            and pid in _JOINT_COMMANDS
            and any(d.index >= 0 for d in targets)
        ):
            self._stop_end_velocity()
        handler = self._handlers.get(pid)
        if handler is None:
            if pid in self._reporters:
                self.ignored.record(
                    Ignored.READ_ONLY.value,
                    f"packet 0x{pid:02X} is read-only here (send a REQUEST)",
                )
            else:
                self._error(
                    targets,
                    ErrorReason.UNKNOWN_PACKET,
                    f"packet id 0x{pid:02X} is not implemented; ignored",
                    flag=False,
                )
            return []
        try:
            return handler(targets, packet)
        except _Rejected as rejected:
            self._error(targets, rejected.reason, f"{packet!r}: {rejected}")
            return []

    def note_link_error(self, error: DecodeError) -> None:
        """A frame the server could not decode: flag it on the base device (0x05), where the
        host link enters the arm."""
        base = self._by_id.get(int(DeviceID.E), self._devices[-1])
        flag = (
            HardwareStatus.CRC_ERROR
            if error.reason == DecodeReason.CRC
            else HardwareStatus.SERIAL_ERROR
        )
        self._raise_flag([base], flag)

    def tick(self, dt: float) -> list[Packet]:
        """Advance control loops and physics by dt of sim time (in whole physics steps; the
        remainder carries over); the unprompted packets (heartbeats, status) due meanwhile."""
        if not (math.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"tick dt must be a finite number >= 0 s, got {dt}")
        self._pending += dt
        h = self._step
        n = int(self._pending / h + 1e-9)
        self._pending = max(0.0, self._pending - n * h)
        out: list[Packet] = []
        for _ in range(n):
            self._control_step(h)
            self._housekeeping(h, out)
        return out

    def steps(self, n: int) -> list[Packet]:
        """Advance exactly n physics steps (what tick() does for n * dt)."""
        out: list[Packet] = []
        for _ in range(n):
            self._control_step(self._step)
            self._housekeeping(self._step, out)
        return out

    def report(self, device_id: int, packet_id: int) -> Packet | None:
        """The packet device `device_id` sends for a REQUEST of `packet_id` (None if none)."""
        dev = self._by_id[device_id]
        reporter = self._reporters.get(packet_id)
        data = reporter(dev) if reporter is not None else None
        return None if data is None else Packet(dev.spec.device_id, packet_id, data)

    # -- control ----------------------------------------------------------------------------
    def _control_step(self, h: float) -> None:
        arm = self.arm
        if self._end_velocity is not None:
            self._follow_end_velocity(h)
        q = arm.q.tolist()
        qd = arm.qdot.tolist()
        currents = [self._loop(self._joints[i], q[i], qd[i], h) for i in range(4)]
        jaw = self._jaw
        jaw_mA = 0.0 if jaw is None else self._loop(jaw, arm.jaw_mm, arm.jaw_velocity_mm_s, h)
        arm.step(currents, jaw_mA)

    def _loop(self, d: Device, pos: float, vel: float, h: float) -> float:
        mode = d.mode
        if mode == Mode.CURRENT:
            d.integral = 0.0
            d.applied_mA = d.current_limits.clamp(d.current_target)
            return d.applied_mA
        if mode in _HOLDING_MODES:
            err = d.position_target - pos
            if d.continuous:
                err = (err + math.pi) % (2.0 * math.pi) - math.pi
            demand = d.spec.gains.position * err
        elif mode == Mode.VELOCITY:
            demand = d.velocity_target
            if not d.continuous and (
                (pos >= d.position_limits.hi and demand > 0.0)
                or (pos <= d.position_limits.lo and demand < 0.0)
            ):
                demand = 0.0  # soft end stop at the position limits
        elif mode == Mode.ZERO_VELOCITY:
            demand = 0.0
        else:  # PASSIVE, or a mode without a loop
            d.integral = 0.0
            d.applied_mA = 0.0
            return 0.0
        rate = d.spec.rate_limit
        demand = min(demand, rate, d.velocity_limits.hi)
        demand = max(demand, -rate, d.velocity_limits.lo)
        gains = d.spec.gains
        error = demand - vel
        integral = d.integral + error * h
        # Anti-windup: the integral alone never asks for more than the current limit.
        limits = d.current_limits
        ki = gains.velocity_i
        integral = min(max(integral, limits.lo / ki), limits.hi / ki)
        d.integral = integral
        d.applied_mA = limits.clamp(gains.velocity_p * error + ki * integral)
        return d.applied_mA

    def _monitor_step(self, h: float) -> None:
        """Step the climate and supply model every `_MONITOR_STEPS` physics steps, and carry
        its flags into each device's status (a newly raised one is reported at once)."""
        self._monitor_countdown -= 1
        if self._monitor_countdown > 0:
            return
        self._monitor_countdown = _MONITOR_STEPS
        arm = self.arm
        joint_mA = arm.current_mA.tolist()
        jaw_mA = arm.jaw_current_mA
        amps = [(jaw_mA if d.index < 0 else joint_mA[d.index]) / 1000.0 for d in self._devices]
        monitor = self.monitor
        monitor.step(h * _MONITOR_STEPS, amps, arm.motor.supply_voltage)
        for d, modelled in zip(self._devices, monitor.flags, strict=True):
            now = d.status & MONITOR_FLAGS
            flags = modelled | (d.injected & MONITOR_FLAGS)
            if flags != now:
                raised = flags & ~now
                if raised and not d.status:
                    d.status_phase = self.config.status_period_s  # report at once
                d.status = (d.status & ~MONITOR_FLAGS) | flags
                log.info(
                    "device %s: monitor flags now %s",
                    d.spec.letter,
                    ", ".join(flags.flag_names()) or "clear",
                )

    def _housekeeping(self, h: float, out: list[Packet]) -> None:
        now = self.arm.time
        cfg = self.config
        self._monitor_step(h)
        for d in self._devices:
            if d.heartbeat_hz and d.heartbeat_ids:
                d.heartbeat_phase += h
                period = 1.0 / d.heartbeat_hz
                if d.heartbeat_phase >= period - 1e-9:
                    d.heartbeat_phase = max(0.0, d.heartbeat_phase - period)
                    for pid in d.heartbeat_ids:
                        packet = self.report(int(d.spec.device_id), pid)
                        if packet is not None:
                            out.append(packet)
            if not d.status:  # (a plain int test: IntFlag operators are slow per step)
                continue
            if d.status & LINK_ERROR_FLAGS and now - d.last_error_time >= cfg.error_hold_s:
                d.status &= ~LINK_ERROR_FLAGS
                log.info(
                    "device %s: link error flags cleared after %.1f s without errors",
                    d.spec.letter,
                    cfg.error_hold_s,
                )
                continue
            # Any flag set: HARDWARE_STATUS unprompted at about 1 Hz.
            d.status_phase += h
            if d.status_phase >= cfg.status_period_s - 1e-9:
                d.status_phase = 0.0
                out.append(Packet(d.spec.device_id, PacketID.HARDWARE_STATUS, d.status.to_bytes()))

    # -- measurements -----------------------------------------------------------------------
    def _position(self, d: Device) -> float:
        return self.arm.jaw_mm if d.index < 0 else float(self.arm.q[d.index])

    def _velocity(self, d: Device) -> float:
        return self.arm.jaw_velocity_mm_s if d.index < 0 else float(self.arm.qdot[d.index])

    def _current(self, d: Device) -> float:
        return self.arm.jaw_current_mA if d.index < 0 else float(self.arm.current_mA[d.index])

    def _noisy_position(self, d: Device) -> float:
        value = self._position(d)
        if self._noise is not None and self._noise.position_std > 0.0:
            value += self._rng.gauss(0.0, self._noise.position_std)
        return value

    def _noisy_velocity(self, d: Device) -> float:
        value = self._velocity(d)
        if self._noise is not None and self._noise.velocity_std > 0.0:
            value += self._rng.gauss(0.0, self._noise.velocity_std)
        return value

    def _end_pose(self, d: Device) -> bytes | None:
        if d.spec.device_id != DeviceID.E:
            return None  # the base device does the kinematics
        return pack_floats(*self.arm.end_effector_pose())

    def _end_twist(self, d: Device) -> bytes | None:
        if d.spec.device_id != DeviceID.E:
            return None
        linear, angular = ik.tcp_velocity(self.arm, self.arm.q, self.arm.qdot)
        return pack_floats(*(linear * 1000.0).tolist(), *angular.tolist())

    # -- end-effector moves (base device) ---------------------------------------------------
    def _end_command(self, targets: list[Device], packet: Packet, name: str) -> list[float] | None:
        """The 6 floats of a KM_END_POS/KM_END_VEL for the base device (None: not for it, or
        a joint cannot take it; counted)."""
        if not any(d.spec.device_id == DeviceID.E for d in targets):
            self.ignored.record(
                Ignored.NOT_BASE.value,
                f"{name} to device 0x{int(packet.device_id):02X}: only the base device "
                "(0x05) does kinematics",
            )
            return None
        if len(packet.data) != 24:
            raise _Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"{name} payload must be 6 float32 (24 bytes), got {len(packet.data)}",
            )
        values = packet.floats()
        if not all(math.isfinite(v) for v in values):
            raise _Rejected(ErrorReason.BAD_VALUE, f"{name} {values} is not finite")
        if len(self._control(self._joints, name)) < len(self._joints):
            return None  # a joint in DISABLE or PASSIVE: the arm cannot move as a whole
        return values

    def _joint_limits(self) -> np.ndarray:
        return np.array([[d.position_limits.lo, d.position_limits.hi] for d in self._joints])

    def _on_end_pos(self, targets: list[Device], packet: Packet) -> list[Packet]:
        pose = self._end_command(targets, packet, "KM_END_POS")
        if pose is None:
            return []
        wrist = self._joints[-1]
        solution = ik.solve(self.arm, pose, self.arm.q, self._joint_limits(), wrist.continuous)
        if not solution.reachable:
            self.ignored.record(
                Ignored.UNREACHABLE.value,
                f"KM_END_POS ({pose[0]:.1f}, {pose[1]:.1f}, {pose[2]:.1f}) mm is out of reach "
                f"inside the joint limits (closest {solution.position_error_mm:.1f} mm); "
                "no motion",
            )
            return []
        for d, angle in zip(self._joints, solution.q.tolist(), strict=True):
            self._command_position(d, angle)
        return []

    def _on_end_vel(self, targets: list[Device], packet: Packet) -> list[Packet]:
        twist = self._end_command(targets, packet, "KM_END_VEL")
        if twist is None:
            return []
        for d in self._joints:
            self._set_mode(d, Mode.VELOCITY)
            d.velocity_target = 0.0
        if any(twist):
            linear = np.array(twist[:3]) / 1000.0
            self._end_velocity = (linear, np.array(twist[3:]))
            self._end_velocity_countdown = 0
        else:
            self._end_velocity = None  # zero: stop, in velocity mode
        return []

    def _stop_end_velocity(self) -> None:
        self._end_velocity = None
        for d in self._joints:
            if d.mode == Mode.VELOCITY:
                d.velocity_target = 0.0

    def _follow_end_velocity(self, h: float) -> None:
        """Joint rates for the Cartesian velocity, every `_MONITOR_STEPS` physics steps,
        inside each joint's rate and velocity limits; stops at a joint's position limit."""
        self._end_velocity_countdown -= 1
        if self._end_velocity_countdown > 0:
            return
        self._end_velocity_countdown = _MONITOR_STEPS
        assert self._end_velocity is not None
        linear, angular = self._end_velocity
        joints = self._joints
        max_rates = np.array(
            [
                max(min(d.spec.rate_limit, d.velocity_limits.hi, -d.velocity_limits.lo), 1e-9)
                for d in joints
            ]
        )
        q = self.arm.q
        rates = ik.joint_rates(self.arm, q, linear, angular, max_rates).tolist()
        lookahead = h * _MONITOR_STEPS
        for d, angle, rate in zip(joints, q.tolist(), rates, strict=True):
            ahead = angle + rate * lookahead
            if not d.continuous and not d.position_limits.contains(ahead) and abs(rate) > 1e-6:
                self.ignored.record(
                    Ignored.END_VELOCITY_STOPPED.value,
                    f"KM_END_VEL stopped: joint {d.spec.letter} at its position limit",
                )
                self._stop_end_velocity()
                return
        for d, rate in zip(joints, rates, strict=True):
            d.velocity_target = rate

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
        if mode in _HOLDING_MODES:
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
            raise _Rejected(
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
            raise _Rejected(
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
        value = _one_float(packet, "POSITION")
        for d in self._control(targets, "POSITION"):
            self._command_position(d, value)
        return []

    def _on_relative(self, targets: list[Device], packet: Packet) -> list[Packet]:
        delta = _one_float(packet, "relative POSITION")
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
        value = _one_float(packet, "VELOCITY")
        for d in self._control(targets, "VELOCITY"):
            self._set_mode(d, Mode.VELOCITY)
            rate = d.spec.rate_limit
            d.velocity_target = max(min(d.velocity_limits.clamp(value), rate), -rate)
        return []

    def _on_current(self, targets: list[Device], packet: Packet) -> list[Packet]:
        value = _one_float(packet, "CURRENT")
        for d in self._control(targets, "CURRENT"):
            self._set_mode(d, Mode.CURRENT)
            d.current_target = d.current_limits.clamp(value)
        return []

    def _on_limits(self, targets: list[Device], packet: Packet) -> list[Packet]:
        """Limits are refused (counted, changing nothing) when they are not [max, min], but no
        status flag is raised: a client sending them once at start-up has no link fault."""
        try:
            return self._set_limits(targets, packet)
        except _Rejected as rejected:
            self._error(targets, rejected.reason, f"{packet!r}: {rejected}", flag=False)
            return []

    def _set_limits(self, targets: list[Device], packet: Packet) -> list[Packet]:
        pid = PacketID(int(packet.packet_id))
        if len(packet.data) == 16:
            raise _Rejected(
                ErrorReason.LIMITS_16_BYTES,
                f"{pid.name} payload of 16 bytes (8 zero bytes then [min, max]?) refused: the "
                "payload is 8 bytes, [max, min] (protocol V1.12.1)",
            )
        if len(packet.data) != 8:
            raise _Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"{pid.name} payload must be 8 bytes [max, min], got {len(packet.data)}",
            )
        hi, lo = packet.floats()
        if not (math.isfinite(hi) and math.isfinite(lo)):
            raise _Rejected(ErrorReason.BAD_VALUE, f"{pid.name} [{hi}, {lo}] is not finite")
        if hi < lo:
            raise _Rejected(
                ErrorReason.BAD_LIMITS,
                f"{pid.name} max {hi} < min {lo}: refused (the wire order is [max, min]; "
                "[min, max] is the order of protocol V1.9 and of some client libraries)",
            )
        if pid != PacketID.POSITION_LIMITS and not lo <= 0.0 <= hi:
            raise _Rejected(
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
        if d.index < 0:
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
            self._set_mode(d, Mode.STANDBY)
            d.position_target = self._position(d)
        return []

    def _on_request(self, targets: list[Device], packet: Packet) -> list[Packet]:
        ids = packet.data
        if not 1 <= len(ids) <= MAX_REQUEST_IDS:
            raise _Rejected(
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
                elif not broadcast or pid not in self._reporters:
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
            raise _Rejected(
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
        unknown = [pid for pid in ids if pid not in self._reporters]
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
            raise _Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"HEARTBEAT_FREQUENCY payload must be 1 byte, got {len(packet.data)}",
            )
        for d in targets:
            d.heartbeat_hz = packet.data[0]
            d.heartbeat_phase = 0.0
        return []


def _one_float(packet: Packet, name: str) -> float:
    if len(packet.data) != 4:
        raise _Rejected(
            ErrorReason.BAD_PAYLOAD,
            f"{name} payload must be one float32 (4 bytes), got {len(packet.data)}",
        )
    value = packet.floats()[0]
    if not math.isfinite(value):
        raise _Rejected(ErrorReason.BAD_VALUE, f"{name} value {value} is not finite")
    return value


def _limits_payload(limits: Limits) -> bytes:
    return pack_floats(limits.hi, limits.lo)


def _heartbeat_payload(ids: tuple[int, ...]) -> bytes:
    return bytes(ids) + bytes(HEARTBEAT_SLOTS - len(ids))
