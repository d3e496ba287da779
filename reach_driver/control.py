"""The closed loop: any controller `act(state, target) -> currents` against the live arm.

Two pacings, one code path for the virtual arm and a real one:

- `Pacing.STREAM` (default): the arm paces the loop. Each joint streams CURRENT, POSITION and
  VELOCITY as its heartbeat at the control rate; the loop steps once per heartbeat tick (see
  `_StateAssembler` for lost packets) and counts time in ticks, i.e. in ARM time. Against
  `reach-sim --speed X` a run takes 1/X of the wall time and sees the same sequence of states.
- `Pacing.POLL`: the host paces the loop on its own clock and REQUESTs the state each period
  (for arms whose heartbeat cannot be set). Time is wall time.

Controller outputs are clipped to the current limits (counted as saturation) and then pass
the client's soft barrier; a per-step hook receives a `StepRecord` (a recorder logs these).
The joints enter current mode only with the first command, so they hold their previous mode
until the controller has seen a state. Each joint's status flags are polled once a second; a
motor, driver or encoder fault ends the run (`ArmFaultError`). On any exit, Ctrl-C included,
the joints are put in the safe mode and streaming is stopped; if the link is down at that
moment the loop waits a little for it to return so the safe mode can go out, and the summary
says how the arm was left.

The summary carries the run as a uniformly sampled `LoopTrace` (the state that ended the run
is its last row) from which `reach_driver.metrics` scores it like the evaluation runner does,
on the angles the arm reported; torque is current x the joint's torque constant.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum

import numpy as np

from protocol import Mode, Packet, PacketID, ProtocolError, commands
from reach_driver.client import ArmClient
from reach_driver.controllers import Controller, ControlState
from reach_driver.errors import ArmFaultError, DriverError
from reach_driver.link import LinkState
from reach_driver.safety import LimitKind
from reach_driver.state import JOINTS, joint_name

log = logging.getLogger(__name__)

N = len(JOINTS)
TELEMETRY = (PacketID.POSITION, PacketID.VELOCITY)
# CURRENT first: a joint's heartbeat sends its ids in order, so the measured current is in
# before the VELOCITY that completes the state.
TELEMETRY_WITH_CURRENT = (PacketID.CURRENT, PacketID.POSITION, PacketID.VELOCITY)

#: Joint output torque per motor amp, E D C B (N m/A): Kt x gear ratio x efficiency
#: (reference/alpha5-model.md). The driver cannot import the simulator's motor model, and on a
#: real arm this is the only torque estimate there is.
TORQUE_CONSTANT_NM_PER_A = np.array([20.2, 20.2, 20.2, 7.1])
RECONNECT_WAIT_S = 3.0
STATUS_PERIOD_S = 1.0
"""Each joint's HARDWARE_STATUS is asked for this often (loop time) during a run, one joint at
a time so a half-duplex line never sees two answers at once; a motor, driver or encoder
fault ends the run."""


def torque_from_current(current_mA: np.ndarray) -> np.ndarray:
    """Joint torque (N m) from motor current (mA), E D C B."""
    return np.asarray(current_mA, dtype=float) * 1e-3 * TORQUE_CONSTANT_NM_PER_A


class Pacing(str, Enum):
    STREAM = "stream"
    POLL = "poll"


@dataclass(frozen=True)
class StepRecord:
    """One control step, as the per-step hook receives it."""

    step: int
    t: float  # loop time: arm time when streaming, wall time when polling (s)
    wall_t: float  # host seconds since the loop started
    q: np.ndarray
    qdot: np.ndarray
    target: np.ndarray
    raw_command_mA: np.ndarray  # what the controller asked for
    command_mA: np.ndarray  # what was sent (after clipping and the soft barrier)
    state_age_s: float  # age of the oldest reading in the state when the controller ran
    latency_s: float  # from the state being complete to the command being written
    saturated: bool
    barrier: bool
    good_frames: int
    bad_frames: int
    current_mA: np.ndarray | None = None  # measured with the state (None when not streamed)
    torque_Nm: np.ndarray | None = None  # over the period ending at this state (see LoopTrace)


StepHook = Callable[[StepRecord], None]


@dataclass(frozen=True)
class TimingStats:
    """How well the loop kept time (wall seconds unless named otherwise)."""

    steps: int
    nominal_period_s: float  # in loop time
    rate_hz: float  # steps per wall second
    arm_speed: float  # loop seconds per wall second (the simulator's speed-up)
    period_mean_s: float
    period_jitter_s: float  # standard deviation of step intervals
    period_jitter_max_s: float  # largest deviation of a step interval from the mean
    state_age_p50_s: float
    state_age_p99_s: float
    state_age_max_s: float
    latency_p50_s: float
    latency_p99_s: float
    latency_max_s: float
    missed_deadlines: int
    skipped_states: int
    cpu_per_step_s: float  # the loop thread
    process_cpu_per_step_s: float  # the whole process (reader thread included)
    partial_states: int = 0  # ticks handed out with a lost packet filled in
    incomplete_ticks: int = 0  # ticks never handed out (lost packets, or the loop was late)


@dataclass(frozen=True)
class LoopTrace:
    """The run sampled once per period: row 0 is the first state the controller saw, row k the
    state k periods (heartbeats) later, the last row the state that ended the run.

    Row k of `command_mA`, `current_mA` and `torque_Nm` belongs to the period ENDING at sample
    k (row 0 is zero), the convention of `reach_driver.metrics.Trace`. Torque comes from the
    measured current where the arm streamed it, else from the command. Ticks whose state never
    completed (lost packets) are filled: angles and speeds linearly, commands held; `filled`
    counts them.
    """

    dt: float
    t: np.ndarray  # (N+1,) loop time (s)
    q: np.ndarray  # (N+1, 4) rad, as the arm reported them
    qdot: np.ndarray  # (N+1, 4) rad/s
    command_mA: np.ndarray  # (N+1, 4) sent (after clipping and the barrier)
    current_mA: np.ndarray  # (N+1, 4) measured; NaN where the arm did not report it
    torque_Nm: np.ndarray  # (N+1, 4)
    filled: int

    @property
    def samples(self) -> int:
        return int(self.q.shape[0])


@dataclass(frozen=True)
class ControlSummary:
    target: np.ndarray
    final_q: np.ndarray
    final_error: np.ndarray  # target - q at the state that ended the run (rad)
    steps: int
    loop_seconds: float
    wall_seconds: float
    saturated_steps: int
    barrier_steps: int
    timing: TimingStats
    stopped_by: str  # "duration", "stop requested", or the error that ended the run
    error: str | None = None
    trace: LoopTrace | None = None  # None when fewer than two states were seen
    left_in: str = ""  # how the run left the arm (safe mode sent, or why it could not be)
    events: tuple[str, ...] = ()  # link, watchdog and fault events during the run

    @property
    def ok(self) -> bool:
        return self.error is None


GRACE_FRACTION = 0.25
"""An incomplete tick is handed to the loop this fraction of a period after it began ..."""
GRACE_SPAN_FACTOR = 1.5
"""... or, if later, this many times as long as a whole tick usually takes to arrive (a slow
line, or joints whose heartbeats are not in phase)."""


@dataclass(frozen=True)
class _Taken:
    ticks: int  # heartbeat ticks since the stream started
    values: np.ndarray  # position, velocity interleaved per joint
    times: np.ndarray  # arrival times of the values
    serial: int
    currents: np.ndarray  # latest measured currents (NaN until reported)
    partial: bool  # some slot was missing and filled from the previous tick


class _StateAssembler:
    """Turns the joints' POSITION and VELOCITY heartbeats into one state per heartbeat tick.

    Runs as a reader-thread listener. The joints send their heartbeat packets in a fixed
    order, which is learnt from the first complete tick. A tick begins when a packet arrives
    that comes no later in that order than the last one of the current tick (or when a slot,
    joint x packet, repeats), so ticks are counted even when packets are lost, and a lost
    packet costs only its own tick: neither the count of arm time nor the tick boundary
    drifts (per-slot counts would undercount arm time under steady loss, and completing on
    "every slot refreshed" would leave part of every later state a tick stale after one loss).

    A tick is published once all eight slots are in, or incomplete as soon as the last packet
    in the order has come (the missing ones were lost); when it is the last one that is lost,
    `take` hands the tick out GRACE_FRACTION of a period after it began (the period in wall
    time is the median spacing of recent ticks), or GRACE_SPAN_FACTOR times the usual time a
    whole tick takes to arrive if that is longer. In an incomplete tick a missing position is
    extrapolated from the previous one and its velocity, a missing velocity is held. A tick in
    which every packet is lost is not counted. The latest CURRENT of each joint rides along.
    """

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.currents = np.full(N, np.nan)
        self.values = np.full(2 * N, np.nan)
        self.times = np.full(2 * N, np.nan)
        self.have = np.zeros(2 * N, dtype=bool)
        self.prev_values = np.full(2 * N, np.nan)
        self.prev_times = np.full(2 * N, np.nan)
        self.tick = -1
        self.tick_start = math.nan
        self.published_tick = -1
        self.order: dict[int, int] = {}  # slot -> place in a tick, once learnt
        self.sequence: list[int] = []  # slots of the current tick in arrival order
        self.last_place = -1
        self._starts: deque[float] = deque(maxlen=17)
        self._spans: deque[float] = deque(maxlen=17)  # first to last packet of whole ticks
        self._index = {int(d): i for i, d in enumerate(JOINTS)}
        self._cond = threading.Condition()
        self._latest: _Taken | None = None
        self.completed = 0  # states published
        self.skipped = 0  # published but superseded before the loop took them
        self.partial = 0  # published incomplete, after the grace
        self.incomplete = 0  # ticks never published

    def __call__(self, packet: Packet, t: float) -> None:
        pid = packet.packet_id
        if pid != PacketID.POSITION and pid != PacketID.VELOCITY and pid != PacketID.CURRENT:
            return
        i = self._index.get(int(packet.device_id))
        if i is None:
            return
        try:
            value = packet.as_float()
        except ProtocolError:
            return
        with self._cond:
            if pid == PacketID.CURRENT:
                self.currents[i] = value
                return
            slot = 2 * i + (0 if pid == PacketID.POSITION else 1)
            place = self.order.get(slot, -1)
            if self.tick < 0 or self.have[slot] or (0 <= place <= self.last_place):
                self._new_tick(t)
            self.values[slot] = value
            self.times[slot] = t
            self.have[slot] = True
            self.sequence.append(slot)
            self.last_place = max(self.last_place, place)
            if self.published_tick == self.tick:
                return
            if self.have.all():
                if len(self.sequence) == 2 * N:
                    self.order = {s: k for k, s in enumerate(self.sequence)}
                    self._spans.append(t - self.tick_start)
                self._publish()
            elif place == 2 * N - 1:
                self._publish()  # the tick's last packet: the missing ones were lost

    def _new_tick(self, t: float) -> None:
        if self.tick >= 0 and self.published_tick != self.tick:
            self.incomplete += 1
        self.prev_values[self.have] = self.values[self.have]
        self.prev_times[self.have] = self.times[self.have]
        self.have[:] = False
        self.sequence = []
        self.last_place = -1
        self.tick += 1
        self.tick_start = t
        self._starts.append(t)

    def _publish(self) -> bool:
        """Hand out the current tick (called with the lock held); False if it cannot be
        filled (a slot has never been seen)."""
        values, times = self.values.copy(), self.times.copy()
        missing = ~self.have
        partial = bool(missing.any())
        if partial:
            pos, vel = self.prev_values[0::2], self.prev_values[1::2]
            fill = np.empty(2 * N)
            fill[0::2] = pos + vel * self.period_s
            fill[1::2] = vel
            values[missing] = fill[missing]
            times[missing] = self.prev_times[missing]
            if not np.all(np.isfinite(values)):
                return False
            self.partial += 1
        if self._latest is not None:
            self.skipped += 1
        self.completed += 1
        self.published_tick = self.tick
        self._latest = _Taken(
            self.tick, values, times, self.completed, self.currents.copy(), partial
        )
        self._cond.notify()
        return True

    def _grace_end(self) -> float | None:
        """When the open tick may be handed out incomplete (None: not yet knowable)."""
        if self.tick < 0 or self.published_tick == self.tick or len(self._starts) < 3:
            return None
        spacing = float(np.median(np.diff(np.asarray(self._starts))))
        if not spacing > 0:
            return None
        span = float(np.median(np.asarray(self._spans))) if self._spans else 0.0
        return self.tick_start + max(GRACE_FRACTION * spacing, GRACE_SPAN_FACTOR * span)

    def take(self, timeout: float) -> _Taken | None:
        """The newest state not yet taken; None if nothing came within `timeout` s."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._latest is None:
                now = time.monotonic()
                grace = self._grace_end()
                if grace is not None and now >= grace and self._publish():
                    break
                if now >= deadline:
                    break
                until = deadline if grace is None or grace <= now else min(deadline, grace)
                self._cond.wait(max(until - now, 1e-4))
            latest, self._latest = self._latest, None
            return latest

    def newer_than(self, serial: int) -> bool:
        return self.completed > serial


def preferred_period(controller: object) -> float | None:
    """The control period a controller asks for (`period_s`, or `control_hz`), if any.

    A learned policy only works at the rate it was trained at, so a controller that knows its
    rate should say so and the CLI uses it unless told otherwise."""
    period = getattr(controller, "period_s", None)
    if isinstance(period, (int, float)) and math.isfinite(period) and period > 0:
        return float(period)
    hz = getattr(controller, "control_hz", None)
    if isinstance(hz, (int, float)) and math.isfinite(hz) and hz > 0:
        return 1.0 / float(hz)
    return None


class ControlLoop:
    """Runs `controller` against `client` at `period_s` (see the module docstring)."""

    def __init__(
        self,
        client: ArmClient,
        controller: Controller,
        period_s: float = 0.05,
        *,
        pacing: Pacing | str = Pacing.STREAM,
        on_step: StepHook | None = None,
        state_timeout_s: float | None = None,
        leave_safe: bool = True,
        measure_current: bool = True,
        reconnect_wait_s: float = RECONNECT_WAIT_S,
    ) -> None:
        self.client = client
        self.controller = controller
        self.pacing = Pacing(pacing)
        if self.pacing is Pacing.STREAM:
            hz = round(1.0 / period_s)
            if not 1 <= hz <= 255:
                raise ValueError(
                    f"period {period_s} s needs a {1 / period_s:.3g} Hz heartbeat; the arm "
                    "streams at 1..255 Hz (use --pacing poll for other periods)"
                )
            self.hz = hz
            self.period_s = 1.0 / hz
        else:
            if period_s <= 0:
                raise ValueError(f"period must be positive, got {period_s}")
            self.hz = 0
            self.period_s = period_s
        self.on_step = on_step
        self.state_timeout_s = state_timeout_s or max(0.5, 10 * self.period_s)
        self.leave_safe = leave_safe
        self.measure_current = measure_current
        self.reconnect_wait_s = reconnect_wait_s
        self._stop = threading.Event()

    def stop(self) -> None:
        """Ask a running loop to end after its current step (from any thread)."""
        self._stop.set()

    def run(self, target: Sequence[float] | np.ndarray, seconds: float) -> ControlSummary:
        """Drive towards `target` (E D C B, rad) for `seconds` of loop time."""
        goal = np.asarray(target, dtype=float).reshape(-1)
        if goal.shape != (N,):
            raise ValueError(f"target needs 4 angles in joint order E D C B, got {goal.size}")
        for dev, value in zip(JOINTS, goal, strict=True):
            self.client.guard.check(int(dev), LimitKind.POSITION, float(value))
        if seconds <= 0:
            raise ValueError(f"seconds must be positive, got {seconds}")
        self._stop.clear()
        events_before = len(self.client.events)
        run = _Run(self, goal, seconds)
        try:
            run.execute()
        except DriverError as exc:
            run.error = str(exc)
            run.stopped_by = f"{type(exc).__name__}: {exc}"
        finally:
            run.cleanup()
        history = list(self.client.events)
        run.events = tuple(f"{e.kind.value}: {e.message}" for e in history[events_before:])
        return run.summary()


def _past(deadline: float) -> Callable[[], bool]:
    return lambda: time.monotonic() > deadline


def _superseded(assembler: _StateAssembler, serial: int) -> Callable[[], bool]:
    return lambda: assembler.newer_than(serial)


class _Run:
    """The bookkeeping of one `ControlLoop.run`."""

    def __init__(self, loop: ControlLoop, goal: np.ndarray, seconds: float) -> None:
        self.loop = loop
        self.client = loop.client
        self.goal = goal
        self.seconds = seconds
        limits = [self.client.guard.limit(int(d), LimitKind.CURRENT) for d in JOINTS]
        self.i_lo = np.array([lim.low for lim in limits])
        self.i_hi = np.array([lim.high for lim in limits])
        self.step = 0
        self.t = 0.0
        self.q = np.full(N, np.nan)
        self.qdot = np.full(N, np.nan)
        self.step_walls: list[float] = []
        # one row per state taken (the trace): loop time, q, qdot, measured current, command
        self.rows_t: list[float] = []
        self.rows_q: list[np.ndarray] = []
        self.rows_qdot: list[np.ndarray] = []
        self.rows_current: list[np.ndarray] = []
        self.rows_command: list[np.ndarray] = []
        self.final: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.next_status_t = 0.0
        self.status_joint = 0
        self.left_in = ""
        self.events: tuple[str, ...] = ()
        self.mode_set = False
        self.ages: list[float] = []
        self.latencies: list[float] = []
        self.missed = 0
        self.saturated = 0
        self.barrier = 0
        self.error: str | None = None
        self.stopped_by = "duration"
        self.assembler: _StateAssembler | None = None
        self.t0_wall = time.monotonic()
        self.wall_end = self.t0_wall
        self.cpu0 = time.thread_time()
        self.pcpu0 = time.process_time()
        self.cpu = 0.0
        self.pcpu = 0.0

    # -- the loop ---------------------------------------------------------------------------
    def execute(self) -> None:
        loop = self.loop
        loop.controller.reset()
        if loop.pacing is Pacing.STREAM:
            self._run_stream()
        else:
            self._run_poll()

    def _run_stream(self) -> None:
        loop, client = self.loop, self.client
        self.assembler = asm = _StateAssembler(loop.period_s)
        subscription = client.subscribe(asm)
        try:
            ids = TELEMETRY_WITH_CURRENT if loop.measure_current else TELEMETRY
            client.stream(ids, loop.hz, JOINTS)
            ticks0: int | None = None
            while not loop._stop.is_set():
                got = asm.take(loop.state_timeout_s)
                if got is None:
                    raise DriverError(
                        f"feedback stopped: no complete state for {loop.state_timeout_s:.2f} s "
                        f"(link {client.link_state.value}: {client.link_reason})"
                    )
                if ticks0 is None:
                    ticks0 = got.ticks
                    self.t0_wall = time.monotonic()
                    self.cpu0, self.pcpu0 = time.thread_time(), time.process_time()
                t = (got.ticks - ticks0) / loop.hz
                q, qdot = got.values[0::2], got.values[1::2]
                if t >= self.seconds - 1e-9:
                    self.final = (t, q.copy(), qdot.copy(), got.currents)
                    break
                self._act(t, q, qdot, got.times, _superseded(asm, got.serial), got.currents)
            else:
                self.stopped_by = "stop requested"
        finally:
            subscription.cancel()
            self._finish_timing()

    def _run_poll(self) -> None:
        loop, client = self.loop, self.client
        period = loop.period_s
        self.t0_wall = next_t = time.monotonic()
        self.cpu0, self.pcpu0 = time.thread_time(), time.process_time()
        try:
            while not loop._stop.is_set():
                t = next_t - self.t0_wall
                if t >= self.seconds - 1e-9:
                    break
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                replies = client.request_many(
                    JOINTS, TELEMETRY, timeout_s=max(0.8 * period, 0.005), retries=0, partial=True
                )
                values = np.full(2 * N, np.nan)
                times = np.full(2 * N, np.nan)
                for i, dev in enumerate(JOINTS):
                    js = client.joint(dev)
                    got = replies.get(int(dev), {})
                    for j, (pid, reading) in enumerate(
                        ((PacketID.POSITION, js.position), (PacketID.VELOCITY, js.velocity))
                    ):
                        if pid in got and reading is not None:
                            values[2 * i + j], times[2 * i + j] = reading.value, reading.t
                next_t += period
                if np.isnan(values).any():
                    self.missed += 1  # replies late or lost: no step this period
                else:
                    self._act(t, values[0::2], values[1::2], times, _past(next_t), None)
                now = time.monotonic()
                if now > next_t:
                    lost = math.floor((now - next_t) / period) + 1
                    self.missed += lost
                    next_t += lost * period
            else:
                self.stopped_by = "stop requested"
        finally:
            self._finish_timing()

    def _act(
        self,
        t: float,
        q: np.ndarray,
        qdot: np.ndarray,
        times: np.ndarray,
        late: Callable[[], bool],
        currents: np.ndarray | None,
    ) -> None:
        loop, client = self.loop, self.client
        faults = client.blocking_faults()
        if faults:
            named = "; ".join(f"{joint_name(d)}: {', '.join(f)}" for d, f in faults.items())
            raise ArmFaultError(f"the arm reports a fault at t = {t:.2f} s: {named}")
        now = time.monotonic()
        self.t, self.q, self.qdot = t, q, qdot
        self.step_walls.append(now)
        age = now - float(np.min(times))
        raw = np.asarray(
            loop.controller.act(ControlState(q.copy(), qdot.copy(), t), self.goal.copy()),
            dtype=float,
        ).reshape(-1)
        if raw.shape != (N,) or not np.all(np.isfinite(raw)):
            raise DriverError(f"controller returned {raw!r}: need 4 finite currents in mA")
        clipped = np.clip(raw, self.i_lo, self.i_hi)
        saturated = bool(np.any(clipped != raw))
        if not self.mode_set:
            # Only now: until the controller has acted the joints keep holding as they were.
            client.set_mode(JOINTS, Mode.CURRENT)
            self.mode_set = True
        sent = client.command_currents(clipped)
        written = time.monotonic()
        if t >= self.next_status_t:
            # Fire and forget: the reply updates the client's fault flags, checked each step.
            device = int(JOINTS[self.status_joint])
            client.write_frames([commands.request(device, [PacketID.HARDWARE_STATUS]).encode()])
            self.status_joint = (self.status_joint + 1) % N
            self.next_status_t = t + STATUS_PERIOD_S / N
        barrier = bool(np.any(sent != clipped))
        latency = written - float(np.max(times))
        self.ages.append(age)
        self.latencies.append(latency)
        self.saturated += saturated
        self.barrier += barrier
        if late():
            self.missed += 1
        measured = None if currents is None else currents.copy()
        torque = self._torque(measured)
        self.rows_t.append(t)
        self.rows_q.append(q.copy())
        self.rows_qdot.append(qdot.copy())
        self.rows_current.append(np.full(N, np.nan) if measured is None else measured)
        self.rows_command.append(np.asarray(sent, dtype=float).copy())
        if loop.on_step is not None:
            stats = client.decoder_stats
            loop.on_step(
                StepRecord(
                    step=self.step,
                    t=t,
                    wall_t=now - self.t0_wall,
                    q=q.copy(),
                    qdot=qdot.copy(),
                    target=self.goal.copy(),
                    raw_command_mA=raw,
                    command_mA=sent,
                    state_age_s=age,
                    latency_s=latency,
                    saturated=saturated,
                    barrier=barrier,
                    good_frames=stats.good_frames,
                    bad_frames=stats.bad_total,
                    current_mA=measured,
                    torque_Nm=torque,
                )
            )
        self.step += 1

    def _torque(self, measured: np.ndarray | None) -> np.ndarray:
        """Torque over the period ending now: the measured current where there is one, else
        the command held over that period."""
        held = self.rows_command[-1] if self.rows_command else np.zeros(N)
        if measured is None:
            return torque_from_current(held)
        return torque_from_current(np.where(np.isfinite(measured), measured, held))

    def _finish_timing(self) -> None:
        self.wall_end = time.monotonic()
        self.cpu = time.thread_time() - self.cpu0
        self.pcpu = time.process_time() - self.pcpu0

    def cleanup(self) -> None:
        client = self.client
        mode = client.guard.config.safe_mode.name.lower()
        after = ""
        if client.link_state is not LinkState.UP:
            # The client sends the safe mode by itself once the link is back; wait a little
            # for that so the run can say how it left the arm.
            lost = f"{client.link_state.value} ({client.link_reason})"
            wait = self.loop.reconnect_wait_s if client.link_config.reconnect else 0.0
            deadline = time.monotonic() + wait
            while client.link_state is not LinkState.UP and time.monotonic() < deadline:
                if client.link_state is LinkState.CLOSED:
                    break
                time.sleep(0.02)
            if client.link_state is not LinkState.UP:
                self.left_in = (
                    f"unknown: the link is {lost} after waiting {wait:g} s; "
                    f"the driver sends {mode} as soon as the arm answers again"
                )
                return
            after = " after the link came back"
        try:
            client.stop_stream()
        except DriverError as exc:
            log.warning("could not stop streaming: %s", exc)
        if not self.loop.leave_safe:
            self.left_in = f"as the controller left it (leave_safe off){after}"
            return
        try:
            client.safe_stop(JOINTS)
            self.left_in = f"{mode}{after}"
        except DriverError as exc:
            log.warning("could not put the joints in the safe mode: %s", exc)
            self.left_in = f"unknown: could not send {mode}: {exc}"

    # -- results ----------------------------------------------------------------------------
    def trace(self) -> LoopTrace | None:
        """The rows on the uniform tick grid (see LoopTrace); None with under two states."""
        ts = list(self.rows_t)
        qs, qds, cur = list(self.rows_q), list(self.rows_qdot), list(self.rows_current)
        cmds = list(self.rows_command)
        if self.final is not None:
            t, q, qdot, currents = self.final
            ts.append(t)
            qs.append(q)
            qds.append(qdot)
            cur.append(currents)
        if len(ts) < 2:
            return None
        dt = self.loop.period_s
        k = np.rint(np.asarray(ts) / dt).astype(int)
        n = int(k[-1])
        grid = np.arange(n + 1)
        q_arr, qd_arr = np.asarray(qs), np.asarray(qds)
        q_out = np.column_stack([np.interp(grid, k, q_arr[:, j]) for j in range(N)])
        qd_out = np.column_stack([np.interp(grid, k, qd_arr[:, j]) for j in range(N)])
        # command row i = what was held over the period ending at sample i
        cmd_rows = np.zeros((n + 1, N))
        cur_rows = np.full((n + 1, N), np.nan)
        held = np.zeros(N)
        by_tick = {int(kk): i for i, kk in enumerate(k)}
        for i in range(n + 1):
            if i > 0 and (i - 1) in by_tick and by_tick[i - 1] < len(cmds):
                held = cmds[by_tick[i - 1]]
            cmd_rows[i] = held if i > 0 else 0.0
            if i in by_tick:
                cur_rows[i] = cur[by_tick[i]]
        measured = np.where(np.isfinite(cur_rows), cur_rows, cmd_rows)
        measured[0] = np.where(np.isfinite(cur_rows[0]), cur_rows[0], 0.0)
        return LoopTrace(
            dt=dt,
            t=grid * dt,
            q=q_out,
            qdot=qd_out,
            command_mA=cmd_rows,
            current_mA=cur_rows,
            torque_Nm=torque_from_current(measured),
            filled=int(n + 1 - len(set(k.tolist()))),
        )

    def summary(self) -> ControlSummary:
        steps = self.step
        wall = max(self.wall_end - self.t0_wall, 1e-9)
        loop_seconds = self.t + (self.loop.period_s if steps else 0.0)
        intervals = np.diff(self.step_walls) if len(self.step_walls) > 1 else np.zeros(1)
        mean = float(np.mean(intervals))
        asm = self.assembler
        skipped = asm.skipped if asm is not None else 0

        def pct(values: list[float], p: float) -> float:
            return float(np.percentile(values, p)) if values else math.nan

        timing = TimingStats(
            steps=steps,
            nominal_period_s=self.loop.period_s,
            rate_hz=steps / wall,
            arm_speed=loop_seconds / wall,
            period_mean_s=mean,
            period_jitter_s=float(np.std(intervals)),
            period_jitter_max_s=float(np.max(np.abs(intervals - mean))),
            state_age_p50_s=pct(self.ages, 50),
            state_age_p99_s=pct(self.ages, 99),
            state_age_max_s=max(self.ages, default=math.nan),
            latency_p50_s=pct(self.latencies, 50),
            latency_p99_s=pct(self.latencies, 99),
            latency_max_s=max(self.latencies, default=math.nan),
            missed_deadlines=self.missed,
            skipped_states=skipped,
            cpu_per_step_s=self.cpu / steps if steps else math.nan,
            process_cpu_per_step_s=self.pcpu / steps if steps else math.nan,
            partial_states=asm.partial if asm is not None else 0,
            incomplete_ticks=asm.incomplete if asm is not None else 0,
        )
        # The state that ended the run is the last one the arm reported.
        final_q = self.final[1] if self.final is not None else self.q
        return ControlSummary(
            target=self.goal.copy(),
            final_q=final_q.copy(),
            final_error=self.goal - final_q,
            steps=steps,
            loop_seconds=loop_seconds,
            wall_seconds=wall,
            saturated_steps=self.saturated,
            barrier_steps=self.barrier,
            timing=timing,
            stopped_by=self.stopped_by,
            error=self.error,
            trace=self.trace(),
            left_in=self.left_in,
            events=self.events,
        )
