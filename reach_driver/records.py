"""What a control run hands out: one `StepRecord` per step, and a `ControlSummary` at the end
with its `TimingStats` and the run as a uniformly sampled `LoopTrace`.

Plain frozen records, so a step hook, a recorder or `policy` can keep them without holding
on to the loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from protocol.models import ALPHA5, ArmModel
from reach_driver.chatter import Verdict
from reach_driver.loop_timing import GapStats
from reach_driver.realtime import RealtimeReport


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
    #: Wall seconds since the previous command (NaN at the first): what the watchdog judges.
    loop_period_s: float = float("nan")


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
    stream_gaps: int = 0  # gaps in the stream (ticks lost whole, or the host stalled)
    lost_ticks: int = 0  # ticks those gaps could have held: arm time not counted (at most)
    #: The gaps between commands (what the watchdog judges): percentiles, the longest taken apart.
    gaps: GapStats = field(default_factory=GapStats)
    #: Whether the loop and the link's reader ran with real-time priority, and why not.
    realtime: RealtimeReport = field(default_factory=RealtimeReport)


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
    stopped_by: str  # "duration", "stop requested", the chatter guard, or the error that ended it
    error: str | None = None
    trace: LoopTrace | None = None  # None when fewer than two states were seen
    left_in: str = ""  # how the run left the arm (safe mode sent, or why it could not be)
    events: tuple[str, ...] = ()  # link, watchdog and fault events during the run
    chatter: Verdict | None = None  # set when the chatter guard ended the run (docs/chatter.md)
    implausible_samples: int = 0  # joint samples refused as physically impossible (held)
    measured_hz: float | None = None  # the stream's rate from the arm's kinematics (None: unmoved)
    duplicate_packets: int = 0  # stream packets received twice in a row, dropped
    model: ArmModel = ALPHA5  # the arm run: its joints are the arrays' order

    @property
    def ok(self) -> bool:
        return self.error is None
