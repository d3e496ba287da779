"""Emulation of the Alpha 5's joint firmware on top of the MuJoCo arm.

Each device (A jaws 0x01 .. E base 0x05) keeps the state the real firmware keeps: mode,
setpoints, [max, min] limits, identity, hardware status flags and a heartbeat. Its control
loops run once per physics step in sim time, cascaded like the arm's: position error ->
velocity demand (clamped to the firmware rate limit and the velocity limits) -> PI velocity
loop -> current (clamped to the current limits) -> motor. Current mode goes straight to the
motor. The integral term of the velocity loop is what holds D and C against gravity. Its
anti-windup (an assumption: model/README.md, "the firmware's velocity loop at an end stop")
bleeds the integral while it only pushes a joint into a limit or a stall. Every mode's current
is also capped by the device's thermal derating (`reach_sim_bridge.emulator.derating`, also
an assumption): sustained current above the continuous rating lowers the limit, rest restores
it.

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

The devices' specs, configuration and live state are plain data in `devices`; what each
packet from the host does is in `handlers` (`PacketHandlers`, which `Firmware` inherits).
"""

from __future__ import annotations

import logging
import math
import random
from collections.abc import Callable

import numpy as np

from protocol import (
    DecodeError,
    DecodeReason,
    DeviceID,
    HardwareStatus,
    Mode,
    Packet,
    PacketID,
)
from protocol.alpha5 import JOINT_LETTERS
from protocol.commands import HEARTBEAT_SLOTS
from protocol.payload import pack_floats, pack_u8s
from reach_sim_bridge.emulator.derating import CurrentDerating
from reach_sim_bridge.emulator.devices import (
    ALPHA5_DEVICES,
    HOLDING_MODES,
    Device,
    DeviceSpec,
    ErrorReason,
    FirmwareConfig,
    Ignored,
    Limits,
    LoopGains,
    Saved,
)
from reach_sim_bridge.emulator.events import EventLog
from reach_sim_bridge.emulator.faults import Leak, StuckReading
from reach_sim_bridge.emulator.handlers import Handler, PacketHandlers, Rejected
from reach_sim_bridge.emulator.monitor import MONITOR_FLAGS, Monitor
from reach_sim_bridge.model import ik
from reach_sim_bridge.model.arm import Alpha5Arm

log = logging.getLogger(__name__)

# What configures a firmware, importable from here as well as from `devices`.
__all__ = [
    "ALPHA5_DEVICES",
    "DeviceSpec",
    "Firmware",
    "FirmwareConfig",
    "LoopGains",
]

LINK_ERROR_FLAGS = HardwareStatus.SERIAL_ERROR | HardwareStatus.CRC_ERROR
_MONITOR_STEPS = 5  # physics steps per monitor update (10 ms at the default 2 ms)
#: Anti-windup bleed [A]: the velocity loop's integral decays with this time constant while
#: it only pushes a joint into a limit or a stall (`Firmware._winding_up`). Real firmware's
#: anti-windup is not documented; this is the emulator's assumption (model/README.md).
WINDUP_BLEED_S = 0.2
#: Below this speed (unit/s) in the direction of the push, a joint at the current limit
#: counts as stalled [A].
STALL_SPEED = 0.01

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


class Firmware(PacketHandlers):
    """All five devices of one arm. Not thread-safe: one owner calls handle() and tick()."""

    def __init__(self, arm: Alpha5Arm, config: FirmwareConfig | None = None) -> None:
        self.arm = arm
        self.config = config if config is not None else FirmwareConfig()
        self._rng = random.Random(self.config.seed)
        self._noise = self.config.sensor_noise
        self._step = arm.dt
        self._windup_keep = math.exp(-self._step / WINDUP_BLEED_S)  # per control step
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
                peak_mA=imax,
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
        self._derating = self.config.derating
        self._derate_factor = (
            0.0
            if self._derating is None
            else self._derating.step_factor(self._step * _MONITOR_STEPS)
        )
        for leak in self.config.leaks:
            self.inject_leak(leak)
        # (device, packet) -> (arm time it sticks from, the payload it is stuck at, once known)
        self._stuck: dict[tuple[int, int], tuple[float, bytes | None]] = {}
        for stuck in self.config.stuck:
            self.inject_stuck(stuck)
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

    def inject_stuck(self, stuck: StuckReading) -> None:
        """From `stuck.from_s` (arm time) on, the device reports that packet with the value
        it reports at that moment (`faults.StuckReading`); replaces a stuck one there."""
        device = self._by_id[int(stuck.device_id)]
        if int(stuck.packet_id) not in self._reporters:
            raise ValueError(f"device {device.spec.letter} reports no 0x{stuck.packet_id:02X}")
        self._stuck[(int(stuck.device_id), int(stuck.packet_id))] = (stuck.from_s, None)

    def unstick(self, device_id: int, packet_id: int) -> None:
        """The reading follows the arm again."""
        self._stuck.pop((device_id, packet_id), None)

    def stop_leak(self, device_id: int) -> None:
        """The housing is sealed again; what got in stays (readings stop drifting)."""
        self.monitor.leak(self._by_id[device_id].slot, None)

    def current_ceiling(self, device_id: int) -> float:
        """The derated current limit of one device (mA, either sign; inf while it is cool
        enough not to derate). The wire shows it only as the CURRENT the joint draws."""
        return self._by_id[device_id].ceiling_mA

    def thermal_load(self, device_id: int) -> float:
        """The derating's I^2 t estimate of one device (1.0: the winding's rated rise)."""
        return self._by_id[device_id].thermal_load

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
        except Rejected as rejected:
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
        stuck = self._stuck.get((device_id, packet_id)) if self._stuck else None
        if stuck is not None and self.arm.time >= stuck[0] and stuck[1] is not None:
            return Packet(dev.spec.device_id, packet_id, stuck[1])
        reporter = self._reporters.get(packet_id)
        data = reporter(dev) if reporter is not None else None
        if stuck is not None and self.arm.time >= stuck[0] and data is not None:
            self._stuck[(device_id, packet_id)] = (stuck[0], data)  # stuck at this one
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
        limits = d.current_limits
        lo, hi, cap = limits.lo, limits.hi, d.ceiling_mA
        if hi > cap:  # thermally derated
            hi = cap
        if lo < -cap:
            lo = -cap
        if mode == Mode.CURRENT:
            d.integral = 0.0
            target = d.current_target
            d.applied_mA = hi if target > hi else (lo if target < lo else target)
            return d.applied_mA
        if mode in HOLDING_MODES:
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
        ki = gains.velocity_i
        integral = min(max(integral, lo / ki), hi / ki)
        wanted = gains.velocity_p * error + ki * integral
        if integral and self._winding_up(d, pos, vel, ki * integral, wanted, lo, hi):
            integral *= self._windup_keep
            wanted = gains.velocity_p * error + ki * integral
        d.integral = integral
        d.applied_mA = hi if wanted > hi else (lo if wanted < lo else wanted)
        return d.applied_mA

    @staticmethod
    def _winding_up(
        d: Device, pos: float, vel: float, push_mA: float, wanted_mA: float, lo: float, hi: float
    ) -> bool:
        """Whether the integral term (`push_mA`) only pushes the joint into something it
        cannot pass: the joint at or past a position limit with the push outward, or the
        output at the current limit in force (`lo`, `hi`, derating included) with the joint
        stalled (an end stop, an obstacle). The error is then zero or cannot shrink, so
        without a bleed the integral would hold the stall current for ever (a bumpless switch
        to ZERO_VELOCITY at an end stop starts it there)."""
        out = 1.0 if push_mA > 0.0 else -1.0
        if not d.continuous:
            lim = d.position_limits
            if (out > 0.0 and pos >= lim.hi) or (out < 0.0 and pos <= lim.lo):
                return True
        edge = hi if out > 0.0 else lo
        saturated = wanted_mA * out >= edge * out - 1e-9 and edge * out > 0.0
        return saturated and vel * out < STALL_SPEED

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
        if self._derating is not None:
            self._derate(self._derating, amps)
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

    def _derate(self, derating: CurrentDerating, amps: list[float]) -> None:
        """Advance each device's I^2 t estimate with the current it drew (A) and set its
        derated limit (`reach_sim_bridge.emulator.derating`)."""
        a = self._derate_factor
        start = derating.start
        for d, amp in zip(self._devices, amps, strict=True):
            ratio = amp * 1000.0 / (derating.continuous_fraction * d.peak_mA)
            load = d.thermal_load
            load += (ratio * ratio - load) * a
            d.thermal_load = load
            was = d.ceiling_mA
            d.ceiling_mA = math.inf if load <= start else derating.ceiling(load, d.peak_mA)
            if (was == math.inf) != (d.ceiling_mA == math.inf):
                log.info(
                    "device %s: current limit %s (thermal load %.2f)",
                    d.spec.letter,
                    "derated" if d.ceiling_mA != math.inf else "restored",
                    load,
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
            raise Rejected(
                ErrorReason.BAD_PAYLOAD,
                f"{name} payload must be 6 float32 (24 bytes), got {len(packet.data)}",
            )
        values = packet.floats()
        if not all(math.isfinite(v) for v in values):
            raise Rejected(ErrorReason.BAD_VALUE, f"{name} {values} is not finite")
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


def _limits_payload(limits: Limits) -> bytes:
    return pack_floats(limits.hi, limits.lo)


def _heartbeat_payload(ids: tuple[int, ...]) -> bytes:
    return bytes(ids) + bytes(HEARTBEAT_SLOTS - len(ids))
