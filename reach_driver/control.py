"""The closed loop: any controller `act(state, target) -> currents` against the live arm.

Two pacings, one code path for the virtual arm and a real one:

- `Pacing.STREAM` (default): the arm paces the loop. Each joint streams CURRENT, POSITION and
  VELOCITY as its heartbeat at the control rate; the loop steps once per heartbeat tick (see
  `reach_driver.assembler` for lost packets) and counts time in ticks, i.e. in ARM time. Against
  `reach-sim --speed X` a run takes 1/X of the wall time and sees the same sequence of states.
- `Pacing.POLL`: the host paces the loop on its own clock and REQUESTs the state each period
  (for arms whose heartbeat cannot be set). Time is wall time.

Before a controller sees a state, every joint's position and velocity must be fresh (reported
within the stale limit, in arm time) and plausible (`reach_driver.plausibility`: an implausible
sample is held at the last good one, counted and reported; one that lasts ends the run), and
the stream must run at the rate asked (`reach_driver.stream_rate`, measured from the arm's
kinematics; a wrong rate ends the run).

Controller outputs are clipped to the current limits (counted as saturation) and then pass
the client's soft barrier; a per-step hook receives a `StepRecord` (a recorder logs these).
The joints enter current mode only with the first command, so they hold their previous mode
until the controller has seen a state. Each joint's status flags are polled once a second; a
motor, driver or encoder fault ends the run (`ArmFaultError`). The chatter guard
(`SafetyConfig.chatter`, `reach_driver.chatter`) watches every step sent: when a joint
bang-bangs around its goal the driver stops asking the controller, holds the arm (POSITION
at the present angles, or ZERO_VELOCITY) and ends the run with the reason in `stopped_by`
and `chatter`. Every other end (the duration, a driver error, a non-finite reading from the
arm, an exception in the controller or the step hook, Ctrl-C or a signal raised as
`KeyboardInterrupt`) takes one path: streaming stopped, the joints put in the safe mode and
their modes read back, resent until the arm confirms it or `SafetyConfig.safe_wait_s` runs
out (a lost link is waited for meanwhile), and a summary whose `left_in` claims only what the
arm confirmed. An interrupt is passed on as `Interrupted` carrying that summary.

The loop's thread asks for real-time priority as the client's `realtime` policy says (the
reader asks as it starts; `reach_driver.realtime`) for the run and gets its own back after it;
a required priority not granted raises `RealtimeRefusedError` before anything is commanded, and
the summary's `timing.realtime` says what each thread was given.

The summary carries the run as a uniformly sampled `LoopTrace` (the state that ended the run
is its last row) from which `reach_driver.metrics` scores it like the evaluation runner does,
on the angles the arm reported; torque is current x the joint's torque constant.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from enum import Enum

import numpy as np

from protocol import Mode, PacketID, commands
from protocol.models import ALPHA5, ArmModel
from reach_driver.assembler import StateAssembler
from reach_driver.chatter import ChatterDetector, HoldMode, Verdict
from reach_driver.client import ArmClient
from reach_driver.controllers import Controller, ControlState
from reach_driver.errors import (
    ArmFaultError,
    BadReadingError,
    ControllerError,
    DriverError,
    Interrupted,
    RealtimeRefusedError,
    StreamRateError,
    WatchdogTrippedError,
)
from reach_driver.link import EventKind, LinkState
from reach_driver.loop_timing import Gap, GapLog
from reach_driver.plausibility import FeedbackCheck, PlausibilityConfig
from reach_driver.realtime import RealtimeReport, ThreadRole
from reach_driver.records import ControlSummary, LoopTrace, StepHook, StepRecord, TimingStats
from reach_driver.safety import LimitKind
from reach_driver.state import joint_name
from reach_driver.stream_rate import RateCheck, RateConfig
from reach_driver.streaming import Stream
from reach_driver.trace import FinalState, TraceRows
from reach_driver.watchdog import watchdog_too_short

log = logging.getLogger(__name__)

__all__ = [
    "ControlLoop",
    "ControlSummary",
    "LoopTrace",
    "Pacing",
    "StepHook",
    "StepRecord",
    "TimingStats",
    "control_period",
    "preferred_period",
]

TELEMETRY = (PacketID.POSITION, PacketID.VELOCITY)
# CURRENT first: a joint's heartbeat sends its ids in order, so the measured current is in
# before the VELOCITY that completes the state.
TELEMETRY_WITH_CURRENT = (PacketID.CURRENT, PacketID.POSITION, PacketID.VELOCITY)


def telemetry_fits(
    ids: Sequence[int], hz: int, wire_bytes_per_s: float | None, model: ArmModel = ALPHA5
) -> bool:
    """Whether the joints' heartbeat of `ids` at `hz` fits the link (None: no limit)."""
    return Stream(tuple(ids), hz, tuple(model.joints)).fits(wire_bytes_per_s)


STATUS_PERIOD_S = 1.0
"""Each joint's HARDWARE_STATUS is asked for this often (loop time) during a run, one joint at
a time so a half-duplex line never sees two answers at once; a motor, driver or encoder
fault ends the run."""


class Pacing(str, Enum):
    STREAM = "stream"
    POLL = "poll"


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


DEFAULT_PERIOD_S = 0.05


def control_period(controller: object, requested: float | None) -> tuple[float, str | None]:
    """The period to run at (the one asked for, else the controller's own, else 20 Hz) and a
    warning when it differs from the controller's own."""
    own = preferred_period(controller)
    period = requested or own or DEFAULT_PERIOD_S
    if own is not None and not math.isclose(period, own, rel_tol=1e-6):
        return period, (
            f"the controller asks for a {own:g} s period ({1 / own:g} Hz); running at "
            f"{period:g} s as told"
        )
    return period, None


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
        plausibility: PlausibilityConfig | None = None,
        stream_rate: RateConfig | None = None,
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
        too_short = watchdog_too_short(self.period_s, client.guard.config.watchdog_s)
        if too_short is not None:
            raise ValueError(too_short)
        self.on_step = on_step
        #: How long (host time) to wait for a complete state. Never shorter than the watchdog:
        #: without a state there is no command, and the watchdog makes the arm safe after
        #: `watchdog_s` without one anyway, so a shorter wait would only end the run sooner
        #: than safety asks, and `--watchdog` raised for a busy machine would not reach it.
        watchdog_s = client.guard.config.watchdog_s or 0.0
        self.state_timeout_s = state_timeout_s or max(0.5, 10 * self.period_s, watchdog_s)
        #: How long (arm time) a joint's position or velocity may go without a fresh, plausible
        #: sample before the run stops: the watchdog's limit, else the state timeout.
        self.stale_limit_s = client.guard.config.watchdog_s or self.state_timeout_s
        self.plausibility = plausibility or PlausibilityConfig()
        self.stream_rate = stream_rate or RateConfig()
        self.leave_safe = leave_safe
        self.measure_current = measure_current
        self._stop = threading.Event()

    def stop(self) -> None:
        """Ask a running loop to end after its current step, or the next run not to start
        stepping (from any thread, or a signal handler): it ends as every run does."""
        self._stop.set()

    def run(self, target: Sequence[float] | np.ndarray, seconds: float) -> ControlSummary:
        """Drive towards `target` (rad, in the arm's joint order: E D C B on the Alpha 5) for
        `seconds` of loop time."""
        model = self.client.model
        goal = np.asarray(target, dtype=float).reshape(-1)
        if goal.shape != (model.n_joints,):
            raise ValueError(
                f"target needs {model.n_joints} angles in joint order "
                f"{' '.join(model.joint_letters)}, got {goal.size}"
            )
        for dev, value in zip(model.joints, goal, strict=True):
            self.client.guard.check(int(dev), LimitKind.POSITION, float(value))
        if seconds <= 0:
            raise ValueError(f"seconds must be positive, got {seconds}")
        realtime = self.client.realtime
        with realtime.held(ThreadRole.LOOP):
            report = realtime.report(ThreadRole.LOOP, ThreadRole.READER)
            refusal = report.refusal()
            if refusal is not None:
                raise RealtimeRefusedError(refusal)  # before anything is commanded
            return self._run(goal, seconds, report)

    def _run(self, goal: np.ndarray, seconds: float, realtime: RealtimeReport) -> ControlSummary:
        events_before = len(self.client.events)
        run = _Run(self, goal, seconds, realtime)
        interrupted: KeyboardInterrupt | None = None
        try:
            run.execute()
        except _Guarded as exc:
            run.error = run.stopped_by = str(exc)
        except DriverError as exc:
            run.error = str(exc)
            if isinstance(exc, WatchdogTrippedError) and run.tripped_gap is not None:
                # where the loop's time went meanwhile (`reach_driver.loop_timing`)
                run.error += f"; the loop meanwhile: {run.tripped_gap.describe()}"
            run.stopped_by = f"{type(exc).__name__}: {exc}"
        except KeyboardInterrupt as exc:  # Ctrl-C, or a signal the caller turned into one
            interrupted = exc
            name = exc.signal_name if isinstance(exc, Interrupted) else "SIGINT"
            run.error = run.stopped_by = f"interrupted by {name} at t = {run.t:.2f} s"
        except Exception as exc:  # a bug anywhere in a step: still one way out, and said
            log.exception("the control loop failed")
            run.error = f"internal error at t = {run.t:.2f} s: {type(exc).__name__}: {exc}"
            run.stopped_by = f"{type(exc).__name__}: {exc}"
        finally:
            run.cleanup()
            self._stop.clear()  # asked of this run; the next starts afresh
        history = list(self.client.events)
        run.events = tuple(f"{e.kind.value}: {e.message}" for e in history[events_before:])
        if run.verdict is not None:
            run.events += (run.stopped_by,)
        summary = run.summary()
        if interrupted is not None:
            # Passed on, carrying how the run ended and how it left the arm.
            out = interrupted if isinstance(interrupted, Interrupted) else Interrupted()
            out.summary = summary
            out.left_in = summary.left_in
            if out is interrupted:
                raise out
            raise out from interrupted
        return summary


class _Guarded(Exception):
    """The chatter guard ended the run (the message is the summary's `stopped_by`)."""


def _past(deadline: float) -> Callable[[], bool]:
    return lambda: time.monotonic() > deadline


def _superseded(assembler: StateAssembler, serial: int) -> Callable[[], bool]:
    return lambda: assembler.newer_than(serial)


class _Run:
    """The bookkeeping of one `ControlLoop.run`."""

    def __init__(
        self, loop: ControlLoop, goal: np.ndarray, seconds: float, realtime: RealtimeReport
    ) -> None:
        self.loop = loop
        self.realtime = realtime
        self.client = loop.client
        self.goal = goal
        self.seconds = seconds
        #: The arm's model (the client's): its joints are every array's order here.
        self.model = self.client.model
        self.joints = self.model.joints
        n = self.n = self.model.n_joints
        limits = [self.client.guard.limit(int(d), LimitKind.CURRENT) for d in self.joints]
        self.i_lo = np.array([lim.low for lim in limits])
        self.i_hi = np.array([lim.high for lim in limits])
        self.step = 0
        self.t = 0.0
        self.q = np.full(n, np.nan)
        self.qdot = np.full(n, np.nan)
        self.step_walls: list[float] = []
        self.rows = TraceRows(self.model.torque_per_amp_nm)  # one per state taken
        self.final: FinalState | None = None
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
        self.assembler: StateAssembler | None = None
        self.feedback = FeedbackCheck(loop.plausibility, self.model)
        self.implausible = 0  # joint samples refused by the plausibility check
        self.held = np.zeros(n, dtype=bool)  # joints held at their last good sample this tick
        self.unseen_s = 0.0  # arm time lost whole in a gap before this state (estimated)
        self.bad_since = np.full(n, np.nan)  # arm time each joint turned implausible
        self.reported_t = -math.inf  # when implausible samples were last reported
        self.unreported = 0
        self.rate = RateCheck(loop.hz, loop.stream_rate) if loop.pacing is Pacing.STREAM else None
        chatter = self.client.guard.config.chatter
        self.chatter = (
            None
            if chatter is None
            else ChatterDetector(
                chatter,
                np.maximum(np.abs(self.i_lo), np.abs(self.i_hi)),
                self.model.joint_letters,
            )
        )
        self.verdict: Verdict | None = None
        self.held_in_position = False
        self.t0_wall = time.monotonic()
        self.wall_end = self.t0_wall
        self.cpu0 = time.thread_time()
        self.pcpu0 = time.process_time()
        self.cpu = 0.0
        self.pcpu = 0.0
        self.gap_log = GapLog(self.client.reader_away)  # the gaps between commands
        self.tripped_gap: Gap | None = None  # the gap the watchdog ended

    # -- the loop ---------------------------------------------------------------------------
    def execute(self) -> None:
        loop = self.loop
        loop.controller.reset()
        self.gap_log.start()
        without = self.realtime.without()
        self.client.loop_timing = lambda: self.gap_log.timing(loop.period_s, without)
        try:
            if loop.pacing is Pacing.STREAM:
                self._run_stream()
            else:
                self._run_poll()
        finally:
            self.gap_log.stop()
            self.client.loop_timing = None

    def _run_stream(self) -> None:
        loop, client = self.loop, self.client
        self.assembler = asm = StateAssembler(loop.period_s, self.joints)
        subscription = client.subscribe(asm)
        try:
            ids = TELEMETRY_WITH_CURRENT if loop.measure_current else TELEMETRY
            wire = client.transport.wire_bytes_per_s
            if ids is TELEMETRY_WITH_CURRENT and not telemetry_fits(ids, loop.hz, wire, self.model):
                # A slow line cannot carry CURRENT too at this rate (115200 baud: 96 Hz):
                # the arm's queue would drop frames and states would arrive stale.
                log.warning("%d Hz exceeds the line with CURRENT: streaming without it", loop.hz)
                ids = TELEMETRY
            client.stream(ids, loop.hz, self.joints)
            ticks0: int | None = None
            lost_before = 0
            while not loop._stop.is_set():
                asked = time.monotonic()
                got = asm.take(loop.state_timeout_s)
                held = time.monotonic()
                if got is not None:
                    complete = float(np.nanmax(got.times)) if np.isfinite(got.times).any() else 0
                    self.gap_log.add_state_wait(held - asked, complete, held)
                if got is None:
                    why = client.tripped or client.stream_problem()
                    raise DriverError(
                        f"feedback stopped: no complete state for {loop.state_timeout_s:.2f} s "
                        f"({why or f'link {client.link_state.value}: {client.link_reason}'})"
                    )
                if ticks0 is None:
                    ticks0 = got.ticks
                    self.t0_wall = time.monotonic()
                    self.cpu0, self.pcpu0 = time.thread_time(), time.process_time()
                t = (got.ticks - ticks0) / loop.hz
                self._check_fresh(t, (got.ticks - got.seen) / loop.hz)
                q, qdot = got.values[0::2], got.values[1::2]
                # joints whose position and velocity were both reported in this tick
                fresh = (got.seen[0::2] == got.ticks) & (got.seen[1::2] == got.ticks)
                # ticks lost whole since the last state taken (a gap in the stream: not
                # counted in t, so the checks comparing two samples allow for them)
                self.unseen_s, lost_before = (got.lost - lost_before) / loop.hz, got.lost
                if t >= self.seconds - 1e-9:
                    q, qdot = self._plausible(t, q, qdot, fresh)
                    self.final = (t, q.copy(), qdot.copy(), got.currents)
                    break
                self._act(t, q, qdot, got.times, _superseded(asm, got.serial), got.currents, fresh)
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
                asked = time.monotonic()
                delay = next_t - asked
                if delay > 0:
                    time.sleep(delay)
                replies = client.request_many(
                    self.joints,
                    TELEMETRY,
                    timeout_s=max(0.8 * period, 0.005),
                    retries=0,
                    partial=True,
                )
                held = time.monotonic()
                self.gap_log.add_state_wait(held - asked, held, held)
                values = np.full(2 * self.n, np.nan)
                times = np.full(2 * self.n, np.nan)
                for i, dev in enumerate(self.joints):
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
        fresh: np.ndarray | None = None,
    ) -> None:
        loop, client = self.loop, self.client
        faults = client.blocking_faults()
        if faults:
            named = "; ".join(f"{joint_name(d)}: {', '.join(f)}" for d, f in faults.items())
            raise ArmFaultError(f"the arm reports a fault at t = {t:.2f} s: {named}")
        self.t = t
        q, qdot = self._plausible(t, q, qdot, fresh)
        if np.isnan(q).any():
            return  # implausible before any good sample: nothing to hold, no step
        now = time.monotonic()
        self.q, self.qdot = q, qdot
        usable = ~self.held if fresh is None else fresh & ~self.held
        self._check_rate(t, q, qdot, usable)
        self.step_walls.append(now)
        age = now - float(np.min(times))
        try:
            raw = np.asarray(
                loop.controller.act(ControlState(q.copy(), qdot.copy(), t), self.goal.copy()),
                dtype=float,
            ).reshape(-1)
        except Exception as exc:
            raise ControllerError(
                f"the controller failed at t = {t:.2f} s: {type(exc).__name__}: {exc}"
            ) from exc
        finally:
            self.gap_log.add_controller(time.monotonic() - now)
        if raw.shape != (self.n,) or not np.all(np.isfinite(raw)):
            raise ControllerError(
                f"controller returned {raw!r}: need {self.n} finite currents in mA"
            )
        clipped = np.clip(raw, self.i_lo, self.i_hi)
        saturated = bool(np.any(clipped != raw))
        if not self.mode_set:
            # Only now: until the controller has acted the joints keep holding as they were.
            client.set_mode(self.joints, Mode.CURRENT)
            self.mode_set = True
        try:
            sent = client.command_currents(clipped)
        except WatchdogTrippedError:
            self.tripped_gap = self.gap_log.pending(time.monotonic(), self.step, t)
            raise
        written = time.monotonic()
        gap = self.gap_log.in_gap(written) if self.step else math.nan
        self.gap_log.command(written, self.step, t)
        if t >= self.next_status_t:
            # Fire and forget: the reply updates the client's fault flags, checked each step.
            device = int(self.joints[self.status_joint])
            client.write_frames([commands.request(device, [PacketID.HARDWARE_STATUS]).encode()])
            self.status_joint = (self.status_joint + 1) % self.n
            self.next_status_t = t + STATUS_PERIOD_S / self.n
        barrier = bool(np.any(sent != clipped))
        latency = written - float(np.max(times))
        self.ages.append(age)
        self.latencies.append(latency)
        self.saturated += saturated
        self.barrier += barrier
        if late():
            self.missed += 1
        measured = None if currents is None else currents.copy()
        torque = self.rows.period_torque(measured)
        self.rows.add(
            t,
            q.copy(),
            qdot.copy(),
            np.full(self.n, np.nan) if measured is None else measured,
            np.asarray(sent, dtype=float).copy(),
        )
        if loop.on_step is not None:
            stats = client.decoder_stats
            record = StepRecord(
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
                loop_period_s=gap,
            )
            hooked = time.monotonic()
            try:
                loop.on_step(record)
            except Exception as exc:
                raise ControllerError(
                    f"the step hook (recorder or viewer) failed at t = {t:.2f} s: "
                    f"{type(exc).__name__}: {exc}"
                ) from exc
            finally:
                self.gap_log.add_hook(time.monotonic() - hooked)
        self.step += 1
        if self.chatter is not None:
            verdict = self.chatter.update(t, q, qdot, sent, self.goal)
            if verdict is not None:
                self._hold(verdict, q)

    def _plausible(
        self, t: float, q: np.ndarray, qdot: np.ndarray, fresh: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The state a controller may see (`reach_driver.plausibility`): a non-finite reading
        ends the run; an implausible joint (outside the envelope, too fast, a jump, a velocity
        stuck while the joint moves otherwise; `fresh`: which velocities were reported now)
        is counted, reported (at most once a second) and held at its last good sample; one
        implausible for `stale_limit_s` ends the run."""
        for name, values, unit in (("position", q, "rad"), ("velocity", qdot, "rad/s")):
            bad = ~np.isfinite(values)
            if np.any(bad):
                which = ", ".join(
                    f"{joint_name(int(d))} {v}"
                    for d, v in zip(self.joints, values, strict=True)
                    if not np.isfinite(v)
                )
                raise BadReadingError(
                    f"the arm reported a non-finite {name} ({unit}) at t = {t:.2f} s: {which}; "
                    "no controller was given it"
                )
        verdict = self.feedback.check(t, q, qdot, fresh, self.unseen_s)
        self.held = verdict.bad
        self.bad_since = np.where(verdict.bad, np.fmin(self.bad_since, t), np.nan)
        if not verdict.bad.any():
            return q, qdot
        self.implausible += int(np.count_nonzero(verdict.bad))
        self.unreported += 1
        why = "; ".join(verdict.why)
        limit = self.loop.stale_limit_s
        lasting = t - self.bad_since
        if np.nanmax(lasting) >= limit - 1e-9:
            i = int(np.nanargmax(lasting))
            raise BadReadingError(
                f"implausible feedback from {joint_name(int(self.joints[i]))} for "
                f"{lasting[i]:.2f} s "
                f"of arm time (limit {limit:g} s, the stale limit) at t = {t:.2f} s: {why}; "
                "the arm's encoder or link is not to be trusted"
            )
        if t - self.reported_t >= 1.0:
            self.client.note_event(
                EventKind.IMPLAUSIBLE,
                f"{self.unreported} implausible sample(s), held at the last good state, "
                f"latest at t = {t:.2f} s: {why}",
            )
            self.reported_t, self.unreported = t, 0
        return self.feedback.held(q, qdot, verdict)

    def _check_rate(self, t: float, q: np.ndarray, qdot: np.ndarray, usable: np.ndarray) -> None:
        """The arm must stream at the rate asked (`reach_driver.stream_rate`, measured on the
        `usable` joints: reported in this tick and plausible): else arm time, the
        controller's step and the metrics are wrong, and the run stops before acting."""
        rate, hz = self.rate, self.loop.hz
        if rate is None:
            return
        rate.update(round(t * hz), q, qdot, usable, resumed=self.unseen_s > 0.0)
        if not rate.off():
            return
        measured = rate.measured_hz
        shown = "an unmeasurable rate" if measured is None else f"{measured:.3g} Hz"
        true_t = t * (rate.ratio or math.nan)
        raise StreamRateError(
            f"the arm streams at {shown}, asked {hz} Hz (measured from its positions and "
            f"velocities, tolerance {rate.config.tolerance:.0%}): at t = {t:.2f} s counted, "
            f"{true_t:.2f} s of arm time had passed; the controller's time step and the run's "
            "duration would be wrong. Check the arm's heartbeat frequency (HEARTBEAT_FREQUENCY)"
        )

    def _check_fresh(self, t: float, ages: np.ndarray) -> None:
        """Every value a controller uses must be fresh: a joint's position or velocity not
        reported for `stale_limit_s` of arm time (held or extrapolated meanwhile) ends the run."""
        limit = self.loop.stale_limit_s
        stale = ages > limit + 1e-9
        if not stale.any():
            return
        which = ", ".join(
            f"{joint_name(int(self.joints[k // 2]))} {'position' if k % 2 == 0 else 'velocity'} "
            f"({ages[k]:.2f} s)"
            for k in np.flatnonzero(stale)
        )
        raise BadReadingError(
            f"stale feedback at t = {t:.2f} s: {which} not reported for longer than {limit:g} s "
            "of arm time (the stale limit); the arm stopped sending it"
        )

    def _hold(self, verdict: Verdict, q: np.ndarray) -> None:
        """The chatter guard fired: hold the arm, never ask the controller again."""
        self.verdict = verdict
        hold = self.client.guard.config.chatter
        how = "held in zero velocity"
        if hold is not None and hold.hold is HoldMode.POSITION:
            try:
                self.client.command_positions(q)
                self.held_in_position = True
                how = "held in position"
            except DriverError as exc:  # e.g. an angle a hair outside a tightened bound
                log.warning("chatter guard: could not hold in position (%s)", exc)
                how = f"could not hold in position ({exc}); the safe mode follows"
        if not self.held_in_position:
            self.client.set_mode(self.joints, Mode.ZERO_VELOCITY)
        reason = f"chatter guard: {verdict.describe()} at t = {verdict.t:.2f} s; {how}"
        log.warning("%s", reason)
        raise _Guarded(reason)

    def _finish_timing(self) -> None:
        self.wall_end = time.monotonic()
        self.cpu = time.thread_time() - self.cpu0
        self.pcpu = time.process_time() - self.pcpu0

    def cleanup(self) -> None:
        """Stop streaming and leave the arm in the safe mode (`ArmClient.make_safe`: resent
        until the arm confirms it or `SafetyConfig.safe_wait_s` runs out); `left_in` says
        how, claiming only what the arm confirmed."""
        client = self.client
        if client.link_state is LinkState.UP:
            try:
                client.stop_stream()
            except DriverError as exc:
                log.warning("could not stop streaming: %s", exc)
        if self.held_in_position:
            # The guard's POSITION hold stays; the safe mode would release it.
            jaw = client.make_safe([self.model.jaw])
            if not jaw.confirmed:
                log.warning("the jaw's safe mode: %s", jaw.describe())
            try:
                problem = client.mode_problem(self.joints, Mode.POSITION)
            except DriverError as exc:
                problem = str(exc)
            how = "(confirmed by the arm)" if not problem else f"(not confirmed: {problem})"
            self.left_in = (
                f"position hold at the angles of t = {self.t:.2f} s (chatter guard) {how}"
            )
            return
        if not self.loop.leave_safe:
            self.left_in = "as the controller left it (leave_safe off)"
            return
        self.left_in = client.make_safe(self.joints).describe()

    # -- results ----------------------------------------------------------------------------
    def trace(self) -> LoopTrace | None:
        return self.rows.resample(self.loop.period_s, self.final)

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
            stream_gaps=asm.gaps if asm is not None else 0,
            lost_ticks=asm.lost if asm is not None else 0,
            gaps=self.gap_log.stats(),
            realtime=self.realtime,
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
            implausible_samples=self.implausible,
            measured_hz=None if self.rate is None else self.rate.measured_hz,
            duplicate_packets=asm.duplicates if asm is not None else 0,
            timing=timing,
            stopped_by=self.stopped_by,
            error=self.error,
            trace=self.trace(),
            left_in=self.left_in,
            events=self.events,
            chatter=self.verdict,
            model=self.model,
        )
