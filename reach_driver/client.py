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
(`requests`) and the reads built on it (`queries`, `ArmQueries`), the commands and the safe
mode (`commanding`, `ArmCommands`: it inherits both), link supervision and reconnecting
(`supervisor`) and what a lost or reopened link means for requests, the watchdog and the
arm's identity (`recovery`), which joints are armed and the watchdog (`watchdog`), the
checks before a command goes out (`gate`), status flags (`faults`), heartbeat streaming
(`streaming`) and why a stream stopped (`stream_diagnosis`), the reader thread's absences
(`reader_away`), and the events it reports (`link`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence

from protocol import DecoderStats, Packet, PacketDecoder, PacketID, commands
from protocol.models import ALPHA5, MODELS, ArmModel
from reach_driver.commanding import ArmCommands
from reach_driver.errors import ArmIdentityError, DriverError, LinkDownError, TransportError
from reach_driver.faults import FaultFlags
from reach_driver.gate import LIMIT_KIND_OF, CommandGate
from reach_driver.identity import DeviceIdentity, ModelCheck, devices_to_ask, model_taken
from reach_driver.link import (
    ClientStats,
    EventCallback,
    EventHistory,
    EventKind,
    LinkConfig,
    LinkState,
)
from reach_driver.listeners import ListenerSet, PacketListener, PacketQueue, Subscription
from reach_driver.loop_timing import SchedStat
from reach_driver.queries import limit_verdict
from reach_driver.reader_away import ReaderAway
from reach_driver.realtime import RealtimeThreads, ThreadRole
from reach_driver.recovery import LinkRecovery
from reach_driver.requests import Requester, Waiters
from reach_driver.safety import SafetyConfig, SafetyGuard
from reach_driver.state import ArmState, JointState, StateTable, joint_name
from reach_driver.stream_diagnosis import StreamDiagnosis
from reach_driver.streaming import Stream, stalest_feedback
from reach_driver.supervisor import LinkSupervisor
from reach_driver.transport import Transport
from reach_driver.watchdog import LoopTiming, Watchdog

log = logging.getLogger(__name__)

__all__ = ["ArmClient"]


class ArmClient(ArmCommands):
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
        self._events = EventHistory(clock, log)
        #: The latest events (link, watchdog, faults...), oldest first.
        self.events = self._events.kept
        self.found_devices: tuple[int, ...] = ()
        #: Every device that answered discovery (with a model check: of every known model's
        #: joints and jaws, an arm's that is not this client's model included).
        self.answering: tuple[int, ...] = ()
        #: What each device reported at connect; a reconnect must find the same.
        self.identity: dict[int, DeviceIdentity] = {}
        self.warnings: list[str] = []
        self._lock = threading.RLock()  # link state and the watchdog change together
        self._write_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._stream: Stream | None = None
        self.watchdog = Watchdog()
        self._away = ReaderAway()
        self._diagnosis = StreamDiagnosis(
            transport,
            self.table,
            self.watchdog,
            clock=clock,
            emit=self._events.emit,
            request=self.request,
        )
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
            emit=self._events.emit,
            send_internal=lambda frames: self._write(frames, internal=True),
            probe_frame=self._probe_frame,
            on_lost=self._link_lost,
            reset_decoder=self._reopened,
        )
        self._recovery = LinkRecovery(
            self.supervisor,
            self.watchdog,
            self._waiters,
            self.table,
            self.stats,
            identity=self.identity,
            lock=self._lock,
            stop=self._stop,
            emit=self._events.emit,
            send_internal=lambda frames: self._write(frames, internal=True),
            guard=lambda: self.guard,
            safe_frames=self._safe_mode_frames,
            stream=lambda: self._stream,
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
        model = model_taken(check, self.model, self.answering, models, self.transport.url)
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
        return self._away.longest()

    def blocking_faults(self) -> dict[int, list[str]]:
        """Status flags, by device, that say a joint must not be driven (motor, driver,
        encoder, pressure...), from the last HARDWARE_STATUS each device sent; the policy
        (which flags block, and why) is `reach_driver.faults.FLAG_POLICY`. The gate refuses
        motion commands to these joints."""
        return self.faults.blocking()

    def on_event(self, callback: EventCallback) -> None:
        self._events.callbacks.append(callback)

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
        self._events.emit(kind, message, device)

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
        wanted = Stream(tuple(int(i) for i in ids), int(hz), tuple(int(d) for d in devs))
        stream, capped = wanted.capped_to(self.transport.wire_bytes_per_s)
        if capped is not None:
            log.warning("%s", capped)
        self._stream = stream
        self._write(stream.start_frames())
        return stream.hz

    def stop_stream(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            self._write(stream.stop_frames())

    def stream_problem(self) -> str | None:
        """Why this client's heartbeat stopped arriving, when the arm can tell: over a link
        other hosts share (UDP), ask a streamed device for its rate (which also takes the
        stream back). None when not knowable: no stream, a private link, no answer."""
        return self._diagnosis.problem(self._stream)

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
            self._events.emit(EventKind.LINK_DOWN, f"reader thread crashed: {exc!r}")

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
                queue0 = self._away.came_back(now, sched, queue0)
                if chunk:
                    for packet in self.decoder.feed(chunk):
                        self._dispatch(packet, now)
                self.supervisor.duties(self.clock(), self._watchdog)
        finally:
            sched.close()

    def _dispatch(self, packet: Packet, t: float) -> None:
        self.stats.packets += 1
        if self.supervisor.state is LinkState.FAILED:
            return  # another arm: nothing it says is this arm's state
        if self.supervisor.heard(t) and not self._recovery.confirm(packet, t):
            return
        pid = packet.packet_id
        if self.table.update(packet, t):
            if pid in LIMIT_KIND_OF:
                self._consider_limits(packet)
            elif pid == PacketID.HARDWARE_STATUS:
                event = self.faults.note(packet)
                if event is not None:
                    self._events.emit(*event)
        self._diagnosis.offer(packet, self.guard.config)
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
        self._events.emit(
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
            return stalest_feedback(self.table.get(dev), dev, self._stream)

        timing = self.loop_timing
        expired = self.watchdog.expired(
            now,
            self.guard.config.watchdog_s,
            feedback_t,
            away_s=self._away.gap_s,
            loop=None if timing is None else timing(),
        )
        if expired is None:
            return
        reason, devices = expired
        self.watchdog.trip(reason)
        self.stats.watchdog_trips += 1
        mode = self.guard.config.safe_mode
        probe = self._diagnosis.probe_frames(
            self._stream, now, self.guard.config, self._away.gap_s, feedback_t
        )
        try:
            self._write(self._safe_mode_frames(devices) + probe, internal=True)
            sent = f"put {', '.join(joint_name(d) for d in devices)} in {mode.name}"
        except LinkDownError:
            self.watchdog.mark_safe_pending()
            sent = f"could not send {mode.name} (link down): will on reconnect"
        self._events.emit(EventKind.WATCHDOG, f"{reason}; {sent}")

    # ----------------------------------------------------------------- link loss

    def _link_lost(self, reason: str) -> None:
        """Mark the link down (any thread); the reader thread reopens it."""
        self._recovery.lost(reason)

    def _reopened(self) -> None:
        """The supervisor reopened the link (reader thread): a fresh start."""
        self.decoder.reset()
        self._recovery.reopened()
        self._diagnosis.reset()
