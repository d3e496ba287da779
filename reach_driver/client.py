"""The arm client: a reader thread, live state, matched requests, safe commands, a watchdog.

    with ArmClient(open_transport("/dev/ttyUSB0")).start() as arm:
        arm.request(DeviceID.E, [PacketID.POSITION])
        arm.command_positions([3.1, 1.5, 1.5, 3.0])

One thread owns the transport: it reads and decodes, updates the state table, answers
waiting requests by (device, packet id), feeds subscribers, runs the watchdog and the
keepalive, and reopens the link with backoff when it is lost. Commands are written from the
caller's thread; while the link is down they fail at once with `LinkDownError`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from protocol import (
    DecoderStats,
    DeviceID,
    HardwareStatus,
    Mode,
    Packet,
    PacketDecoder,
    PacketID,
    ProtocolError,
    commands,
)
from protocol.alpha5 import ALL_DEVICES, JAW, JOINTS, Range
from reach_driver.errors import (
    DriverError,
    GarbageError,
    LimitError,
    LinkDownError,
    NoResponseError,
    RequestTimeoutError,
    TransportError,
    WatchdogTrippedError,
)
from reach_driver.link import (
    Backoff,
    ClientEvent,
    EventCallback,
    EventKind,
    LinkConfig,
    LinkState,
)
from reach_driver.listeners import ListenerSet, PacketListener, PacketQueue, Subscription
from reach_driver.safety import LimitKind, SafetyConfig, SafetyGuard
from reach_driver.state import ArmState, JointState, StateTable, joint_name
from reach_driver.transport import Transport

log = logging.getLogger(__name__)

CONTROL_PACKETS = frozenset({PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT})
CONTINUOUS: dict[int, LimitKind] = {
    PacketID.VELOCITY: LimitKind.VELOCITY,
    PacketID.CURRENT: LimitKind.CURRENT,
}
LIMIT_KIND_OF: dict[int, LimitKind] = {kind.packet_id: kind for kind in LimitKind}
MAX_REQUEST_IDS = 10
EVENT_HISTORY = 200
#: Flags that only say the arm saw noise on the line; they clear by themselves.
LINK_ERROR_FLAGS = HardwareStatus.SERIAL_ERROR | HardwareStatus.CRC_ERROR


@dataclass
class ClientStats:
    """Counters for the monitor and for tests (link errors are in transport/decoder stats)."""

    packets: int = 0
    requests_sent: int = 0
    request_retries: int = 0
    request_timeouts: int = 0
    link_drops: int = 0
    reconnects: int = 0
    watchdog_trips: int = 0
    keepalives: int = 0


class _Waiter:
    """One outstanding request: the (device, packet id) pairs still wanted."""

    def __init__(self, wanted: Iterable[tuple[int, int]]) -> None:
        self.wanted = set(wanted)
        self.got: dict[tuple[int, int], Packet] = {}
        self.event = threading.Event()
        self.error: DriverError | None = None

    def offer(self, packet: Packet) -> None:
        key = (int(packet.device_id), int(packet.packet_id))
        if key in self.wanted:
            self.wanted.discard(key)
            self.got[key] = packet
            if not self.wanted:
                self.event.set()

    def fail(self, error: DriverError) -> None:
        self.error = error
        self.event.set()


@dataclass(frozen=True)
class _Stream:
    ids: tuple[int, ...]
    hz: int
    devices: tuple[int, ...]


class ArmClient:
    """Talks to one arm over one transport. See the module docstring."""

    def __init__(
        self,
        transport: Transport,
        *,
        safety: SafetyConfig | None = None,
        link: LinkConfig | None = None,
        devices: Sequence[int] = ALL_DEVICES,
        request_timeout_s: float = 0.1,
        retries: int = 2,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.transport = transport
        self.guard = SafetyGuard(safety)
        self.link_config = link or LinkConfig()
        self.devices = tuple(int(d) for d in devices)
        self.request_timeout_s = request_timeout_s
        self.retries = retries
        self.clock = clock
        self.table = StateTable()
        self.decoder = PacketDecoder()
        self.listeners = ListenerSet()
        self.stats = ClientStats()
        self.events: deque[ClientEvent] = deque(maxlen=EVENT_HISTORY)
        self.found_devices: tuple[int, ...] = ()
        self.warnings: list[str] = []
        self._event_callbacks: list[EventCallback] = []
        self._lock = threading.RLock()
        self._write_lock = threading.Lock()
        self._waiters: dict[tuple[int, int], list[_Waiter]] = {}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._link = LinkState.CLOSED
        self._link_reason = ""
        self._link_since = 0.0
        self._backoff = Backoff(self.link_config.backoff_initial_s, self.link_config.backoff_max_s)
        self._probe_deadline = 0.0
        self._last_packet_t = -math.inf
        self._last_keepalive_t = -math.inf
        self._contact = False
        # watchdog: devices under continuous (velocity/current) command -> time armed
        self._armed: dict[int, float] = {}
        self._last_command_t = -math.inf
        self._tripped: str | None = None
        self._safe_pending = False
        self._stream: _Stream | None = None
        self._faults: dict[int, HardwareStatus] = {}

    # ----------------------------------------------------------------- lifecycle

    def start(self, *, discover: bool = True, read_limits: bool = True) -> ArmClient:
        """Open the link, start the reader, find the devices and read their limits.

        Raises `NoResponseError` (or `GarbageError` when bytes arrive but never decode, the
        sign of a wrong baud rate) if no device answers; the link is closed again then.
        """
        if self._thread is not None:
            return self
        if not self.transport.is_open:
            self.transport.open()
        now = self.clock()
        self._set_link(LinkState.UP, "opened", now)
        self._last_packet_t = now
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run, name=f"reach-driver reader {self.transport.url}", daemon=True
        )
        self._thread.start()
        try:
            if discover:
                self.discover()
            if read_limits and self.found_devices:
                self.read_limits()
        except BaseException:
            self.close(safe=False)
            raise
        return self

    def close(self, *, safe: bool = True) -> None:
        """Leave the arm safe (stop streaming, safe mode on joints under continuous command),
        stop the reader and close the link. Safe to call twice."""
        if safe and self._link is LinkState.UP:
            try:
                if self._armed:
                    self._send_safe_mode(tuple(self._armed))
                if self._stream is not None:
                    self.stop_stream()
            except DriverError as exc:
                log.warning("could not leave the arm safe while closing: %s", exc)
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        self.transport.close()
        self._set_link(LinkState.CLOSED, "closed", self.clock())
        with self._lock:
            for waiters in self._waiters.values():
                for w in waiters:
                    w.fail(LinkDownError(f"client for {self.transport.url} closed"))
            self._waiters.clear()

    def __enter__(self) -> ArmClient:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- state and events

    @property
    def state(self) -> ArmState:
        return self.table.snapshot(self.clock())

    def joint(self, device: int) -> JointState:
        return self.table.get(int(device))

    @property
    def link_state(self) -> LinkState:
        return self._link

    @property
    def link_reason(self) -> str:
        return self._link_reason

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    @property
    def tripped(self) -> str | None:
        """Why the watchdog tripped, or None while it has not (or after `rearm()`)."""
        return self._tripped

    def blocking_faults(self) -> dict[int, list[str]]:
        """Status flags, by device, that say a joint must not be driven (motor, driver,
        encoder, pressure...), from the last HARDWARE_STATUS each device sent; link error
        flags are left out."""
        with self._lock:
            faults = dict(self._faults)
        out: dict[int, list[str]] = {}
        for dev, flags in faults.items():
            serious = flags & ~LINK_ERROR_FLAGS
            if serious:
                out[dev] = serious.flag_names() or [f"0x{int(serious):08X}"]
        return out

    def on_event(self, callback: EventCallback) -> None:
        self._event_callbacks.append(callback)

    def subscribe(self, listener: PacketListener) -> Subscription:
        """Call `listener(packet, arrival_time)` on the reader thread for every packet."""
        return self.listeners.add(listener)

    def listen(self, maxsize: int = 10000) -> PacketQueue:
        """A queue of every packet from now on; close it (or use `with`) to unsubscribe."""
        q = PacketQueue(maxsize)
        q.subscription = self.listeners.add(q)
        return q

    def _emit(self, kind: EventKind, message: str, device: int | None = None) -> None:
        event = ClientEvent(kind, self.clock(), message, device)
        self.events.append(event)
        quiet = kind in (EventKind.LINK_UP, EventKind.FAULT_CLEARED)
        level = logging.INFO if quiet else logging.WARNING
        log.log(level, "%s: %s", kind.value, message)
        for callback in list(self._event_callbacks):
            try:
                callback(event)
            except Exception:
                log.exception("event callback %r failed", callback)

    # ----------------------------------------------------------------- requests

    def request(
        self,
        device: int,
        ids: Sequence[int],
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> dict[int, Packet]:
        """Ask one device for packets; returns {packet id: reply}.

        Replies are matched by device *and* packet id. Missing ones are asked for again up
        to `retries` times; then `RequestTimeoutError` names what never came.
        """
        got = self.request_many([device], ids, timeout_s=timeout_s, retries=retries)
        return got[int(device)]

    def request_many(
        self,
        devices: Sequence[int],
        ids: Sequence[int],
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
        partial: bool = False,
    ) -> dict[int, dict[int, Packet]]:
        """The same packet ids from several devices, all requests written at once.

        With `partial=True` devices that never answer are left out instead of raising.
        """
        devs = [int(d) for d in devices]
        pids = [int(i) for i in ids]
        if not devs or not pids:
            raise ValueError("request needs at least one device and one packet id")
        if DeviceID.BROADCAST in devs:
            raise ValueError(
                "broadcast REQUEST: every joint answers at once (collisions on RS-485) and the "
                "replies cannot be told apart from a timeout; request each device instead"
            )
        if len(devs) > 1 and not self.transport.broadcast_ok:
            # Half duplex: one device at a time, or the replies collide with our requests.
            merged: dict[int, dict[int, Packet]] = {}
            for d in devs:
                merged.update(
                    self.request_many(
                        [d], pids, timeout_s=timeout_s, retries=retries, partial=partial
                    )
                )
            return merged
        timeout = self.request_timeout_s if timeout_s is None else timeout_s
        attempts = 1 + (self.retries if retries is None else retries)
        wanted = {(d, p) for d in devs for p in pids}
        got: dict[tuple[int, int], Packet] = {}
        for attempt in range(attempts):
            waiter = _Waiter(wanted)
            self._add_waiter(waiter)
            try:
                frames = []
                for d in devs:
                    missing = [p for p in pids if (d, p) in wanted]
                    for start in range(0, len(missing), MAX_REQUEST_IDS):
                        chunk = missing[start : start + MAX_REQUEST_IDS]
                        frames.append(commands.request(d, chunk).encode())
                self._write(frames)
                self.stats.requests_sent += len(frames)
                if attempt:
                    self.stats.request_retries += len(frames)
                waiter.event.wait(timeout)
            finally:
                self._remove_waiter(waiter)
            got.update(waiter.got)
            wanted = waiter.wanted
            if waiter.error is not None:
                raise waiter.error
            if not wanted:
                break
        if wanted and not partial:
            self.stats.request_timeouts += 1
            never = ", ".join(
                f"{joint_name(d)}: {_pid_names(p for dd, p in sorted(wanted) if dd == d)}"
                for d in sorted({d for d, _ in wanted})
            )
            raise RequestTimeoutError(
                f"no reply on {self.transport.url} after {attempts} attempt(s) of "
                f"{timeout:.3g} s from {never}"
            )
        out: dict[int, dict[int, Packet]] = {}
        for (d, p), packet in got.items():
            out.setdefault(d, {})[p] = packet
        if not partial:
            for d in devs:
                out.setdefault(d, {})
        return out

    def _add_waiter(self, waiter: _Waiter) -> None:
        with self._lock:
            for key in waiter.wanted:
                self._waiters.setdefault(key, []).append(waiter)

    def _remove_waiter(self, waiter: _Waiter) -> None:
        with self._lock:
            for key in list(self._waiters):
                items = self._waiters[key]
                if waiter in items:
                    items.remove(waiter)
                if not items:
                    del self._waiters[key]

    # ----------------------------------------------------------------- discovery and info

    def discover(self, devices: Sequence[int] | None = None) -> tuple[int, ...]:
        """Find which devices answer (a MODE request each); raises if none does."""
        devs = list(devices or self.devices)
        before = self.decoder.stats.good_frames, self.decoder.stats.bytes_received
        got = self.request_many(devs, [PacketID.MODE], partial=True)
        self.found_devices = tuple(d for d in devs if d in got)
        if not self.found_devices:
            stats = self.decoder.stats
            received = stats.bytes_received - before[1]
            waited = self.request_timeout_s * (1 + self.retries)
            baud = getattr(self.transport, "baud", None)
            if received and stats.good_frames == before[0]:
                raise GarbageError(
                    f"{received} bytes arrived on {self.transport.url} in {waited:.2g} s but "
                    f"none decoded as a BPL frame ({stats.bad_total} bad frames)"
                    + (f": wrong baud rate? (using {baud})" if baud else "")
                )
            raise NoResponseError(
                f"nothing answered on {self.transport.url} within {waited:.2g} s "
                f"(asked devices {', '.join(joint_name(d) for d in devs)}): is the arm powered "
                "and is this its port or address?"
            )
        return self.found_devices

    def read_limits(
        self, devices: Sequence[int] | None = None
    ) -> dict[int, dict[LimitKind, Range]]:
        """Read position, velocity and current limits; the safety guard adopts them.

        A device that does not report a limit keeps the documented default (and a warning
        is recorded in `warnings`).
        """
        devs = list(devices or self.found_devices or self.devices)
        kinds = list(LimitKind)
        for d in devs:
            for kind in kinds:
                self.table.forget(d, kind.packet_id)
        got = self.request_many(devs, [k.packet_id for k in kinds], partial=True)
        out: dict[int, dict[LimitKind, Range]] = {}
        for d in devs:
            js = self.table.get(d)
            for kind in kinds:
                reading = getattr(js, f"{kind.value}_limits")
                if reading is not None and kind.packet_id in got.get(d, {}):
                    self.guard.set_arm_limit(d, kind, reading.value)
                    out.setdefault(d, {})[kind] = reading.value
                elif not self.guard.has_arm_limit(d, kind):
                    self.warnings.append(
                        f"{joint_name(d)} did not report its {kind.value} limits; "
                        "using the documented defaults"
                    )
        return out

    def write_limits(self, device: int, kind: LimitKind, maximum: float, minimum: float) -> Range:
        """Set one limit on the arm, read it back and adopt what the arm reports."""
        self._write([commands.limits(int(device), kind.packet_id, maximum, minimum).encode()])
        self.table.forget(int(device), kind.packet_id)
        reply = self.request(device, [kind.packet_id])[kind.packet_id]
        lo, hi = sorted(reply.floats())
        self.guard.set_arm_limit(device, kind, (lo, hi))
        return (lo, hi)

    def read_info(self, devices: Sequence[int] | None = None) -> dict[int, JointState]:
        """Versions, serial and model numbers, modes and status flags of each device."""
        devs = list(devices or self.found_devices or self.devices)
        ids = [
            PacketID.MODE,
            PacketID.SOFTWARE_VERSION,
            PacketID.SERIAL_NUMBER,
            PacketID.MODEL_NUMBER,
            PacketID.HARDWARE_STATUS,
        ]
        self.request_many(devs, ids, partial=True)
        return {d: self.table.get(d) for d in devs}

    def read_status(self, devices: Sequence[int] | None = None) -> dict[int, list[str]]:
        """Hardware status flags by name for each device that answers ([] when healthy)."""
        devs = list(devices or self.found_devices or self.devices)
        self.request_many(devs, [PacketID.HARDWARE_STATUS], partial=True)
        out = {}
        for d in devs:
            js = self.table.get(d)
            if js.status is not None:
                out[d] = js.fault_names
        return out

    def read_joints(self, ids: Sequence[int] = (PacketID.POSITION, PacketID.VELOCITY)) -> ArmState:
        """Poll the four joints once (one write) and return the fresh state."""
        self.request_many(JOINTS, ids)
        return self.state

    # ----------------------------------------------------------------- streaming

    def stream(
        self,
        ids: Sequence[int] = (PacketID.POSITION, PacketID.VELOCITY),
        hz: int = 20,
        devices: Sequence[int] = JOINTS,
    ) -> None:
        """Have each device send `ids` at `hz` (its heartbeat), re-applied after a reconnect.

        Each device is addressed on its own (no broadcast: the jaw would stream too, and on
        RS-485 every joint would answer at once).
        """
        if not 1 <= hz <= 255:
            raise ValueError(f"heartbeat frequency must be 1..255 Hz, got {hz}")
        self._stream = _Stream(tuple(int(i) for i in ids), int(hz), tuple(int(d) for d in devices))
        self._write(self._stream_frames(self._stream))

    def stop_stream(self) -> None:
        stream, self._stream = self._stream, None
        if stream is None:
            return
        frames = [commands.heartbeat_frequency(d, 0).encode() for d in stream.devices]
        frames += [commands.heartbeat_set(d, []).encode() for d in stream.devices]
        self._write(frames)

    @staticmethod
    def _stream_frames(stream: _Stream) -> list[bytes]:
        frames = [commands.heartbeat_set(d, stream.ids).encode() for d in stream.devices]
        frames += [commands.heartbeat_frequency(d, stream.hz).encode() for d in stream.devices]
        return frames

    # ----------------------------------------------------------------- commands

    def send(self, *packets: Packet) -> None:
        """Write packets as they are, after the same safety checks as the command helpers."""
        for p in packets:
            self._check_packet(p)
        self._write([p.encode() for p in packets])
        self._note_commands(packets)

    def set_mode(self, devices: int | Sequence[int], mode: Mode) -> None:
        devs = [devices] if isinstance(devices, int) else list(devices)
        self._write([commands.mode(int(d), mode).encode() for d in devs])
        if mode not in (Mode.VELOCITY, Mode.CURRENT):
            self._disarm(devs)

    def command_position(self, device: int, value: float) -> None:
        """Absolute position (rad; mm for the jaw); refused outside the position limit."""
        self._positions([int(device)], [float(value)])

    def command_positions(self, q: Sequence[float] | np.ndarray) -> None:
        """Positions of E D C B; all are checked before any is sent."""
        self._positions(JOINTS, _four(q))

    def _positions(self, devices: Sequence[int], values: Sequence[float]) -> None:
        for d, v in zip(devices, values, strict=True):
            self._check_device(int(d))
            self.guard.check(int(d), LimitKind.POSITION, v)
        self.send(*(commands.position(int(d), v) for d, v in zip(devices, values, strict=True)))

    def command_jaw(self, mm: float) -> None:
        self.command_position(JAW, mm)

    def command_velocity(self, device: int, value: float) -> float:
        return float(self.command_velocities_for([int(device)], [value])[0])

    def command_velocities(self, v: Sequence[float] | np.ndarray) -> np.ndarray:
        """Velocities of E D C B after the soft barrier (what was actually sent)."""
        return self.command_velocities_for(JOINTS, _four(v))

    def command_velocities_for(
        self, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> np.ndarray:
        return self._continuous(PacketID.VELOCITY, devices, values)

    def command_current(self, device: int, milliamps: float) -> float:
        return float(self._continuous(PacketID.CURRENT, [int(device)], [milliamps])[0])

    def command_currents(self, currents_mA: Sequence[float] | np.ndarray) -> np.ndarray:
        """Currents of E D C B in mA after the soft barrier (what was actually sent)."""
        return self._continuous(PacketID.CURRENT, JOINTS, _four(currents_mA))

    def _continuous(
        self, pid: PacketID, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> np.ndarray:
        if self._tripped is not None:
            raise WatchdogTrippedError(
                f"watchdog tripped ({self._tripped}); the arm was put in "
                f"{self.guard.config.safe_mode.name}; call rearm() to command again"
            )
        kind = CONTINUOUS[pid]
        devs = [int(d) for d in devices]
        vals = [float(v) for v in values]
        if len(devs) != len(vals):
            raise ValueError(f"{len(devs)} devices but {len(vals)} values")
        sent = np.empty(len(vals))
        for i, (d, v) in enumerate(zip(devs, vals, strict=True)):
            self._check_device(d)
            self.guard.check(d, kind, v)
            pos = self.table.get(d).position
            sent[i] = self.guard.soften(d, None if pos is None else pos.value, v)
        builder = commands.current if pid is PacketID.CURRENT else commands.velocity
        self._write([builder(d, float(v)).encode() for d, v in zip(devs, sent, strict=True)])
        now = self.clock()
        with self._lock:
            self._last_command_t = now
            for d in devs:
                self._armed.setdefault(d, now)
        return sent

    def _check_device(self, device: int) -> None:
        if device == DeviceID.BROADCAST:
            raise LimitError(
                "refused: broadcast position/velocity/current commands bypass per-joint "
                "limits; address each joint; nothing was sent"
            )

    def _check_packet(self, packet: Packet) -> None:
        pid, dev = packet.packet_id, int(packet.device_id)
        if pid in CONTROL_PACKETS:
            self._check_device(dev)
            value = packet.as_float()
            if pid == PacketID.POSITION:
                self.guard.check(dev, LimitKind.POSITION, value)
            else:
                if self._tripped is not None:
                    raise WatchdogTrippedError(f"watchdog tripped ({self._tripped}); rearm() first")
                self.guard.check(dev, CONTINUOUS[pid], value)
                pos = self.table.get(dev).position
                if self.guard.soften(dev, None if pos is None else pos.value, value) != value:
                    raise LimitError(
                        f"refused: {_pid_names([pid]).lower()} {value:.4g} for joint "
                        f"{joint_name(dev)} "
                        "pushes past its position limit (inside the soft barrier); use "
                        "command_currents/command_velocities to have it scaled; nothing was sent"
                    )
        elif (
            not self.transport.broadcast_ok
            and dev == DeviceID.BROADCAST
            and pid
            in (
                PacketID.REQUEST,
                PacketID.HEARTBEAT_SET,
                PacketID.HEARTBEAT_FREQUENCY,
            )
        ):
            raise ValueError(
                f"broadcast {_pid_names([pid])} on half-duplex {self.transport.url}: every "
                "joint would answer at once and collide; address each device"
            )

    def _note_commands(self, packets: Iterable[Packet]) -> None:
        now = self.clock()
        with self._lock:
            for p in packets:
                dev = int(p.device_id)
                if p.packet_id in CONTINUOUS:
                    self._last_command_t = now
                    self._armed.setdefault(dev, now)
                elif p.packet_id == PacketID.POSITION:
                    self._armed.pop(dev, None)
                elif (
                    p.packet_id == PacketID.MODE
                    and p.data
                    and p.data[0]
                    not in (
                        Mode.VELOCITY,
                        Mode.CURRENT,
                    )
                ):
                    self._armed.pop(dev, None)

    def _disarm(self, devices: Iterable[int]) -> None:
        with self._lock:
            for d in devices:
                self._armed.pop(int(d), None)

    def safe_stop(self, devices: Sequence[int] | None = None) -> None:
        """Put joints (default: the four joints and the jaw) in the configured safe mode."""
        self._send_safe_mode(tuple(devices or (*JOINTS, JAW)))

    def rearm(self) -> None:
        """Allow velocity/current commands again after a watchdog trip."""
        with self._lock:
            self._tripped = None

    def _send_safe_mode(self, devices: Sequence[int]) -> None:
        mode = self.guard.config.safe_mode
        self._write([commands.mode(int(d), mode).encode() for d in devices])
        self._disarm(devices)

    # ----------------------------------------------------------------- writing

    def _write(self, frames: Sequence[bytes], *, internal: bool = False) -> float:
        """Write frames in one go; returns the time the write completed."""
        if not internal and self._link is not LinkState.UP:
            raise LinkDownError(self._down_message())
        with self._write_lock:
            try:
                self.transport.write_frames(frames)
            except TransportError as exc:
                self._link_lost(str(exc))
                raise LinkDownError(self._down_message()) from None
        return self.clock()

    def write_frames(self, frames: Sequence[bytes]) -> float:
        """Raw, unchecked frames (for tools and tests); returns the write completion time."""
        return self._write(frames)

    def _down_message(self) -> str:
        if self._link is LinkState.CLOSED:
            why = f" ({self._link_reason})" if "crashed" in self._link_reason else ""
            return f"client for {self.transport.url} is not running{why}; start() it first"
        age = self.clock() - self._link_since
        return (
            f"link to {self.transport.url} is {self._link.value} since {age:.2f} s "
            f"({self._link_reason}); reconnecting, attempt {self._backoff.attempt}; "
            "nothing was sent"
        )

    # ----------------------------------------------------------------- the reader thread

    def _run(self) -> None:
        try:
            self._read_loop()
        except Exception as exc:  # a bug: make commands fail fast instead of hanging
            log.exception("reader thread of %s crashed", self.transport.url)
            with self._lock:
                self._set_link(LinkState.CLOSED, f"reader thread crashed: {exc!r}", self.clock())
                waiters = [w for ws in self._waiters.values() for w in ws]
            for w in waiters:
                w.fail(LinkDownError(self._down_message()))
            self._emit(EventKind.LINK_DOWN, f"reader thread crashed: {exc!r}")

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            if self._link is LinkState.DOWN:
                self._reconnect_attempt()
                continue
            try:
                chunk = self.transport.read()
            except TransportError as exc:
                self._link_lost(str(exc))
                continue
            now = self.clock()
            if chunk:
                for packet in self.decoder.feed(chunk):
                    self._dispatch(packet, now)
            self._duties(self.clock())

    def _dispatch(self, packet: Packet, t: float) -> None:
        self.stats.packets += 1
        self._last_packet_t = t
        if self._link is LinkState.PROBING:
            self._link_restored(t)
        self._contact = True
        pid = packet.packet_id
        if self.table.update(packet, t):
            if pid in (
                PacketID.POSITION_LIMITS,
                PacketID.VELOCITY_LIMITS,
                PacketID.CURRENT_LIMITS,
            ):
                kind = LIMIT_KIND_OF[int(pid)]
                reading = getattr(self.table.get(int(packet.device_id)), f"{kind.value}_limits")
                if reading is not None:
                    self.guard.set_arm_limit(int(packet.device_id), kind, reading.value)
            elif pid == PacketID.HARDWARE_STATUS:
                self._note_status(packet)
        key = (int(packet.device_id), int(pid))
        with self._lock:
            waiters = list(self._waiters.get(key, ()))
        for w in waiters:
            w.offer(packet)
        self.listeners.dispatch(packet, t)

    def _note_status(self, packet: Packet) -> None:
        try:
            flags = HardwareStatus.from_bytes(packet.data)
        except ProtocolError:
            return
        dev = int(packet.device_id)
        with self._lock:
            before = self._faults.get(dev, HardwareStatus.NONE)
            if flags == before:
                return
            self._faults[dev] = flags
        if flags:
            names = ", ".join(flags.flag_names()) or f"0x{int(flags):08X}"
            self._emit(EventKind.FAULT, f"{joint_name(dev)} reports {names}", dev)
        else:
            self._emit(EventKind.FAULT_CLEARED, f"{joint_name(dev)} status clear", dev)

    def _duties(self, now: float) -> None:
        cfg = self.link_config
        if self._link is LinkState.PROBING:
            if now > self._probe_deadline:
                self.transport.close()
                self._set_link(
                    LinkState.DOWN, f"no answer within {cfg.probe_timeout_s} s after reopening", now
                )
            return
        if self._link is not LinkState.UP:
            return
        self._watchdog(now)
        silent = now - self._last_packet_t
        if self._contact and silent > cfg.stale_link_s:
            self._link_lost(f"no valid packet for {silent:.2f} s")
            return
        if (
            self._contact
            and silent > cfg.keepalive_s
            and now - self._last_keepalive_t > cfg.keepalive_s
        ):
            self._last_keepalive_t = now
            self.stats.keepalives += 1
            try:
                self._write([self._probe_frame()], internal=True)
            except LinkDownError:
                pass

    def _probe_frame(self) -> bytes:
        device = (self.found_devices or self.devices)[0]
        return commands.request(device, [PacketID.MODE]).encode()

    # ----------------------------------------------------------------- watchdog

    def _watchdog(self, now: float) -> None:
        limit = self.guard.config.watchdog_s
        if limit is None or not self._armed:
            return
        with self._lock:
            armed = dict(self._armed)
            last_command = self._last_command_t
        reason = None
        if now - last_command > limit:
            reason = f"no command for {now - last_command:.3f} s (limit {limit} s)"
        else:
            for dev, since in armed.items():
                pos = self.table.get(dev).position
                last = max(since, pos.t if pos is not None else -math.inf)
                if now - last > limit:
                    reason = (
                        f"feedback from {joint_name(dev)} stale for {now - last:.3f} s "
                        f"(limit {limit} s)"
                    )
                    break
        if reason is not None:
            self._trip(reason, tuple(armed))

    def _trip(self, reason: str, devices: Sequence[int]) -> None:
        with self._lock:
            self._tripped = reason
            self._armed.clear()
        self.stats.watchdog_trips += 1
        mode = self.guard.config.safe_mode
        try:
            self._write([commands.mode(d, mode).encode() for d in devices], internal=True)
            sent = f"put {', '.join(joint_name(d) for d in devices)} in {mode.name}"
        except LinkDownError:
            self._safe_pending = True
            sent = f"could not send {mode.name} (link down): will on reconnect"
        self._emit(EventKind.WATCHDOG, f"{reason}; {sent}")

    # ----------------------------------------------------------------- link loss

    def _set_link(self, state: LinkState, reason: str, now: float) -> None:
        self._link = state
        self._link_reason = reason
        self._link_since = now

    def _link_lost(self, reason: str) -> None:
        """Mark the link down (any thread); the reader thread reopens it."""
        with self._lock:
            if self._stop.is_set() or self._link in (LinkState.DOWN, LinkState.CLOSED):
                return
            was_up = self._link is LinkState.UP
            self._set_link(LinkState.DOWN, reason, self.clock())
            armed = tuple(self._armed)
            if armed:
                # Feedback is gone while joints obey the last velocity/current: the same
                # as stale feedback. The safe mode goes out first thing after reconnecting.
                self._tripped = f"link lost while commanding {len(armed)} joint(s)"
                self._armed.clear()
                self._safe_pending = True
            waiters = [w for ws in self._waiters.values() for w in ws]
        for w in waiters:
            w.fail(LinkDownError(self._down_message()))
        if was_up:
            self.stats.link_drops += 1
            self._emit(EventKind.LINK_DOWN, f"{self.transport.url}: {reason}")
            if armed:
                self.stats.watchdog_trips += 1
                self._emit(
                    EventKind.WATCHDOG,
                    f"{self._tripped}; {self.guard.config.safe_mode.name} goes out on reconnect",
                )
        if not self.link_config.reconnect:
            self._stop.set()

    def _reconnect_attempt(self) -> None:
        self.transport.close()
        delay = self._backoff.next_delay()
        if self._stop.wait(delay):
            return
        try:
            self.transport.open()
        except TransportError as exc:
            self._link_reason = str(exc)
            if self._backoff.attempt in (1, 3, 10) or self._backoff.attempt % 30 == 0:
                self._emit(
                    EventKind.RECONNECT_FAILED,
                    f"attempt {self._backoff.attempt}: {exc}; retrying",
                )
            return
        self.decoder.reset()
        now = self.clock()
        self._probe_deadline = now + self.link_config.probe_timeout_s
        self._set_link(LinkState.PROBING, "reopened, waiting for an answer", now)
        try:
            self._write([self._probe_frame()], internal=True)
        except LinkDownError:
            pass

    def _link_restored(self, t: float) -> None:
        attempts = self._backoff.attempt
        self._backoff.reset()
        self._set_link(LinkState.UP, "answering again", t)
        self.stats.reconnects += 1
        frames: list[bytes] = []
        if self._safe_pending:
            mode = self.guard.config.safe_mode
            frames += [commands.mode(d, mode).encode() for d in (*JOINTS, JAW)]
            self._safe_pending = False
        if self._stream is not None:
            frames += self._stream_frames(self._stream)
        if frames:
            try:
                self._write(frames, internal=True)
            except LinkDownError:
                return
        self._emit(
            EventKind.LINK_UP,
            f"{self.transport.url} answering again after {attempts} attempt(s)",
        )


def _four(values: Sequence[float] | np.ndarray) -> list[float]:
    out = [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]
    if len(out) != len(JOINTS):
        raise ValueError(f"expected 4 values in joint order E D C B, got {len(out)}")
    return out


def _pid_names(ids: Iterable[int]) -> str:
    names = []
    for p in ids:
        try:
            names.append(PacketID(p).name)
        except ValueError:
            names.append(f"0x{p:02X}")
    return "/".join(names)
