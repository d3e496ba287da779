"""The arm client: a reader thread, live state, matched requests, safe commands, a watchdog.

    with ArmClient(open_transport("/dev/ttyUSB0")).start() as arm:
        arm.request(DeviceID.E, [PacketID.POSITION])
        arm.command_positions([3.1, 1.5, 1.5, 3.0])

One thread owns the transport: it reads and decodes, updates the state table, answers
waiting requests by (device, packet id), feeds subscribers, runs the watchdog and the
keepalive, and reopens the link with backoff when it is lost. Commands are written from the
caller's thread; while the link is down they fail at once with `LinkDownError`.

`start()` records each device's identity (serial and model numbers, firmware version). After
a reconnect that identity is confirmed before anything else is sent or accepted; a different
arm gets only its safe stop and the link becomes FAILED (`ArmIdentityError`).

`ArmClient` is the facade over the pieces, each in its own module: request matching
(`requests`) and the reads built on it (`queries`, whose `ArmQueries` it inherits), link
supervision and reconnecting (`supervisor`), which joints are armed and the watchdog
(`watchdog`), the checks before a command goes out (`gate`), status flags (`faults`) and
heartbeat streaming (`streaming`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from protocol import (
    DecoderStats,
    Mode,
    Packet,
    PacketDecoder,
    PacketID,
    ProtocolError,
    commands,
    decode_packet,
)
from protocol.models import ALPHA5, MODELS, ArmModel, model_named
from reach_driver import ik
from reach_driver.drawing import DRAWINGS
from reach_driver.errors import (
    ArmIdentityError,
    ArmModelError,
    DriverError,
    LimitError,
    LinkDownError,
    TransportError,
)
from reach_driver.faults import FaultFlags
from reach_driver.gate import LIMIT_KIND_OF, CommandGate
from reach_driver.identity import (
    DeviceIdentity,
    IdentityCheck,
    ModelCheck,
    devices_to_ask,
    model_answering,
    model_mismatch,
)
from reach_driver.link import (
    ClientEvent,
    ClientStats,
    EventCallback,
    EventKind,
    LinkConfig,
    LinkState,
)
from reach_driver.listeners import ListenerSet, PacketListener, PacketQueue, Subscription
from reach_driver.loop_timing import SchedStat
from reach_driver.queries import ArmQueries, limit_verdict
from reach_driver.realtime import RealtimeThreads, ThreadRole
from reach_driver.requests import Requester, Waiters
from reach_driver.safe_stop import SafeStop
from reach_driver.safety import SafetyConfig, SafetyGuard
from reach_driver.state import ArmState, JointState, StateTable, joint_name
from reach_driver.streaming import Stream
from reach_driver.supervisor import LinkSupervisor
from reach_driver.transport import Transport
from reach_driver.watchdog import LoopTiming, Watchdog

log = logging.getLogger(__name__)

SAFE_RETRY_S = 0.05
"""`make_safe`: the pause between attempts (a silent arm already costs each attempt its
request timeouts)."""

__all__ = ["ArmClient", "ClientStats"]

EVENT_HISTORY = 200


class ArmClient(ArmQueries):
    """Talks to one arm over one transport. See the module docstring."""

    def __init__(
        self,
        transport: Transport,
        *,
        safety: SafetyConfig | None = None,
        link: LinkConfig | None = None,
        devices: Sequence[int] | None = None,
        request_timeout_s: float = 0.1,
        retries: int = 2,
        clock: Callable[[], float] = time.monotonic,
        model: ArmModel = ALPHA5,
    ) -> None:
        self.transport = transport
        #: The arm model: its joints, their order and its factory limits.
        self.model = model
        self.guard = SafetyGuard(safety, model)
        self.link_config = link or LinkConfig()
        self.devices = tuple(int(d) for d in (model.actuators if devices is None else devices))
        self._devices_given = devices is not None
        self.request_timeout_s = request_timeout_s
        self.retries = retries
        self.clock = clock
        self.table = StateTable(model)
        self.decoder = PacketDecoder()
        self.listeners = ListenerSet()
        self.stats = ClientStats()
        self.events: deque[ClientEvent] = deque(maxlen=EVENT_HISTORY)
        self.found_devices: tuple[int, ...] = ()
        #: Every device that answered discovery (with a model check: of every known model's
        #: joints and jaws, an arm's that is not this client's model included).
        self.answering: tuple[int, ...] = ()
        #: What each device reported at connect; a reconnect must find the same.
        self.identity: dict[int, DeviceIdentity] = {}
        self._check: IdentityCheck | None = None  # reader thread only
        self.warnings: list[str] = []
        self._event_callbacks: list[EventCallback] = []
        self._lock = threading.RLock()  # link state and the watchdog change together
        self._write_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._stream: Stream | None = None
        #: After a trip on stale feedback over a shared link: (device asked for its heartbeat
        #: rate, seconds the feedback had stopped); reader thread only (`_stream_answer`).
        self._stream_probe: tuple[int, float] | None = None
        self.watchdog = Watchdog()
        #: When the reader thread last came back from a read, and how long it had been away
        #: then (reader thread only): the watchdog tells a stalled process from a stalled loop.
        self._reader_t: float | None = None
        self._reader_gap_s = 0.0
        self._reader_away_max_s = 0.0  # the longest absence since `reader_away()` last asked
        self._reader_away_queue_s: float | None = None  # of which runnable, given no CPU
        #: Set by a running `ControlLoop`: how it keeps time, for the watchdog to name.
        self.loop_timing: Callable[[], LoopTiming | None] | None = None
        #: Real-time priority for the reader and a `ControlLoop`'s thread (set before start()).
        self.realtime = RealtimeThreads()
        self.faults = FaultFlags()
        self._waiters = Waiters()
        self._requests = Requester(
            self._write, self._waiters, self.stats, transport.url, self._broadcast_ok
        )
        self._gate = self._make_gate()
        self.supervisor = LinkSupervisor(
            transport,
            self.link_config,
            clock=clock,
            stop=self._stop,
            stats=self.stats,
            emit=self._emit,
            send_internal=lambda frames: self._write(frames, internal=True),
            probe_frame=self._probe_frame,
            on_lost=self._link_lost,
            reset_decoder=self._reopened,
        )

    def _make_gate(self) -> CommandGate:
        return CommandGate(
            self.guard,
            self.watchdog,
            self.table,
            self.transport.url,
            self._broadcast_ok,
            self.devices,
            faults=self.faults,
        )

    # ----------------------------------------------------------------- lifecycle

    def start(
        self,
        *,
        discover: bool = True,
        read_limits: bool = True,
        model_check: ModelCheck = ModelCheck.TRUST,
    ) -> ArmClient:
        """Open the link, start the reader, find the devices, read their identity (checked
        again after every reconnect) and their limits.

        `model_check` DETECT finds the model from the devices that answer (every known
        model's joints and jaws are asked) and takes it; CONFIRM raises `ArmModelError` if
        they are another model's than the client's. Raises `NoResponseError` (or
        `GarbageError` when bytes arrive but never decode, the sign of a wrong baud rate) if
        no device answers; the link is closed again on any error.
        """
        if self._thread is not None:
            return self
        if not self.transport.is_open:
            self.transport.open()
        self.supervisor.opened(self.clock())
        self._stop.clear()
        self._thread = threading.Thread(
            target=self.realtime.thread_target(ThreadRole.READER, self._run),
            name=f"reach-driver reader {self.transport.url}",
            daemon=True,
        )
        self._thread.start()
        try:
            if discover:
                if model_check is ModelCheck.TRUST:
                    self.answering = self.discover()
                else:
                    self._discover_model(model_check)
                self.read_identity()
            if read_limits and self.found_devices:
                self.read_limits()
        except BaseException:
            self.close(safe=False)
            raise
        return self

    def _discover_model(self, check: ModelCheck) -> None:
        """Discovery over every known model's joints and jaws; the model they are taken
        (DETECT) or confirmed (CONFIRM) before anything but a REQUEST is sent."""
        models = tuple(MODELS.values())
        self.answering = self.discover(devices_to_ask(self.devices, models))
        url = self.transport.url
        model = model_answering(self.answering, models)
        if check is ModelCheck.CONFIRM:
            problem = model_mismatch(url, self.model, self.answering, models)
            if problem is not None:
                raise ArmModelError(
                    f"{problem}; nothing was sent", None if model is None else model.name
                )
        else:
            if model is None:
                raise ArmModelError(
                    f"the devices answering on {url} are no known arm's: "
                    f"{', '.join(joint_name(d) for d in self.answering)}; nothing was sent"
                )
            if model is not self.model:
                self._use_model(model)
        self.found_devices = tuple(d for d in self.devices if d in self.answering)

    def _use_model(self, model: ArmModel) -> None:
        """Take `model` at connect, before anything is commanded: the limits, the order of
        the state's arrays, the gate's devices and (unless given) the devices asked."""
        log.info("%s answers as a %s", self.transport.url, model.title)
        self.model = model
        self.guard = SafetyGuard(self.guard.config, model)
        self.table.model = model
        if not self._devices_given:
            self.devices = tuple(int(d) for d in model.actuators)
        self._gate = self._make_gate()

    def close(self, *, safe: bool = True) -> None:
        """Leave the arm safe (stop streaming, safe mode on joints under continuous command),
        stop the reader and close the link. Safe to call twice."""
        if safe and self.supervisor.state is LinkState.UP:
            try:
                armed = self.watchdog.armed
                if armed:
                    self._send_safe_mode(armed)
                if self._stream is not None:
                    self.stop_stream()
            except DriverError as exc:
                log.warning("could not leave the arm safe while closing: %s", exc)
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        self.transport.close()
        self.supervisor.set(LinkState.CLOSED, "closed", self.clock())
        url = self.transport.url
        self._waiters.fail_all(lambda: LinkDownError(f"client for {url} closed"), forget=True)

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
        return self.supervisor.state

    @property
    def link_reason(self) -> str:
        return self.supervisor.reason

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    @property
    def tripped(self) -> str | None:
        """Why the watchdog tripped, or None while it has not (or after `rearm()`)."""
        return self.watchdog.tripped

    def reader_away(self) -> tuple[float, float | None]:
        """The longest the reader thread was away from the link (between two returns from a
        read, which waits at most the transport's read timeout) since the last call, and how
        much of it it was runnable but given no CPU (None: unknown). More than the read
        timeout means this process was not running."""
        away, self._reader_away_max_s = self._reader_away_max_s, 0.0
        return away, self._reader_away_queue_s

    def blocking_faults(self) -> dict[int, list[str]]:
        """Status flags, by device, that say a joint must not be driven (motor, driver,
        encoder, pressure...), from the last HARDWARE_STATUS each device sent; the policy
        (which flags block, and why) is `reach_driver.faults.FLAG_POLICY`. The gate refuses
        motion commands to these joints."""
        return self.faults.blocking()

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

    def note_event(self, kind: EventKind, message: str, device: int | None = None) -> None:
        """Report something the caller found (the control loop: implausible feedback) as the
        client's own events are: kept in `events`, logged, passed to the callbacks."""
        self._emit(kind, message, device)

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

    # ----------------------------------------------------------------- streaming

    def stream(
        self,
        ids: Sequence[int] = (PacketID.POSITION, PacketID.VELOCITY),
        hz: int = 20,
        devices: Sequence[int] | None = None,
    ) -> int:
        """Have each device send `ids` at `hz` (its heartbeat), re-applied after a reconnect;
        the rate used: capped, with a warning, to what a rate-limited line carries.

        Each device is addressed on its own (no broadcast: the jaw would stream too, and on
        RS-485 every joint would answer at once).
        """
        if not 1 <= hz <= 255:
            raise ValueError(f"heartbeat frequency must be 1..255 Hz, got {hz}")
        devs = self.model.joints if devices is None else devices
        stream = Stream(tuple(int(i) for i in ids), int(hz), tuple(int(d) for d in devs))
        wire = self.transport.wire_bytes_per_s
        if wire is not None and not stream.fits(wire):
            # The arm would queue what the line cannot carry and send it late, shown as fresh
            # (or drop it): cap the rate to what fits and say so.
            capped = stream.max_hz(wire)
            if capped < 1:
                raise LimitError(
                    f"the line ({wire:.0f} B/s) cannot carry {len(stream.ids)} ids from "
                    f"{len(stream.devices)} devices even at 1 Hz ({stream.bytes_per_beat()} B "
                    "a beat): stream fewer ids or devices"
                )
            log.warning(
                "%d Hz of %d ids from %d devices needs %.0f B/s, more than the line's %.0f: "
                "streaming at %d Hz",
                hz,
                len(stream.ids),
                len(stream.devices),
                hz * stream.bytes_per_beat(),
                wire,
                capped,
            )
            stream = Stream(stream.ids, capped, stream.devices)
        self._stream = stream
        self._write(stream.start_frames())
        return stream.hz

    def stop_stream(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            self._write(stream.stop_frames())

    # ----------------------------------------------------------------- commands

    def send(self, *packets: Packet) -> None:
        """Write packets as they are, after the same safety checks as the command helpers.

        Every packet passes the gate (`reach_driver.gate`): only packets known to be
        harmless, and checked motion and limit writes, go out; one refusal sends nothing.
        """
        for p in packets:
            self._gate.check_packet(p)
        self._write_commands(packets)

    def send_unchecked(self, *packets: Packet) -> None:
        """Write packets with no safety check at all (bench work, protocol tests). Nothing
        in the CLI uses it."""
        self._write_commands(packets)

    def set_mode(self, devices: int | Sequence[int], mode: Mode) -> None:
        devs = [devices] if isinstance(devices, int) else list(devices)
        self.send(*(commands.mode(int(d), mode) for d in devs))

    def command_position(self, device: int, value: float) -> None:
        """Absolute position (rad; mm for the jaw); refused outside the position limit."""
        self._positions([int(device)], [float(value)])

    def command_positions(self, q: Sequence[float] | np.ndarray) -> None:
        """Positions of every joint in the model's order (E D C B on the Alpha 5); all are
        checked before any is sent."""
        self._positions(self.model.joints, self._per_joint(q))

    def _per_joint(self, values: Sequence[float] | np.ndarray) -> list[float]:
        """One float per joint of the model, in its order (ValueError naming the order)."""
        out = [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]
        if len(out) != self.model.n_joints:
            order = " ".join(self.model.joint_letters)
            raise ValueError(
                f"expected {self.model.n_joints} values in joint order {order}, got {len(out)}"
            )
        return out

    def _positions(self, devices: Sequence[int], values: Sequence[float]) -> None:
        self._gate.check_positions(devices, values)
        self.send(*(commands.position(int(d), v) for d, v in zip(devices, values, strict=True)))

    def solve_xyz(self, x: float, y: float, z: float) -> np.ndarray:
        """Joint target (rad, the model's order) putting the tool centre point at (x, y, z)
        mm in the base frame, from the present angles, inside the position limits in force
        (the arm's, tightened by the safety config); B keeps its angle (it does not move the
        tool centre point). Sends nothing; `ik.UnreachableError` (a `LimitError`) if no
        angles inside the limits get within `ik.TOLERANCE_MM`. The Alpha 5 by `ik`'s solver,
        another model on its chain from its MJCF (`ik.solve_on_chain`: the Bravo 7's G F E D
        C move, redundantly, the least from where they are); a model the driver has no
        chain for gets a `LimitError` saying so."""
        if self.model.name not in DRAWINGS:
            known = " and the ".join(f"{model_named(name).title}'s" for name in DRAWINGS)
            raise LimitError(
                f"refused: the driver's inverse kinematics are the {known}, not the "
                f"{self.model.title}'s; command joint angles instead; nothing was sent"
            )
        q = self.state.q
        if not np.all(np.isfinite(q)):
            q = self.read_joints((PacketID.POSITION,)).q
        limits = np.array(self.guard.position_limits())
        if self.model is ALPHA5:
            return ik.solve_or_refuse((x, y, z), q, limits)
        drawing = DRAWINGS[self.model.name]
        letters = self.model.joint_letters
        return ik.solve_on_chain_or_refuse(drawing, letters, (x, y, z), q, limits)

    def command_xyz(self, x: float, y: float, z: float) -> np.ndarray:
        """Move the tool centre point to (x, y, z) mm: the driver's own inverse kinematics
        (`solve_xyz`), then joint POSITION commands through the same gate as
        `command_positions` (limits, blocking faults); never a raw KM_END_POS. Returns the
        joint target sent."""
        q = self.solve_xyz(x, y, z)
        self.command_positions(q)
        return q

    def command_jaw(self, mm: float) -> None:
        self.command_position(self.model.jaw, mm)

    def command_velocity(self, device: int, value: float) -> float:
        return float(self.command_velocities_for([int(device)], [value])[0])

    def command_velocities(self, v: Sequence[float] | np.ndarray) -> np.ndarray:
        """Velocities of every joint in the model's order, after the soft barrier (what was
        actually sent)."""
        return self.command_velocities_for(self.model.joints, self._per_joint(v))

    def command_velocities_for(
        self, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> np.ndarray:
        return self._continuous(PacketID.VELOCITY, devices, values)

    def command_current(self, device: int, milliamps: float) -> float:
        return float(self._continuous(PacketID.CURRENT, [int(device)], [milliamps])[0])

    def command_currents(self, currents_mA: Sequence[float] | np.ndarray) -> np.ndarray:
        """Currents of every joint in the model's order in mA, after the soft barrier (what
        was actually sent)."""
        return self._continuous(PacketID.CURRENT, self.model.joints, self._per_joint(currents_mA))

    def _continuous(
        self, pid: PacketID, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> np.ndarray:
        devs, sent = self._gate.continuous(pid, devices, values)
        builder = commands.current if pid is PacketID.CURRENT else commands.velocity
        self._write_commands([builder(d, float(v)) for d, v in zip(devs, sent, strict=True)])
        return sent

    def _write_commands(self, packets: Sequence[Packet], *, disarm: bool = True) -> float:
        """Write checked commands; the watchdog learns which joints they arm (or disarm)."""
        done = self._write([p.encode() for p in packets])
        self.watchdog.note_sent(packets, self.clock(), disarm=disarm)
        return done

    def safe_stop(self, devices: Sequence[int] | None = None) -> None:
        """Put joints (default: the four joints and the jaw) in the configured safe mode."""
        self._send_safe_mode(tuple(devices or self.model.actuators))

    def make_safe(
        self, devices: Sequence[int] | None = None, *, wait_s: float | None = None
    ) -> SafeStop:
        """Put `devices` (default: the four joints and the jaw) in the safe mode and read
        their modes back; until all confirm it, send it again, for up to `wait_s` wall
        seconds (default `SafetyConfig.safe_wait_s`), waiting for a lost link meanwhile.
        Unconfirmed, the safe mode stays owed: this client sends it once the link is back."""
        devs = tuple(int(d) for d in (devices or self.model.actuators))
        mode = self.guard.config.safe_mode
        wait = self.guard.config.safe_wait_s if wait_s is None else float(wait_s)
        start = time.monotonic()
        deadline = start + wait
        sent = 0
        problem = ""
        saw_down = False
        while True:
            state = self.supervisor.state
            if state is LinkState.UP:
                try:
                    self._send_safe_mode(devs)
                    sent += 1
                    problem = self.mode_problem(devs, mode)
                except DriverError as exc:
                    problem = str(exc)
                else:
                    if not problem:
                        return SafeStop(mode, True, sent, time.monotonic() - start, wait, saw_down)
            else:
                saw_down = True
                problem = problem or f"link {state.value}: {self.link_reason}"
                if state in (LinkState.CLOSED, LinkState.FAILED):
                    break
            if time.monotonic() >= deadline:
                break
            time.sleep(SAFE_RETRY_S)
        self.watchdog.mark_safe_pending()
        state = self.supervisor.state
        down = None if state is LinkState.UP else f"{state.value} ({self.link_reason})"
        return SafeStop(mode, False, sent, time.monotonic() - start, wait, saw_down, problem, down)

    def mode_problem(self, devices: Sequence[int], mode: Mode) -> str:
        """Read the modes of `devices` back: "" when every one answers `mode`, else what
        differs ("no answer from E D, C in current")."""
        modes = self.read_modes(devices)
        silent = [joint_name(d) for d, m in modes.items() if m is None]
        other = [
            f"{joint_name(d)} in {_mode_name(m)}" for d, m in modes.items() if m not in (None, mode)
        ]
        parts = ([f"no answer from {' '.join(silent)}"] if silent else []) + other
        return ", ".join(parts)

    def rearm(self) -> None:
        """Allow velocity/current commands again after a watchdog trip."""
        self.watchdog.rearm()

    def _send_safe_mode(self, devices: Sequence[int]) -> None:
        self._write(self._safe_mode_frames(devices))
        self.watchdog.disarm(devices)

    def _safe_mode_frames(self, devices: Sequence[int]) -> list[bytes]:
        mode = self.guard.config.safe_mode
        return [commands.mode(int(d), mode).encode() for d in devices]

    # ----------------------------------------------------------------- writing

    def _write(self, frames: Sequence[bytes], *, internal: bool = False) -> float:
        """Write frames in one go; returns the time the write completed. Only the reader
        thread's own writes (`internal`) go out while the link is not UP."""
        if not internal and self.supervisor.state is not LinkState.UP:
            if self.supervisor.state is LinkState.FAILED:
                raise ArmIdentityError(self.supervisor.down_message())
            raise LinkDownError(self.supervisor.down_message())
        with self._write_lock:
            try:
                self.transport.write_frames(frames)
            except TransportError as exc:
                self._link_lost(str(exc))
                raise LinkDownError(self.supervisor.down_message()) from None
        return self.clock()

    def write_frames(self, frames: Sequence[bytes]) -> float:
        """Encoded frames, each decoded and passed through the same gate as `send`; returns
        the write completion time. Joints they arm are armed in the watchdog, but nothing
        here disarms one (tests use it to fake feedback on loop://)."""
        packets = []
        for frame in frames:
            try:
                packets.append(decode_packet(frame))
            except ProtocolError as exc:
                raise LimitError(
                    f"refused: a frame that does not decode ({exc}) cannot be checked; "
                    "write_frames_unchecked() writes it as it is; nothing was sent"
                ) from None
        for p in packets:
            self._gate.check_packet(p)
        return self._write_commands(packets, disarm=False)

    def write_frames_unchecked(self, frames: Sequence[bytes]) -> float:
        """Raw frames with no check at all (malformed-frame tests, tools); returns the write
        completion time. Nothing in the CLI uses it."""
        return self._write(frames)

    # ----------------------------------------------------------------- the reader thread

    def _run(self) -> None:
        try:
            self._read_loop()
        except Exception as exc:  # a bug: make commands fail fast instead of hanging
            log.exception("reader thread of %s crashed", self.transport.url)
            with self._lock:
                self.supervisor.set(
                    LinkState.CLOSED, f"reader thread crashed: {exc!r}", self.clock()
                )
            self._waiters.fail_all(lambda: LinkDownError(self.supervisor.down_message()))
            self._emit(EventKind.LINK_DOWN, f"reader thread crashed: {exc!r}")

    def _read_loop(self) -> None:
        sched = SchedStat()  # this thread's run-queue time: away for want of a CPU?
        queue0: float | None = None
        try:
            while not self._stop.is_set():
                if self.supervisor.state is LinkState.DOWN:
                    self.supervisor.reconnect_attempt()
                    continue
                try:
                    chunk = self.transport.read()
                except TransportError as exc:
                    self._link_lost(str(exc))
                    if self.supervisor.state is LinkState.FAILED:
                        self._stop.wait(0.1)  # failed for good: nothing to reopen
                    continue
                now = self.clock()
                queue0 = self._came_back(now, sched, queue0)
                if chunk:
                    for packet in self.decoder.feed(chunk):
                        self._dispatch(packet, now)
                self.supervisor.duties(self.clock(), self._watchdog)
        finally:
            sched.close()

    def _came_back(self, now: float, sched: SchedStat, queue0: float | None) -> float | None:
        """The reader is back from a read at `now`. A read waits at most the transport's read
        timeout: a longer absence means this process did not run (no CPU for this thread, or
        the GIL held elsewhere), the loop's thread no more. Keeps the longest absence, and
        how much of it this thread spent runnable but given no CPU; returns the run-queue
        total now."""
        self._reader_gap_s = now - self._reader_t if self._reader_t is not None else 0.0
        self._reader_t = now
        got = sched.read()
        queue = None if got is None else got[1]
        if self._reader_gap_s > self._reader_away_max_s:
            self._reader_away_max_s = self._reader_gap_s
            self._reader_away_queue_s = None if queue is None or queue0 is None else queue - queue0
        return queue

    def _dispatch(self, packet: Packet, t: float) -> None:
        self.stats.packets += 1
        if self.supervisor.state is LinkState.FAILED:
            return  # another arm: nothing it says is this arm's state
        if self.supervisor.heard(t) and not self._confirm_identity(packet, t):
            return
        pid = packet.packet_id
        if self.table.update(packet, t):
            if pid in LIMIT_KIND_OF:
                self._consider_limits(packet)
            elif pid == PacketID.HARDWARE_STATUS:
                event = self.faults.note(packet)
                if event is not None:
                    self._emit(*event)
        if self._stream_probe is not None and packet.key == (
            self._stream_probe[0],
            PacketID.HEARTBEAT_FREQUENCY,
        ):
            self._stream_answer(packet)
        self._waiters.offer(packet)
        self.listeners.dispatch(packet, t)

    def _consider_limits(self, packet: Packet) -> None:
        """Adopt limits the arm reported only if they were asked for (a request for this
        packet from this device is waiting) and are plausible; else keep the ones in force,
        count it and say so. The state table keeps the raw reading either way."""
        dev, kind = int(packet.device_id), LIMIT_KIND_OF[int(packet.packet_id)]
        value, problem = limit_verdict(packet, dev, kind, self.model)
        if value is None:
            return  # malformed: the state table counted it
        if problem is None and not self._waiters.wants(packet.key):
            problem = "not asked for"
        if problem is None:
            self.guard.set_arm_limit(dev, kind, value)
            return
        self.stats.limits_rejected += 1
        kept = self.guard.present_limit(dev, kind)
        self._emit(
            EventKind.LIMITS_REJECTED,
            f"{joint_name(dev)} reported {kind.value} limits {list(value)} ({problem}); "
            f"safety keeps {list(kept) if kept else 'none'}",
            dev,
        )

    def _broadcast_ok(self) -> bool:
        return self.transport.broadcast_ok

    def _probe_frame(self) -> bytes:
        device = (self.found_devices or self.devices)[0]
        return commands.request(device, [PacketID.MODE]).encode()

    def _watchdog(self, now: float) -> None:
        def feedback_t(dev: int) -> tuple[float | None, str]:
            # Position always; velocity too while it is streamed to this device (a controller
            # uses both, and either may stop alone). The stalest is judged, and named.
            joint = self.table.get(dev)
            pos = joint.position
            fed: tuple[float | None, str] = (None if pos is None else pos.t, "position")
            stream, vel = self._stream, joint.velocity
            if (
                stream is not None
                and PacketID.VELOCITY in stream.ids
                and dev in stream.devices
                and vel is not None
                and (fed[0] is None or vel.t < fed[0])
            ):
                fed = (vel.t, "velocity")
            return fed

        timing = self.loop_timing
        expired = self.watchdog.expired(
            now,
            self.guard.config.watchdog_s,
            feedback_t,
            away_s=self._reader_gap_s,
            loop=None if timing is None else timing(),
        )
        if expired is None:
            return
        reason, devices = expired
        self.watchdog.trip(reason)
        self.stats.watchdog_trips += 1
        mode = self.guard.config.safe_mode
        probe = self._stream_probe_frames(now, feedback_t)
        try:
            self._write(self._safe_mode_frames(devices) + probe, internal=True)
            sent = f"put {', '.join(joint_name(d) for d in devices)} in {mode.name}"
        except LinkDownError:
            self.watchdog.mark_safe_pending()
            sent = f"could not send {mode.name} (link down): will on reconnect"
        self._emit(EventKind.WATCHDOG, f"{reason}; {sent}")

    def _stream_probe_frames(
        self, now: float, feedback_t: Callable[[int], tuple[float | None, str]]
    ) -> list[bytes]:
        """Over a link other hosts share (UDP), a stream that stopped may have gone to
        another client: ask a streamed device for its heartbeat rate, sent with the safe
        mode; `_stream_answer` reads the reply. Nothing to ask otherwise."""
        stream, limit = self._stream, self.guard.config.watchdog_s
        if stream is None or limit is None or not self.transport.shared_by_other_hosts:
            return []
        # This reader away for most of the limit is the stale feedback's cause (the trip says
        # the machine was busy): the stream kept coming, into the socket. An arm that answers
        # the probe is then no evidence of another client, only that the link works.
        if self._reader_gap_s > limit / 2:
            return []
        # another client takes the whole stream: only when no streamed device's position
        # arrived in the last half watchdog (one quantity of one joint stopping while the
        # others keep arriving is the arm's own fault; a stream that stopped leaves every
        # device within a tick of the stalest one)
        for dev in stream.devices:
            pos = self.table.get(dev).position
            if pos is not None and now - pos.t <= limit / 2:
                return []
        for dev in stream.devices:
            fed, _quantity = feedback_t(dev)
            if fed is not None and now - fed > limit:
                self._stream_probe = (dev, now - fed)
                return [commands.request(dev, [PacketID.HEARTBEAT_FREQUENCY]).encode()]
        return []

    def _stream_answer(self, packet: Packet) -> None:
        """The arm answered the probe, so the link works: its stream went elsewhere (or was
        turned off). Name that as the trip's reason instead of a failing link."""
        assert self._stream_probe is not None
        dev, stopped = self._stream_probe
        self._stream_probe = None
        reason = (
            f"{self._stream_lost(dev, packet)}; this client's feedback had stopped for "
            f"{stopped:.3f} s (watchdog "
            f"{self.guard.config.watchdog_s:g} s)"
        )
        if self.watchdog.explain(reason):
            self._emit(
                EventKind.WATCHDOG,
                f"{reason}; the armed joints were put in {self.guard.config.safe_mode.name}",
                dev,
            )

    def stream_problem(self) -> str | None:
        """Why this client's heartbeat stopped arriving, when the arm can tell: over a link
        other hosts share (UDP), ask a streamed device for its rate (which also takes the
        stream back). None when not knowable: no stream, a private link, no answer."""
        stream = self._stream
        if stream is None or not self.transport.shared_by_other_hosts:
            return None
        dev = stream.devices[0]
        try:
            reply = self.request(dev, [PacketID.HEARTBEAT_FREQUENCY])
        except DriverError:
            return None
        # The stream still reaching this client (a position within a few ticks of the reply)
        # means the state was late, not taken: the loop's wait ran out while this host did
        # not run it. The arm answering at its rate says nothing of another client then.
        pos = self.table.get(dev).position
        fresh_s = max(3.0 / stream.hz, 0.05)
        if pos is not None and self.clock() - pos.t <= fresh_s:
            return (
                f"the stream still reaches this client ({joint_name(dev)}'s position is "
                f"{1e3 * (self.clock() - pos.t):.0f} ms old): the state came late, not lost; "
                "this host did not run the loop in time (a busy machine)"
            )
        return self._stream_lost(dev, reply[PacketID.HEARTBEAT_FREQUENCY])

    def _stream_lost(self, device: int, rate: Packet) -> str:
        """What an arm that answers us, reporting heartbeat `rate`, says about our stream."""
        hz = rate.data[0] if rate.data else 0
        url = self.transport.url
        if hz:
            return (
                f"another client on this arm's UDP port took the stream: {joint_name(device)} "
                f"still answers {url} and streams at {hz} Hz, but to another host (the arm "
                "sends its heartbeat to the last host that wrote to it; one UDP arm serves one "
                "commanding client: run no info, monitor or second run against it meanwhile)"
            )
        return (
            f"the stream was turned off: {joint_name(device)} still answers {url} but its "
            "heartbeat is 0 Hz (another client on this arm's UDP port stopped it, or the arm "
            "reset)"
        )

    # ----------------------------------------------------------------- link loss

    def _link_lost(self, reason: str) -> None:
        """Mark the link down (any thread); the reader thread reopens it."""
        with self._lock:
            was_up = self.supervisor.mark_down(reason)
            if was_up is None:
                return
            # Feedback is gone while joints obey the last velocity/current: the same as
            # stale feedback. The safe mode goes out first thing after reconnecting.
            armed = self.watchdog.trip_on_link_loss()  # owes the safe mode if armed
        self._waiters.fail_all(lambda: LinkDownError(self.supervisor.down_message()))
        if was_up:
            self.stats.link_drops += 1
            self._emit(EventKind.LINK_DOWN, f"{self.transport.url}: {reason}")
            if armed:
                self.stats.watchdog_trips += 1
                self._emit(
                    EventKind.WATCHDOG,
                    f"{self.watchdog.tripped}; {self.guard.config.safe_mode.name} goes out on "
                    "reconnect",
                )
        if not self.link_config.reconnect:
            self._stop.set()

    def _reopened(self) -> None:
        """The supervisor reopened the link (reader thread): a fresh start for the check."""
        self.decoder.reset()
        self._check = None
        self._stream_probe = None

    def _confirm_identity(self, packet: Packet, t: float) -> bool:
        """While PROBING: True once the link is UP again and `packet` may be used. With an
        identity on record, the reopened link stays PROBING until every device confirmed it
        (its replies are not state); a difference fails the link at once."""
        if not self.identity:
            self._link_restored(t)
            return True
        check = self._check
        if check is None:
            self._check = check = IdentityCheck(self.identity)
            self.supervisor.extend_probe(t)
            try:
                self._write(check.frames(), internal=True)
            except LinkDownError:
                pass
            return False
        check.offer(packet)
        if check.differences:
            self._identity_failed(check.differences, t)
        elif check.complete:
            self._check = None
            self._link_restored(t)
        return False

    def _identity_failed(self, differences: Sequence[str], t: float) -> None:
        """A different arm answers: stop it, send it nothing else, fail the link for good."""
        self._check = None
        mode = self.guard.config.safe_mode
        devices = self.model.actuators
        try:
            self._write(self._safe_mode_frames(devices), internal=True)
            sent = f"sent it {mode.name} and nothing else"
        except LinkDownError:
            sent = f"could not even send it {mode.name}"
        reason = (
            f"a different arm answers on {self.transport.url}: {'; '.join(differences)}; "
            f"{sent}; close this client and start a new one to use that arm"
        )
        with self._lock:
            self.supervisor.set(LinkState.FAILED, reason, t)
            self.watchdog.disarm(devices)
            self.watchdog.take_safe_pending()
        self.table.clear()
        self.stats.identity_mismatches += 1
        self._waiters.fail_all(lambda: ArmIdentityError(self.supervisor.down_message()))
        self._emit(EventKind.IDENTITY, reason)

    def _link_restored(self, t: float) -> None:
        attempts = self.supervisor.restored(t)
        frames: list[bytes] = []
        owed = self.watchdog.take_safe_pending()
        if owed:
            frames += self._safe_mode_frames(self.model.actuators)
        if self._stream is not None:
            frames += self._stream.start_frames()
        if frames:
            try:
                self._write(frames, internal=True)
            except LinkDownError:
                if owed:
                    self.watchdog.mark_safe_pending()
                return
        self._emit(
            EventKind.LINK_UP,
            f"{self.transport.url} answering again after {attempts} attempt(s)",
        )


def _mode_name(mode: Mode | int | None) -> str:
    return mode.name.lower() if isinstance(mode, Mode) else f"mode 0x{int(mode or 0):02X}"
