"""Serving the virtual Alpha 5 on a pty and/or UDP, paced to the wall clock.

One background thread owns the arm, the firmware and the endpoints: it advances physics to
where the (scaled) wall clock says sim time should be, reads whatever arrived, lets the
firmware answer, and writes replies out through the link faults, the added latency and the
serial line's byte rate. One thread means the firmware needs no locking against itself; a
lock only guards it against the inspection methods called from other threads.

Nothing a client sends can take that thread from the physics or make memory grow:

- Input budget. Each frame decoded (good or bad) and each reply made costs one unit; every
  sim second earns each endpoint INPUT_UNITS_PER_S units (at most INPUT_BURST banked), so
  the arm's clock keeps real time under any input. Without credit the pty is not read (a
  flood waits in the tty buffer, as its writer's own backlog), and UDP datagrams are read
  but dropped, as is the rest of a datagram once the credit runs out (counted in
  input_dropped_bytes; stale requests would only delay fresh ones). 8000 units/s is about
  seven times what a 115200 baud line carries: a client that fits a real line never notices.
- Output queue with --baud. Frames wait for the emulated line in two queues, replies ahead
  of the stream (heartbeats, status), together at most `out_queue_limit(baud)` bytes
  (OUT_QUEUE_S of wire time). When full, the oldest stream frames make room, then, for a
  reply, the oldest replies (a stream frame finding only replies is dropped). Drops are
  whole frames, counted in `stats()`. So a reply goes out within about OUT_QUEUE_S, unless
  newer replies push it out under a request flood, and the stream is never staler than
  that. Without --baud the pty's own buffer is the line (when full: lost_bytes).

Half duplex (`SimConfig(half_duplex=True)`, `reach-sim --half-duplex`): the pty is one RS-485
wire shared by the host and the arm, timed at `baud`, as the server sees the bytes:

- The arm does not start a frame while host bytes are still arriving: it waits until the
  line has been quiet for TURNAROUND_BYTES byte times after the host's last byte (the
  driver-enable turnaround of an RS-485 transceiver), then sends. Frames already queued go
  back to back, as one talker's.
- A host frame any byte of which arrives while the arm is sending collides: the host's frame
  is lost (never decoded, with whatever of it the arm held: `collisions` frames,
  `collision_bytes`), and so is the arm's frame on the wire (`collided_out`).
- The firmware's half duplex (a broadcast REQUEST that several devices answer gets no
  answer) comes with it. UDP is not a shared wire and is unaffected.
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

from protocol import DecodeError, HardwareStatus, Packet, PacketDecoder
from protocol.alpha5 import SERIAL_BAUD
from protocol.decoder import DecoderStats
from reach_sim_bridge.emulator.events import EventLog
from reach_sim_bridge.emulator.faults import FaultConfig, LinkFaults
from reach_sim_bridge.emulator.firmware import Firmware, FirmwareConfig
from reach_sim_bridge.emulator.pty import PtyEndpoint
from reach_sim_bridge.emulator.udp import Address, UdpEndpoint, is_loopback
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams

T = TypeVar("T")

log = logging.getLogger(__name__)

BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
MAX_STEPS_PER_PASS = 25  # physics steps between two looks at the endpoints
MAX_LAG_WALL_S = 0.25  # further behind than this, the sim slows down instead of catching up
MIN_WAIT_S = 0.0005
LINE_BUFFER_S = 0.25  # with --baud, stop reading the pty this far ahead of the line
OUT_QUEUE_S = 0.2  # with --baud, frames queued for the line: at most this much wire time
MIN_OUT_QUEUE_BYTES = 512  # ... but room for a broadcast request's answer on a slow line
INPUT_UNITS_PER_S = 8000  # input work per sim second and endpoint: frames + replies
INPUT_BURST = 400  # units banked at most (a burst a client may send at once)
UDP_DATAGRAMS_PER_PASS = 16  # read (or dropped, without credit) per look at the socket
DRAIN_READS = 16  # on stop, reads of each endpoint still acted on
#: Half duplex: byte times of quiet line after the host's last byte before the arm may talk
#: (at 115200 baud 0.35 ms; the driver's RS-485 transport waits 2 ms before it talks).
TURNAROUND_BYTES = 4


def out_queue_limit(baud: int) -> int:
    """Bytes the pty's outgoing queue holds at most at `baud`: OUT_QUEUE_S of wire time."""
    return max(int(OUT_QUEUE_S * baud / BITS_PER_BYTE), MIN_OUT_QUEUE_BYTES)


@dataclass(frozen=True)
class SimConfig:
    """How to serve the virtual arm. At least one of `pty` and `udp` must be on."""

    speed: float = 1.0  # sim seconds per wall second
    pty: bool = True
    link: str | None = None  # stable symlink to the pty, removed on stop
    udp: Address | None = None  # (host, port); port 0 picks a free one
    baud: int | None = None  # throttle the pty to this line rate (10 bits per byte)
    # The pty as one RS-485 wire (module docstring): needs the pty and its baud.
    half_duplex: bool = False
    start: tuple[float, float, float, float] | None = None  # E D C B, rad; None = mid pose
    jaw_mm: float = 5.0
    dt: float = 0.002  # physics (and firmware loop) step, sim seconds
    faults: FaultConfig = field(default_factory=FaultConfig)
    firmware: FirmwareConfig = field(default_factory=FirmwareConfig)
    seed: int | None = None  # link faults and sensor noise
    # The arm served (None: nominal); --randomize-params perturbs around it, and the
    # faults' torque scale multiplies its own.
    params: ArmParams | None = None

    def __post_init__(self) -> None:
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
                f"({SERIAL_BAUD} on the Alpha 5)"
            )
        if self.start is not None:
            if len(self.start) != 4 or not all(math.isfinite(v) for v in self.start):
                raise ValueError(f"start needs 4 finite angles E D C B (rad), got {self.start}")
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
    stream_dropped: int  # heartbeat/status frames dropped from the full --baud queue
    replies_dropped: int  # the oldest replies, pushed out of the full --baud queue
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


class _Counters:
    def __init__(self) -> None:
        self.frames_in = 0
        self.frames_out = 0
        self.bytes_in = 0
        self.bytes_out = 0
        self.datagrams_in = 0
        self.datagrams_out = 0
        self.lost_bytes = 0
        self.stream_dropped = 0
        self.replies_dropped = 0
        self.queued_peak_bytes = 0
        self.input_dropped_bytes = 0
        self.collisions = 0
        self.collision_bytes = 0
        self.collided_out = 0
        self.lag_s = 0.0


class SimServer:
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
        self._counters = _Counters()
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
        self._rx_free = 0.0  # when the serial line is next idle, each way
        self._tx_free = 0.0
        self._turnaround = 0.0 if cfg.baud is None else TURNAROUND_BYTES * BITS_PER_BYTE / cfg.baud
        self._rx_garbled = False  # half duplex: inside a host frame lost to a collision
        self._udp_out: deque[tuple[float, bytes, Address]] = deque()
        self._udp_peer: Address | None = None
        self._pty_credit = self._udp_credit = float(INPUT_BURST)  # input units, each end

    def _make_arm(self) -> Alpha5Arm:
        cfg = self.config
        arm = Alpha5Arm(params=cfg.params, dt=cfg.dt, seed=cfg.faults.randomize_seed)
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
        arm.torque_scale = np.asarray(arm.params.torque_scale) * np.asarray(cfg.faults.torque_scale)
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
            "virtual Alpha 5 serving%s%s at %gx real time",
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

    def observe(self, fn: Callable[[Alpha5Arm, Firmware], T]) -> T:
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

    # -- input ----------------------------------------------------------------------------
    def _earn(self, sim_s: float) -> None:
        earned = sim_s * INPUT_UNITS_PER_S
        self._pty_credit = min(self._pty_credit + earned, INPUT_BURST)
        self._udp_credit = min(self._udp_credit + earned, INPUT_BURST)

    def _pty_landed(self, now: float) -> bool:
        return bool(self._pty_in) and self._pty_in[0][0] <= now

    def _arrive(self, data: bytes, now: float) -> None:
        """Bytes the host wrote to the pty; with --baud each frame is acted on only when its
        last byte would have crossed the serial line."""
        rate = self._line_rate
        if rate is None:
            self._pty_in.append((now, data))
            return
        landed = max(self._rx_free, now)
        pos = 0
        while pos < len(data):
            end = data.find(0, pos)
            end = len(data) if end < 0 else end + 1
            began, landed = landed, landed + (end - pos) / rate
            piece = data[pos:end]
            if self.config.half_duplex and (began < self._tx_free or self._rx_garbled):
                self._collide(piece, landed)
            else:
                self._pty_in.append((landed, piece))
            pos = end
        self._rx_free = landed

    def _collide(self, piece: bytes, landed: float) -> None:
        """Half duplex: host bytes on the wire while the arm sends (or the rest of a frame
        that did). Both talkers' frames are lost: the host's, from what the arm held of it
        to its delimiter, and the arm's frame on the wire."""
        c = self._counters
        with self._lock:
            c.bytes_in += len(piece)
            c.collision_bytes += len(piece)
            if not self._rx_garbled:
                c.collisions += 1
                self._pty_in.append((landed, None))  # the decoder drops what it holds of it
            if self._pty_wire is not None:
                self._pty_wire = None
                c.collided_out += 1
        self._rx_garbled = not piece.endswith(b"\x00")

    def _read_udp(self, udp: UdpEndpoint, now: float, limit: int) -> None:
        """Up to `limit` datagrams: acted on while there is credit, then dropped (so what
        waits in the socket stays fresh)."""
        for _ in range(limit):
            batch = udp.receive(1)
            if not batch:
                return
            self._receive_datagram(*batch[0], now)

    def _take_input(self, now: float) -> None:
        """Act on the pty's frames, and decode what has landed, while there is credit; what
        is left waits for the credit the next physics steps earn."""
        while self._pty_credit > 0.0:
            if self._pty_pending:
                self._act(self._pty_pending.popleft(), None, now)
            elif self._pty_landed(now):
                self._decode_stream(self._pty_in.popleft()[1])
            else:
                return

    def _on_decode_error(self, error: DecodeError, frame: bytes) -> None:
        # Called from feed(), under the lock, in the loop thread.
        self._link_errors.record(
            f"bad_frame_{error.reason.value}",
            f"{error} ({len(frame)} bytes: {frame[:16].hex(' ')})",
        )
        self.firmware.note_link_error(error)

    def _decode(self, decoder: PacketDecoder, data: bytes) -> tuple[list[Packet], int]:
        """Under the lock: the packets in `data` and the frames (good or bad) it held."""
        stats = decoder.stats
        seen = stats.good_frames + stats.bad_total
        packets = decoder.feed(data)
        return packets, stats.good_frames + stats.bad_total - seen

    def _decode_stream(self, data: bytes | None) -> None:
        if data is None:  # lost in a collision: so is what the decoder held of that frame
            with self._lock:
                self._pty_decoder.reset()
            return
        with self._lock:
            self._counters.bytes_in += len(data)
            packets, frames = self._decode(self._pty_decoder, data)
            self._counters.frames_in += len(packets)
        self._pty_credit -= frames
        self._pty_pending.extend(packets)

    def _receive_datagram(self, data: bytes, sender: Address, now: float) -> None:
        """Act on a datagram's frames in order while there is credit; drop the rest."""
        size = len(data)
        c = self._counters
        with self._lock:
            c.datagrams_in += 1
            c.bytes_in += size
        if not data.endswith(b"\x00"):
            data += b"\x00"  # a datagram ends its last frame
        pos = 0
        while pos < size:
            if self._udp_credit <= 0.0:
                c.input_dropped_bytes += size - pos
                return
            end = data.index(0, pos) + 1
            with self._lock:
                packets, _ = self._decode(self._udp_decoder, data[pos:end])
                c.frames_in += len(packets)
                if packets:  # only a sender of a valid frame gets the stream (see udp.py)
                    self._udp_peer = sender
            self._udp_credit -= 1  # a frame, a bad one, or a stray delimiter
            for packet in packets:
                self._act(packet, sender, now)
            pos = end

    def _act(self, packet: Packet, sender: Address | None, now: float) -> None:
        """Let the firmware act on one packet and queue its replies to where it came from."""
        with self._lock:
            replies = self.firmware.handle(packet)
        if not replies:
            return
        due = now + self.config.faults.latency_ms / 1000.0
        if sender is None:
            self._pty_credit -= len(replies)
            for reply in replies:
                self._queue_pty(reply, due, stream=False)
        else:
            self._udp_credit -= len(replies)
            for reply in replies:
                self._queue_udp(reply, due, sender)

    # -- output ---------------------------------------------------------------------------
    def _send_unprompted(self, packets: list[Packet], now: float) -> None:
        """Heartbeats and status go to the pty and to the UDP peer (the last sender of a
        valid frame)."""
        if not packets:
            return
        due = now + self.config.faults.latency_ms / 1000.0
        for packet in packets:
            if self._pty is not None:
                self._queue_pty(packet, due, stream=True)
            if self._udp is not None and self._udp_peer is not None:
                self._queue_udp(packet, due, self._udp_peer)

    def _queue_pty(self, packet: Packet, ready: float, stream: bool) -> None:
        """Queue a frame for the pty; with --baud within out_queue_limit: the oldest stream
        frames make room, then (for a reply) the oldest replies; a stream frame that finds
        the queue full of replies is dropped."""
        frame = self._link_faults.apply(packet.encode())
        if frame is None:
            return
        size = len(frame)
        limit = self._out_limit
        if limit is not None:
            c = self._counters
            while self._pty_queued + size > limit and self._pty_stream:
                self._pty_queued -= len(self._pty_stream.popleft()[1])
                c.stream_dropped += 1
            if self._pty_queued + size > limit and stream:
                c.stream_dropped += 1  # replies fill the queue: they go first
                return
            while self._pty_queued + size > limit and self._pty_replies:
                self._pty_queued -= len(self._pty_replies.popleft()[1])
                c.replies_dropped += 1  # the oldest: its requester has likely given up
            c.queued_peak_bytes = max(c.queued_peak_bytes, self._pty_queued + size)
        self._pty_queued += size
        (self._pty_stream if stream else self._pty_replies).append((ready, frame))

    def _pty_next(self, now: float) -> tuple[float, bytes] | None:
        """Take the frame the line sends next if one is ready by `now`: (when its last byte
        has crossed the line, frame). The line starts a frame when it is free, the waiting
        reply if one was ready by then, else the oldest stream frame."""
        replies, stream = self._pty_replies, self._pty_stream
        first = self._pty_first_ready()
        if first is None or first > now:
            return None
        rate = self._line_rate
        start = first if rate is None else max(self._tx_free, first)
        if self.config.half_duplex:
            start = max(start, now)  # the wire is the host's until now: no sending in the past
        queue = replies if replies and replies[0][0] <= start else stream
        _, frame = queue.popleft()
        self._pty_queued -= len(frame)
        if rate is None:
            return start, frame
        self._tx_free = start + len(frame) / rate
        return self._tx_free, frame

    def _pty_next_due(self) -> float | None:
        """When the pty output next needs the loop (None: nothing to send)."""
        if self._pty_wire is not None:
            return self._pty_wire[0]
        return self._pty_first_ready()

    def _pty_first_ready(self) -> float | None:
        """When the first queued frame may start: when it is ready, and in half duplex not
        before the host's bytes have landed and the turnaround has passed."""
        heads = [q[0][0] for q in (self._pty_replies, self._pty_stream) if q]
        if not heads:
            return None
        if self.config.half_duplex:
            return max(min(heads), self._rx_free + self._turnaround)
        return min(heads)

    def _clear_pty_out(self) -> None:
        self._pty_replies.clear()
        self._pty_stream.clear()
        self._pty_queued = 0
        self._pty_wire = None
        self._pty_partial = b""

    def _queue_udp(self, packet: Packet, due: float, address: Address) -> None:
        frame = self._link_faults.apply(packet.encode())
        if frame is not None:
            self._udp_out.append((due, frame, address))

    def _flush(self, now: float) -> None:
        pty, udp, c = self._pty, self._udp, self._counters
        if pty is not None:
            while True:
                if self._pty_partial:
                    written = pty.write(self._pty_partial)
                    if written == 0:
                        # Buffer full: nobody is reading. A serial line loses these bytes too.
                        wire = self._pty_wire
                        c.lost_bytes += len(self._pty_partial) + self._pty_queued
                        c.lost_bytes += 0 if wire is None else len(wire[1])
                        self._clear_pty_out()
                        break
                    c.bytes_out += written
                    self._pty_partial = self._pty_partial[written:]
                    continue
                if self._pty_wire is None:
                    self._pty_wire = self._pty_next(now)
                    if self._pty_wire is None:
                        break
                due, frame = self._pty_wire
                if due > now:
                    break
                self._pty_wire = None
                self._pty_partial = frame
                c.frames_out += 1
        if udp is not None:
            while self._udp_out and self._udp_out[0][0] <= now:
                _, frame, address = self._udp_out.popleft()
                c.frames_out += 1
                if udp.send(frame, address):
                    c.bytes_out += len(frame)
                    c.datagrams_out += 1
                else:
                    c.lost_bytes += len(frame)


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
