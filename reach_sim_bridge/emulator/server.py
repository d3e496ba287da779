"""Serving the virtual arm (the Alpha 5 by default, or the Bravo 7) on a pty and/or UDP,
paced to the wall clock.

One background thread owns the arm, the firmware and the endpoints: it advances physics to
where the (scaled) wall clock says sim time should be, reads whatever arrived, lets the
firmware answer, and writes replies out through the link faults, the added latency and the
serial line's byte rate. One thread means the firmware needs no locking against itself; a
lock only guards it against the inspection methods called from other threads.

What crosses the endpoints (input credit, the serial line's timing and half duplex, the
output queues) is `WireIO` in `reach_sim_bridge.emulator.wire`, which `SimServer` inherits;
its docstring says how nothing a client sends can take the loop thread from the physics or
make memory grow.
"""

from __future__ import annotations

import logging
import math
import select
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from types import TracebackType
from typing import TypeVar

import numpy as np

from protocol import HardwareStatus, Packet, PacketDecoder
from protocol.decoder import DecoderStats
from protocol.models import ALPHA5, ArmModel
from reach_sim_bridge.emulator.devices import DEVICE_SPECS, MODEL_NUMBERS
from reach_sim_bridge.emulator.events import EventLog
from reach_sim_bridge.emulator.faults import FaultConfig, LinkFaults, StuckReading
from reach_sim_bridge.emulator.firmware import Firmware, FirmwareConfig
from reach_sim_bridge.emulator.pty import PtyEndpoint
from reach_sim_bridge.emulator.udp import Address, UdpEndpoint, is_loopback
from reach_sim_bridge.emulator.wire import (
    BITS_PER_BYTE,
    INPUT_BURST,
    INPUT_UNITS_PER_S,
    TURNAROUND_BYTES,
    Counters,
    WireIO,
    out_frame_max_age,
    out_queue_limit,
)
from reach_sim_bridge.model.arm import MotorArm
from reach_sim_bridge.model.arms import TWINS, arm_twin, params_problem
from reach_sim_bridge.model.params import ArmParams

T = TypeVar("T")

log = logging.getLogger(__name__)

# The wire's limits that callers size things by, importable from here as well as from `wire`.
__all__ = [
    "INPUT_UNITS_PER_S",
    "TURNAROUND_BYTES",
    "ArmSnapshot",
    "ServerStats",
    "SimConfig",
    "SimServer",
    "out_frame_max_age",
    "out_queue_limit",
    "serve_forever",
]


MAX_STEPS_PER_PASS = 25  # physics steps between two looks at the endpoints
MAX_LAG_WALL_S = 0.25  # further behind than this, the sim slows down instead of catching up
MIN_WAIT_S = 0.0005
LINE_BUFFER_S = 0.25  # with --baud, stop reading the pty this far ahead of the line
UDP_DATAGRAMS_PER_PASS = 16  # read (or dropped, without credit) per look at the socket
DRAIN_READS = 16  # on stop, reads of each endpoint still acted on


@dataclass(frozen=True)
class SimConfig:
    """How to serve the virtual arm. At least one of `pty` and `udp` must be on."""

    model: ArmModel = ALPHA5  # the arm served: the Alpha 5 or the Bravo 7
    speed: float = 1.0  # sim seconds per wall second
    pty: bool = True
    link: str | None = None  # stable symlink to the pty, removed on stop
    udp: Address | None = None  # (host, port); port 0 picks a free one
    baud: int | None = None  # throttle the pty to this line rate (10 bits per byte)
    # The pty as one RS-485 wire (module docstring): needs the pty and its baud.
    half_duplex: bool = False
    start: tuple[float, ...] | None = None  # rad, the model's joint order; None = mid pose
    jaw_mm: float = 5.0
    dt: float = 0.002  # physics (and firmware loop) step, sim seconds
    faults: FaultConfig = field(default_factory=FaultConfig)
    firmware: FirmwareConfig = field(default_factory=FirmwareConfig)
    seed: int | None = None  # link faults and sensor noise
    # The arm served, as `ArmParams` of its model (None: nominal); --randomize-params
    # perturbs around it, and the faults' torque scale multiplies its own.
    params: ArmParams | None = None

    def __post_init__(self) -> None:
        model = self.model
        if model.name not in TWINS:
            known = ", ".join(TWINS)
            raise ValueError(f"no virtual {model.title}: the simulator serves {known}")
        problem = None if self.params is None else params_problem(self.params, model)
        if problem:
            raise ValueError(f"--params: {problem}")
        self.faults.torque_scale_for(model)  # one value per joint of this arm
        firmware = self.firmware
        if firmware.model.name != model.name:
            # A firmware configuration left at its model's devices follows the model served.
            if firmware.devices != DEVICE_SPECS.get(firmware.model.name):
                raise ValueError(
                    f"the firmware's devices are the {firmware.model.title}'s, the arm served "
                    f"is the {model.title}"
                )
            number = firmware.model_number
            if number == MODEL_NUMBERS.get(firmware.model.name):
                number = 0.0
            object.__setattr__(
                self, "firmware", replace(firmware, model=model, devices=(), model_number=number)
            )
        if not (math.isfinite(self.speed) and self.speed > 0.0):
            raise ValueError(f"speed must be a finite number > 0, got {self.speed}")
        if not self.pty and self.udp is None:
            raise ValueError("nothing to serve: enable the pty or give a UDP address")
        if self.link is not None and not self.pty:
            raise ValueError("a link to the pty needs the pty")
        if self.baud is not None and self.baud <= 0:
            raise ValueError(f"baud must be a positive number of bits per second, got {self.baud}")
        if self.half_duplex and (not self.pty or self.baud is None):
            raise ValueError(
                "half duplex times a shared serial wire: it needs the pty and its baud "
                f"({model.serial_baud} on the {model.title})"
            )
        if self.start is not None:
            n = model.n_joints
            if len(self.start) != n or not all(math.isfinite(v) for v in self.start):
                raise ValueError(
                    f"start needs {n} finite angles {' '.join(model.joint_letters)} (rad), "
                    f"got {self.start}"
                )
        if self.udp is not None:
            host, port = self.udp
            if not 0 <= port <= 65535:
                raise ValueError(f"UDP port must be in 0..65535, got {port}")
            if not host:
                raise ValueError("UDP host is empty")


@dataclass(frozen=True)
class ServerStats:
    """Counters since the last power cycle; every byte received is in a good frame, counted
    as discarded, (UDP without input credit) in input_dropped_bytes, or (half duplex) in
    collision_bytes."""

    frames_in: int
    frames_out: int  # put on the wire (frames dropped from the --baud queue are not)
    bytes_in: int
    bytes_out: int
    datagrams_in: int
    datagrams_out: int
    bad_frames: dict[str, int]  # by decoder reason (crc, cobs, length, ...)
    bytes_discarded: int
    collisions: int  # half duplex: host frames lost, sent while the arm was sending
    collision_bytes: int  # ... their bytes (received, in bytes_in, never decoded)
    collided_out: int  # half duplex: the arm's frames lost on the wire to a collision
    firmware_errors: dict[str, int]  # well-framed packets rejected (bad payload, ...)
    ignored: dict[str, int]  # valid packets the arm ignores (out of limits, ...)
    dropped_frames: int  # by the drop-rate fault
    corrupted_bytes: int  # by the corrupt-rate fault
    lost_bytes: int  # the pty buffer was full (no client reading)
    stream_dropped: int  # heartbeat/status frames dropped: --baud queue full, or too old
    replies_dropped: int  # the oldest replies, pushed out of the full --baud queue or too old
    queued_bytes: int  # waiting for the pty now
    queued_peak_bytes: int  # the most waiting with --baud (at most out_queue_limit(baud))
    input_dropped_bytes: int  # UDP bytes dropped unread: no input credit left
    sim_time: float
    lag_s: float  # sim time given up because the host could not keep the pace

    @property
    def bad_total(self) -> int:
        return sum(self.bad_frames.values())


@dataclass(frozen=True)
class ArmSnapshot:
    """The simulated arm's true state at one instant (for tests and tools, not the wire)."""

    time: float
    q: np.ndarray
    qdot: np.ndarray
    current_mA: np.ndarray
    jaw_mm: float


class SimServer(WireIO):
    """The virtual arm behind a pty and/or UDP socket, in a background thread.

    `start()` returns the pty path (None when serving UDP only); `udp_address` is the bound
    address. `stop()` is idempotent; `restart()` is a power cycle with the link going down
    and up (new pty, same link and UDP port); `power_cycle()` resets arm and firmware while
    the endpoints stay open.
    """

    def __init__(self, config: SimConfig | None = None) -> None:
        self.config = config if config is not None else SimConfig()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pty: PtyEndpoint | None = None
        self._udp: UdpEndpoint | None = None
        self._udp_port: int | None = None  # kept across restarts when the config said 0
        self.error: BaseException | None = None
        self._anchor: tuple[float, float] | None = None  # (wall, sim) the pacing counts from
        self._cycle_request = threading.Event()
        self._cycle_done = threading.Event()
        self._reset_state()

    # -- lifecycle ------------------------------------------------------------------------
    def _reset_state(self) -> None:
        cfg = self.config
        self.arm = self._make_arm()
        firmware_cfg = cfg.firmware
        if cfg.half_duplex:  # one wire: broadcast answers collide on it too
            firmware_cfg = replace(firmware_cfg, half_duplex=True)
        if cfg.faults.sensor_noise is not None:
            firmware_cfg = replace(
                firmware_cfg, sensor_noise=cfg.faults.sensor_noise, seed=cfg.seed
            )
        self.firmware = Firmware(self.arm, firmware_cfg)
        self._link_faults = LinkFaults(cfg.faults, seed=cfg.seed)
        self._link_errors = EventLog(log, logging.WARNING)
        self._pty_decoder = PacketDecoder(on_error=self._on_decode_error)
        self._udp_decoder = PacketDecoder(on_error=self._on_decode_error)
        self._counters = Counters()
        # (when it has landed, bytes); None: a frame lost in a collision (half duplex)
        self._pty_in: deque[tuple[float, bytes | None]] = deque()
        self._pty_pending: deque[Packet] = deque()  # decoded, waiting for input credit
        # (when ready to go, frame), replies ahead of the stream; _pty_queued bytes in both
        self._pty_replies: deque[tuple[float, bytes]] = deque()
        self._pty_stream: deque[tuple[float, bytes]] = deque()
        self._pty_queued = 0
        self._pty_wire: tuple[float, bytes] | None = None  # (when its last byte lands, frame)
        self._pty_partial = b""
        self._line_rate = None if cfg.baud is None else cfg.baud / BITS_PER_BYTE
        self._out_limit = None if cfg.baud is None else out_queue_limit(cfg.baud)
        self._out_age = None if cfg.baud is None else out_frame_max_age(cfg.baud)
        self._rx_free = 0.0  # when the serial line is next idle, each way
        self._tx_free = 0.0
        self._turnaround = 0.0 if cfg.baud is None else TURNAROUND_BYTES * BITS_PER_BYTE / cfg.baud
        self._rx_garbled = False  # half duplex: inside a host frame lost to a collision
        self._udp_out: deque[tuple[float, bytes, Address]] = deque()
        self._udp_peer: Address | None = None
        self._pty_credit = self._udp_credit = float(INPUT_BURST)  # input units, each end

    def _make_arm(self) -> MotorArm:
        cfg = self.config
        arm = arm_twin(cfg.model, cfg.params, cfg.dt, cfg.faults.randomize_seed)
        if cfg.faults.randomize_seed is not None:
            params = arm.randomize()
            log.info(
                "randomized arm parameters (seed %d): %s",
                cfg.faults.randomize_seed,
                {
                    k: params.as_dict()[k]
                    for k in (
                        "armature",
                        "damping",
                        "frictionloss",
                        "link_mass_kg",
                        "link_volume_l",
                    )
                },
            )
        arm.torque_scale = np.asarray(arm.params.torque_scale) * np.asarray(
            cfg.faults.torque_scale_for(cfg.model)
        )
        arm.reset(q=None if cfg.start is None else np.asarray(cfg.start), jaw_mm=cfg.jaw_mm)
        return arm

    def start(self) -> str | None:
        """Open the endpoints and start the arm; the pty path clients should open."""
        if self._thread is not None:
            raise RuntimeError("the simulator is already running; stop() it first")
        cfg = self.config
        self._stop.clear()
        self.error = None
        # Whatever was in flight when the link went down is lost with it.
        self._pty_in.clear()
        self._pty_pending.clear()
        self._clear_pty_out()
        self._udp_out.clear()
        self._pty_decoder.reset()
        self._rx_free = self._tx_free = 0.0
        self._rx_garbled = False
        try:
            if cfg.pty:
                self._pty = PtyEndpoint(cfg.link)
            if cfg.udp is not None:
                host, port = cfg.udp
                if not is_loopback(host):
                    log.warning("serving UDP on %s: reachable beyond this machine", host)
                self._udp = UdpEndpoint(host, self._udp_port if self._udp_port else port)
                self._udp_port = self._udp.address[1]
        except BaseException:
            self._close_endpoints()
            raise
        self._thread = threading.Thread(target=self._run, name="reach-sim", daemon=True)
        self._thread.start()
        log.info(
            "virtual %s serving%s%s at %gx real time",
            cfg.model.title,
            f" pty {self.pty_path}" if self._pty else "",
            f" udp {self._udp.address[0]}:{self._udp.address[1]}" if self._udp else "",
            cfg.speed,
        )
        return self.pty_path

    def stop(self) -> None:
        """Stop the thread and close the endpoints (removing the link); safe to repeat."""
        thread = self._thread
        if thread is not None:
            self._stop.set()
            thread.join()
            self._thread = None
        self._close_endpoints()

    def restart(self, downtime_s: float = 0.0) -> str | None:
        """Power-cycle the arm with the link down for `downtime_s` wall seconds: state is
        reset, the pty is recreated (new path, same link), the UDP port is kept."""
        self.stop()
        if downtime_s > 0.0:
            time.sleep(downtime_s)
        with self._lock:
            self._reset_state()
        return self.start()

    def power_cycle(self, timeout: float = 10.0) -> None:
        """Reset the arm and firmware to their start state; endpoints stay open."""
        if not self.running:
            with self._lock:
                self._reset_state()
            return
        self._cycle_done.clear()
        self._cycle_request.set()
        if not self._cycle_done.wait(timeout):
            raise TimeoutError("the simulator loop did not power-cycle the arm in time")

    def _do_power_cycle(self) -> None:
        # In the loop thread: queued output and the UDP peer belong to the link, not the arm.
        self._cycle_request.clear()
        link_state = (
            "_pty_in",
            "_pty_pending",
            "_pty_replies",
            "_pty_stream",
            "_pty_queued",
            "_pty_wire",
            "_pty_partial",
            "_rx_free",
            "_tx_free",
            "_rx_garbled",
            "_udp_out",
            "_udp_peer",
            "_pty_credit",
            "_udp_credit",
        )
        with self._lock:
            kept = {name: getattr(self, name) for name in link_state}
            self._reset_state()
            for name, value in kept.items():
                setattr(self, name, value)
            self._counters.queued_peak_bytes = self._pty_queued
            self._anchor = None  # pacing restarts from the new sim time
        log.info("arm power-cycled")
        self._cycle_done.set()

    def _close_endpoints(self) -> None:
        if self._pty is not None:
            self._pty.close()
            self._pty = None
        if self._udp is not None:
            self._udp.close()
            self._udp = None

    def __enter__(self) -> SimServer:
        if self._thread is None:
            self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def pty_path(self) -> str | None:
        return None if self._pty is None else self._pty.path

    @property
    def link(self) -> str | None:
        return self.config.link

    @property
    def udp_address(self) -> Address | None:
        return None if self._udp is None else self._udp.address

    # -- inspection -----------------------------------------------------------------------
    @property
    def sim_time(self) -> float:
        with self._lock:
            return self.arm.time

    def snapshot(self) -> ArmSnapshot:
        with self._lock:
            arm = self.arm
            return ArmSnapshot(arm.time, arm.q, arm.qdot, arm.current_mA, arm.jaw_mm)

    def inject_fault(self, device_id: int, flag: HardwareStatus) -> None:
        """Raise a hardware fault flag on one device, as a failing joint would."""
        with self._lock:
            self.firmware.inject_fault(device_id, flag)

    def inject_stuck(self, stuck: StuckReading) -> None:
        """Make one device's reading stick at its value from `stuck.from_s` of arm time on
        (`reach_sim_bridge.emulator.faults.StuckReading`)."""
        with self._lock:
            self.firmware.inject_stuck(stuck)

    def observe(self, fn: Callable[[MotorArm, Firmware], T]) -> T:
        """Run `fn(arm, firmware)` between physics steps, for a consistent look at the state."""
        with self._lock:
            return fn(self.arm, self.firmware)

    def stats(self) -> ServerStats:
        with self._lock:
            c = self._counters
            bad: dict[str, int] = {}
            discarded = 0
            for dec in (self._pty_decoder, self._udp_decoder):
                s: DecoderStats = dec.stats
                discarded += s.bytes_discarded
                for reason, n in s.bad_frames.items():
                    if n:
                        bad[reason.value] = bad.get(reason.value, 0) + n
            return ServerStats(
                frames_in=c.frames_in,
                frames_out=c.frames_out,
                bytes_in=c.bytes_in,
                bytes_out=c.bytes_out,
                datagrams_in=c.datagrams_in,
                datagrams_out=c.datagrams_out,
                bad_frames=bad,
                bytes_discarded=discarded,
                firmware_errors=self.firmware.errors.snapshot(),
                ignored=self.firmware.ignored.snapshot(),
                dropped_frames=self._link_faults.dropped_frames,
                corrupted_bytes=self._link_faults.corrupted_bytes,
                lost_bytes=c.lost_bytes,
                collisions=c.collisions,
                collision_bytes=c.collision_bytes,
                collided_out=c.collided_out,
                stream_dropped=c.stream_dropped,
                replies_dropped=c.replies_dropped,
                queued_bytes=self._pty_queued,
                queued_peak_bytes=c.queued_peak_bytes,
                input_dropped_bytes=c.input_dropped_bytes,
                sim_time=self.arm.time,
                lag_s=c.lag_s,
            )

    def wait_sim_time(self, sim_time: float, timeout: float | None = None) -> bool:
        """Block until the arm's clock reaches `sim_time`; False on timeout or if stopped."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.sim_time < sim_time:
            if not self.running:
                return False
            if deadline is not None and time.monotonic() >= deadline:
                return False
            wait = (sim_time - self.sim_time) / self.config.speed
            time.sleep(min(max(wait, 0.001), 0.05))
        return True

    # -- the loop -------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # a bug: keep it for the owner, don't die silently
            self.error = exc
            log.exception("the simulator loop stopped on an error")

    def _loop(self) -> None:
        speed = self.config.speed
        dt = self.arm.dt
        self._anchor = None
        while not self._stop.is_set():
            if self._cycle_request.is_set():
                self._do_power_cycle()
            now = time.monotonic()
            with self._lock:
                if self._anchor is None:
                    self._anchor = (now, self.arm.time)
                wall0, sim0 = self._anchor
                behind = sim0 + (now - wall0) * speed - self.arm.time
                if behind > MAX_LAG_WALL_S * speed:
                    # The host cannot keep the pace: slow the sim down rather than run it
                    # in bursts that would starve the endpoints.
                    skipped = behind - dt
                    self._counters.lag_s += skipped
                    self._anchor = (wall0 + skipped / speed, sim0)
                    behind = dt
                steps = min(int(behind / dt + 1e-9), MAX_STEPS_PER_PASS)
                if steps > 0:
                    self._earn(steps * dt)
                    self._send_unprompted(self.firmware.steps(steps), now)
                    behind -= steps * dt
            self._take_input(now)
            self._flush(now)
            timeout = 0.0 if behind >= dt else max((dt - behind) / speed, MIN_WAIT_S)
            readers: list[int] = []
            writers: list[int] = []
            pty, udp = self._pty, self._udp
            if pty is not None:
                # Read only what the input credit lets us act on; without credit, the next
                # physics step (the timeout) earns some.
                if self._pty_credit <= 0.0 or self._pty_pending or self._pty_landed(now):
                    pass
                elif self._line_rate is None or self._rx_free - now < LINE_BUFFER_S:
                    readers.append(pty.fileno())
                else:  # the line is that far behind: leave the rest in the tty buffer
                    timeout = min(timeout, self._rx_free - now - LINE_BUFFER_S / 2)
                if self._pty_in and self._pty_credit > 0.0:
                    timeout = min(timeout, self._pty_in[0][0] - now)
                if self._pty_partial:
                    writers.append(pty.fileno())
                else:
                    due = self._pty_next_due()
                    if due is not None:
                        timeout = min(timeout, due - now)
            if udp is not None:
                if self._udp_credit > 0.0:
                    readers.append(udp.fileno())
                if self._udp_out:
                    timeout = min(timeout, self._udp_out[0][0] - now)
            ready, _, _ = select.select(readers, writers, [], max(timeout, 0.0))
            now = time.monotonic()
            if pty is not None and pty.fileno() in ready:
                data = pty.read(4096)
                if data:
                    self._arrive(data, now)
            if udp is not None and (udp.fileno() in ready or self._udp_credit <= 0.0):
                self._read_udp(udp, now, UDP_DATAGRAMS_PER_PASS)
            self._take_input(now)
            self._flush(now)
        self._drain()

    def _drain(self) -> None:
        """On stop: act on what already reached the arm, so a command sent just before the
        link went down is not lost at random (its replies still go out if they can). One
        more burst of credit and at most DRAIN_READS reads of each endpoint: a flood still
        going on cannot hold stop() up."""
        now = time.monotonic()
        self._pty_credit = max(self._pty_credit, 0.0) + INPUT_BURST
        self._udp_credit = max(self._udp_credit, 0.0) + INPUT_BURST
        self._take_input(math.inf)
        if self._pty is not None:
            for _ in range(DRAIN_READS):
                if self._pty_credit <= 0.0 or not (data := self._pty.read(4096)):
                    break
                self._arrive(data, now)
                self._take_input(math.inf)
        if self._udp is not None:
            self._read_udp(self._udp, math.inf, DRAIN_READS)
        self._flush(math.inf)


def serve_forever(server: SimServer, stop: threading.Event, stats_interval: float = 0.0) -> None:
    """Run until `stop` is set (signal handlers set it), logging stats now and then."""
    next_report = time.monotonic() + stats_interval
    while not stop.wait(0.2):
        if server.error is not None:
            raise RuntimeError("the simulator loop failed") from server.error
        if stats_interval > 0.0 and time.monotonic() >= next_report:
            next_report += stats_interval
            s = server.stats()
            log.info(
                "t=%.1f s: frames in %d out %d, bad %s, errors %s, ignored %s, lag %.2f s%s",
                s.sim_time,
                s.frames_in,
                s.frames_out,
                s.bad_frames or "{}",
                s.firmware_errors or "{}",
                s.ignored or "{}",
                s.lag_s,
                f", collisions {s.collisions} (arm frames lost {s.collided_out})"
                if server.config.half_duplex
                else "",
            )
