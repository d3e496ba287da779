"""The closed loop: any controller `act(state, target) -> currents` against the live arm.

Two pacings, one code path for the virtual arm and a real one:

- `Pacing.STREAM` (default): the arm paces the loop. Each joint streams POSITION and
  VELOCITY as its heartbeat at the control rate; the loop steps once per complete state and
  counts time in heartbeat ticks, i.e. in ARM time. Against `reach-sim --speed X` a run takes
  1/X of the wall time and sees the same sequence of states.
- `Pacing.POLL`: the host paces the loop on its own clock and REQUESTs the state each period
  (for arms whose heartbeat cannot be set). Time is wall time.

Controller outputs are clipped to the current limits (counted as saturation) and then pass
the client's soft barrier; a per-step hook receives a `StepRecord` (a recorder logs these).
On any exit, Ctrl-C included, the joints are put in the safe mode and streaming is stopped.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import numpy as np

from protocol import Mode, Packet, PacketID, ProtocolError
from reach_driver.client import ArmClient
from reach_driver.errors import DriverError
from reach_driver.link import LinkState
from reach_driver.safety import LimitKind
from reach_driver.state import JOINTS

log = logging.getLogger(__name__)

N = len(JOINTS)
TELEMETRY = (PacketID.POSITION, PacketID.VELOCITY)


class Pacing(str, Enum):
    STREAM = "stream"
    POLL = "poll"


@dataclass(frozen=True)
class ControlState:
    """What a controller sees: arm angles and velocities (E D C B) and the loop's time (s)."""

    q: np.ndarray
    qdot: np.ndarray
    t: float


class Controller(Protocol):
    def reset(self) -> None: ...

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray: ...


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


@dataclass(frozen=True)
class ControlSummary:
    target: np.ndarray
    final_q: np.ndarray
    final_error: np.ndarray  # target - q at the last step (rad)
    steps: int
    loop_seconds: float
    wall_seconds: float
    saturated_steps: int
    barrier_steps: int
    timing: TimingStats
    stopped_by: str  # "duration", "stop requested", or the error that ended the run
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


class _StateAssembler:
    """Reader-thread listener: gathers POSITION and VELOCITY of the four joints and publishes
    a state when every one has been refreshed; ticks are counted per (joint, packet) slot so
    one lost packet neither stalls the loop nor skews arm time."""

    def __init__(self) -> None:
        self.values = np.full(2 * N, np.nan)
        self.times = np.full(2 * N, np.nan)
        self.counts = np.zeros(2 * N, dtype=np.int64)
        self.fresh = np.zeros(2 * N, dtype=bool)
        self._index = {int(d): i for i, d in enumerate(JOINTS)}
        self._cond = threading.Condition()
        self._latest: tuple[int, np.ndarray, np.ndarray, int] | None = None
        self.completed = 0
        self.skipped = 0

    def __call__(self, packet: Packet, t: float) -> None:
        pid = packet.packet_id
        if pid != PacketID.POSITION and pid != PacketID.VELOCITY:
            return
        i = self._index.get(int(packet.device_id))
        if i is None:
            return
        try:
            value = packet.as_float()
        except ProtocolError:
            return
        slot = 2 * i + (0 if pid == PacketID.POSITION else 1)
        self.values[slot] = value
        self.times[slot] = t
        self.counts[slot] += 1
        self.fresh[slot] = True
        if self.fresh.all():
            self.fresh[:] = False
            with self._cond:
                if self._latest is not None:
                    self.skipped += 1
                self.completed += 1
                ticks = int(self.counts.max())
                self._latest = (ticks, self.values.copy(), self.times.copy(), self.completed)
                self._cond.notify()

    def take(self, timeout: float) -> tuple[int, np.ndarray, np.ndarray, int] | None:
        """The newest complete state not yet taken: (ticks, values, arrival times, serial)."""
        with self._cond:
            if self._latest is None:
                self._cond.wait(timeout)
            latest, self._latest = self._latest, None
            return latest

    def newer_than(self, serial: int) -> bool:
        return self.completed > serial


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
        run = _Run(self, goal, seconds)
        try:
            run.execute()
        except DriverError as exc:
            run.error = str(exc)
            run.stopped_by = f"{type(exc).__name__}: {exc}"
        finally:
            run.cleanup()
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
        loop, client = self.loop, self.client
        loop.controller.reset()
        client.set_mode(JOINTS, Mode.CURRENT)
        if loop.pacing is Pacing.STREAM:
            self._run_stream()
        else:
            self._run_poll()

    def _run_stream(self) -> None:
        loop, client = self.loop, self.client
        self.assembler = asm = _StateAssembler()
        subscription = client.subscribe(asm)
        try:
            client.stream(TELEMETRY, loop.hz, JOINTS)
            ticks0: int | None = None
            while not loop._stop.is_set():
                got = asm.take(loop.state_timeout_s)
                if got is None:
                    raise DriverError(
                        f"feedback stopped: no complete state for {loop.state_timeout_s:.2f} s "
                        f"(link {client.link_state.value}: {client.link_reason})"
                    )
                ticks, values, times, serial = got
                if ticks0 is None:
                    ticks0 = ticks
                    self.t0_wall = time.monotonic()
                    self.cpu0, self.pcpu0 = time.thread_time(), time.process_time()
                t = (ticks - ticks0) / loop.hz
                if t >= self.seconds - 1e-9:
                    break
                self._act(t, values[0::2], values[1::2], times, _superseded(asm, serial))
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
                    self._act(t, values[0::2], values[1::2], times, _past(next_t))
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
    ) -> None:
        loop, client = self.loop, self.client
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
        sent = client.command_currents(clipped)
        written = time.monotonic()
        barrier = bool(np.any(sent != clipped))
        latency = written - float(np.max(times))
        self.ages.append(age)
        self.latencies.append(latency)
        self.saturated += saturated
        self.barrier += barrier
        if late():
            self.missed += 1
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
                )
            )
        self.step += 1

    def _finish_timing(self) -> None:
        self.wall_end = time.monotonic()
        self.cpu = time.thread_time() - self.cpu0
        self.pcpu = time.process_time() - self.pcpu0

    def cleanup(self) -> None:
        client = self.client
        if client.link_state is not LinkState.UP:
            return  # the client sends the safe mode itself once the link is back
        try:
            client.stop_stream()
        except DriverError as exc:
            log.warning("could not stop streaming: %s", exc)
        if self.loop.leave_safe:
            try:
                client.safe_stop(JOINTS)
            except DriverError as exc:
                log.warning("could not put the joints in the safe mode: %s", exc)

    # -- results ----------------------------------------------------------------------------
    def summary(self) -> ControlSummary:
        steps = self.step
        wall = max(self.wall_end - self.t0_wall, 1e-9)
        loop_seconds = self.t + (self.loop.period_s if steps else 0.0)
        intervals = np.diff(self.step_walls) if len(self.step_walls) > 1 else np.zeros(1)
        mean = float(np.mean(intervals))
        skipped = self.assembler.skipped if self.assembler is not None else 0

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
        )
        return ControlSummary(
            target=self.goal.copy(),
            final_q=self.q.copy(),
            final_error=self.goal - self.q,
            steps=steps,
            loop_seconds=loop_seconds,
            wall_seconds=wall,
            saturated_steps=self.saturated,
            barrier_steps=self.barrier,
            timing=timing,
            stopped_by=self.stopped_by,
            error=self.error,
        )
