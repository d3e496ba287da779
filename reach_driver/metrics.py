"""Tracking metrics for one joint-space step response (definitions: docs/metrics.md).

Every controller is scored by the same functions on the simulator's true joint angles, so
the figures in docs/results.md are comparable across controllers. A trace is sampled at a
uniform period ``dt``: sample 0 is the initial state at t = 0, samples 1..N the states at the
end of each period. Sums and means run over samples 1..N (each sample stands for the period
that ends at it); settling may happen at sample 0 (a zero step is settled at once).

The module lives in the driver because `reach-driver run` and `inspect` score runs and the
driver may not import `policy`; evaluation and training import it from here.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from protocol.alpha5 import DEFAULT_CURRENT_LIMITS_MA
from protocol.models import ALPHA5, ArmModel

OVERSHOOT_MIN_STEP_RAD = 0.05
"""Joints whose step is smaller than this are left out of the overshoot (ratio is noise)."""
SETTLING_BAND_FRACTION = 0.02
"""Settling band: this fraction of the joint's step ..."""
SETTLING_BAND_MIN_RAD = 0.01
"""... but never narrower than this (rad)."""
STEADY_STATE_WINDOW_S = 2.0
"""MSSE averages |e| over the last this many seconds."""
REACHED_TOL_RAD = 0.02
"""An episode reached its target when every final |e_j| is below this (and it is at rest)."""
REST_WINDOW_S = 2.0
"""Rest speed and command reversals are measured over the last this many seconds (from the
settling time on, if that is later: `rest_window`)."""
REST_SPEED_RMS_MAX = 0.05
"""At rest: every joint's RMS true speed over the rest window at most this (rad/s). Settled
episodes measure <= 0.014 rad/s (the MPC's worst), the chattering one 1.15 (docs/metrics.md,
"Rest")."""
REVERSAL_CURRENT_FRACTION = 0.10
"""A command counts towards reversals only when |u_j| exceeds this fraction of the joint's
current limit (60 mA on E D C, 30 mA on B), so noise around a zero hold is not chatter."""
REST_REVERSALS_MAX = 4
"""At rest: at most this many command sign reversals per joint in the rest window (settled: 0,
chattering: 39 of 40 periods)."""
REST_ENERGY_AFTER_SETTLING_MAX_J = 0.5
"""At rest: at most this much energy spent after settling (J; settled <= 0.15, a burst of
chatter that dies out 1.1-1.4, chatter to the end 20-50), a joint still finishing a straight
approach from outside REACHED_TOL_RAD counted from when it is inside (`energy_clocks`). Set on
the Alpha 5; another arm's bound is `rest_energy_limit_j`."""


def rest_energy_limit_j(model: ArmModel) -> float:
    """The energy-after-settling bound on `model`'s arm: REST_ENERGY_AFTER_SETTLING_MAX_J
    times the arm's summed peak joint torque (current limit x torque per amp) over the Alpha
    5's. Holding heavier links against the same sensor noise spends energy in proportion to the
    torque it takes (the Bravo 7: 6.4 times the Alpha's, 3.2 J), and a chatter's in proportion
    to the torque it swings, so the bound keeps its place between the two."""

    def peak_nm(m: ArmModel) -> float:
        limits = np.asarray(m.current_limits_mA, dtype=float) / 1e3
        return float(np.sum(limits * np.asarray(m.torque_per_amp_nm, dtype=float)))

    return REST_ENERGY_AFTER_SETTLING_MAX_J * peak_nm(model) / peak_nm(ALPHA5)


METRIC_KEYS = (
    "energy_j",
    "rmse",
    "mie",
    "msse",
    "overshoot_pct",
    "settling_time_s",
    "reached",
)
"""The paper's six and `reached` (tables that list these keep working unchanged)."""
REST_KEYS = ("at_rest", "rest_speed_rms", "command_reversals", "energy_after_settling_j")
"""The rest metric and the numbers behind it (docs/metrics.md, "Rest")."""
ALL_METRIC_KEYS = METRIC_KEYS + REST_KEYS
"""Every field of `Metrics`: what `summarize` averages and evaluation summaries report."""

METRIC_LABELS: dict[str, tuple[str, str]] = {
    "energy_j": ("energy", "J"),
    "rmse": ("RMSE", "rad"),
    "mie": ("MIE", "rad s"),
    "msse": ("MSSE", "rad"),
    "overshoot_pct": ("overshoot", "%"),
    "settling_time_s": ("settling time", "s"),
    "reached": ("reached", ""),
    "at_rest": ("at rest", ""),
    "rest_speed_rms": ("rest speed RMS", "rad/s"),
    "command_reversals": ("command reversals", ""),
    "energy_after_settling_j": ("energy after settling", "J"),
}
"""Each metric's one name and unit, as every table (run, inspect, evaluate) shows it."""


def metric_label(key: str) -> str:
    """'RMSE [rad]': the metric's name and unit; an unlabelled key is shown as itself."""
    name, unit = METRIC_LABELS.get(key, (key, ""))
    return f"{name} [{unit}]" if unit else name


@dataclass(frozen=True)
class Trace:
    """A uniformly sampled episode: arrays of N+1 rows, row 0 at t = 0, columns in the arm's
    joint order (`model`'s: E D C B on the Alpha 5)."""

    dt: float
    q: np.ndarray  # (N+1, 4) rad
    qdot: np.ndarray  # (N+1, 4) rad/s
    tau: np.ndarray  # (N+1, 4) N m, torque applied over the period ending at each sample
    target: np.ndarray  # (4,) rad
    power: np.ndarray | None = None
    """(N+1, 4) mean |tau qdot| over the period ending at each sample (W), integrated at the
    physics rate by the runner; without it |tau qdot| at the samples stands in for it."""
    command_mA: np.ndarray | None = None
    """(N+1, 4) current commanded over the period ending at each sample (mA); without it the
    rest metric counts reversals of tau / the model's torque per amp instead."""
    model: ArmModel = ALPHA5
    """The arm: its torque per amp and current limits, for the rest metric."""

    def __post_init__(self) -> None:
        if not self.dt > 0:
            raise ValueError(f"dt must be positive, got {self.dt}")
        q = np.asarray(self.q, dtype=float)
        if q.ndim != 2 or q.shape[0] < 2:
            raise ValueError(f"q must be (N+1, joints) with N >= 1, got shape {q.shape}")
        for name in ("qdot", "tau", "power", "command_mA"):
            if getattr(self, name) is None:
                continue
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != q.shape:
                raise ValueError(f"{name} has shape {arr.shape}, q has {q.shape}")
        if np.asarray(self.target).shape != (q.shape[1],):
            raise ValueError(f"target must have {q.shape[1]} values")

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.q.shape[0]) * self.dt

    @property
    def duration(self) -> float:
        return (self.q.shape[0] - 1) * self.dt

    @property
    def errors(self) -> np.ndarray:
        """e_j(t) = q_ref,j - q_j(t), all samples including t = 0."""
        return np.asarray(self.target, dtype=float)[None, :] - np.asarray(self.q, dtype=float)


@dataclass(frozen=True)
class Metrics:
    energy_j: float
    rmse: float
    mie: float
    msse: float
    overshoot_pct: float
    settling_time_s: float
    reached: bool
    """Final errors inside REACHED_TOL_RAD and the episode at rest."""
    # The rest metric (docs/metrics.md, "Rest"). Defaults keep hand-built Metrics valid: a
    # Metrics built without rest figures claims nothing against rest.
    at_rest: bool = True
    rest_speed_rms: float = 0.0
    """Worst joint's RMS true speed over the last REST_WINDOW_S (rad/s)."""
    command_reversals: int = 0
    """Worst joint's sign reversals of commands above the current threshold, last window."""
    energy_after_settling_j: float = 0.0
    """Energy spent after settling (J; `energy_clocks`); 0 if the episode never settled."""

    def as_dict(self) -> dict[str, float | bool]:
        return asdict(self)


def energy(trace: Trace) -> float:
    """Mechanical energy delivered by the motors, sum |tau qdot| dt (J); braking counts too."""
    return energy_after(trace, 0.0)


def energy_after(trace: Trace, t: float) -> float:
    """Energy spent in the periods that end after time ``t`` (J); 0 from the last sample on."""
    first = int(round(t / trace.dt)) + 1
    return float(_joint_power(trace)[first:].sum() * trace.dt)


def _joint_power(trace: Trace) -> np.ndarray:
    """|power| per sample and joint (W): the runner's physics-rate figure, else |tau qdot|."""
    if trace.power is not None:
        return np.abs(np.asarray(trace.power, dtype=float))
    return np.abs(np.asarray(trace.tau, dtype=float) * np.asarray(trace.qdot, dtype=float))


def rmse(errors: np.ndarray) -> float:
    """sqrt(mean e^2) over samples 1..N and all joints (rad)."""
    e = np.asarray(errors, dtype=float)[1:]
    return float(np.sqrt(np.mean(e**2)))


def mean_integral_error(errors: np.ndarray, dt: float) -> float:
    """Mean over joints of sum |e_j| dt (rad s)."""
    e = np.asarray(errors, dtype=float)[1:]
    return float(np.mean(np.abs(e).sum(axis=0) * dt))


def steady_state_samples(n_samples: int, dt: float, window_s: float = STEADY_STATE_WINDOW_S) -> int:
    """How many of the last samples (of samples 1..N) fall in the steady-state window."""
    n = int(round(window_s / dt))
    return max(1, min(n, n_samples - 1))


def mean_steady_state_error(
    errors: np.ndarray, dt: float, window_s: float = STEADY_STATE_WINDOW_S
) -> float:
    """Mean over joints of mean |e_j| over the last ``window_s`` seconds (rad)."""
    e = np.asarray(errors, dtype=float)
    k = steady_state_samples(e.shape[0], dt, window_s)
    return float(np.mean(np.abs(e[-k:])))


def overshoot_pct(q: np.ndarray, target: np.ndarray) -> float:
    """Largest overshoot past the target relative to the step, in % (0 if none or no step).

    Per joint: max(0, max_t (q_j - q0_j) / (q_ref,j - q0_j) - 1) * 100, over joints whose
    step is at least OVERSHOOT_MIN_STEP_RAD. The ratio is signed by the step direction, so a
    joint that first moves the wrong way does not count as overshoot.
    """
    worst = 0.0
    for _, past, step in _past_goal(q, target):
        worst = max(worst, float(past.max()) / step)
    return worst * 100.0


def _past_goal(q: np.ndarray, target: np.ndarray) -> Iterator[tuple[int, np.ndarray, float]]:
    """Per joint with a step of OVERSHOOT_MIN_STEP_RAD or more: its index, how far past its
    goal it is at each sample (rad, signed by the step's direction) and abs(step)."""
    q = np.asarray(q, dtype=float)
    target = np.asarray(target, dtype=float)
    step = target - q[0]
    for j in np.flatnonzero(np.abs(step) >= OVERSHOOT_MIN_STEP_RAD):
        yield int(j), (q[:, j] - target[j]) * np.sign(step[j]), abs(float(step[j]))


#: a joint crossing its goal this fast or faster was carried through by its approach (an
#: arrival); slower, it crept or was pushed across near the goal (docs/metrics.md, "Overshoot")
ARRIVAL_SPEED_RAD_S = 0.1


@dataclass(frozen=True)
class OvershootAnatomy:
    """How the worst joint's overshoot (the one `overshoot_pct` reports) came about."""

    joint: int  # in the arm's joint order (E D C B on the Alpha 5)
    pct: float  # as overshoot_pct
    past_rad: float  # how far past its goal it went
    peak_s: float  # when
    crossing_speed: float  # |qdot| at the first sample past the goal (rad/s)
    letters: tuple[str, ...] = ALPHA5.joint_letters  # the arm's joints

    @property
    def arrival(self) -> bool:
        """Carried through by the approach, not crept across near the goal."""
        return self.crossing_speed >= ARRIVAL_SPEED_RAD_S

    def as_dict(self) -> dict[str, object]:
        """For summaries and JSON: the joint by its letter, and `arrival`."""
        return {
            "joint": self.letters[self.joint],
            "pct": self.pct,
            "past_rad": self.past_rad,
            "peak_s": self.peak_s,
            "crossing_speed": self.crossing_speed,
            "arrival": self.arrival,
        }


def overshoot_anatomy(
    q: np.ndarray,
    qdot: np.ndarray,
    target: np.ndarray,
    dt: float,
    letters: Sequence[str] = ALPHA5.joint_letters,
) -> OvershootAnatomy | None:
    """The worst joint's overshoot in radians, its time and the speed it first crossed its goal
    at; None when no joint with a step of OVERSHOOT_MIN_STEP_RAD or more went past its goal."""
    qdot = np.asarray(qdot, dtype=float)
    worst: OvershootAnatomy | None = None
    for j, past, step in _past_goal(q, target):
        k = int(np.argmax(past))
        if past[k] <= 0:
            continue
        pct = float(past[k]) / step * 100.0
        if worst is None or pct > worst.pct:
            first = int(np.argmax(past > 0))
            speed = abs(float(qdot[first, j]))
            worst = OvershootAnatomy(j, pct, float(past[k]), k * dt, speed, tuple(letters))
    return worst


def settling_band(step: np.ndarray) -> np.ndarray:
    """Per-joint band: max(2 % of |step|, 0.01 rad)."""
    return np.maximum(SETTLING_BAND_FRACTION * np.abs(step), SETTLING_BAND_MIN_RAD)


def settling_time(q: np.ndarray, target: np.ndarray, dt: float) -> float:
    """First time after which every joint stays inside its band to the end (s).

    Returns the episode length if the last sample is outside the band (never settled).
    """
    q = np.asarray(q, dtype=float)
    target = np.asarray(target, dtype=float)
    band = settling_band(target - q[0])
    inside = np.all(np.abs(target[None, :] - q) <= band[None, :], axis=1)
    duration = (q.shape[0] - 1) * dt
    if not inside[-1]:
        return duration
    outside = np.flatnonzero(~inside)
    first = 0 if outside.size == 0 else int(outside[-1]) + 1
    return first * dt


APPROACH_TURN_RAD = 0.001
"""A joint's finishing approach ends when its error grows this much over its smallest since
the settling time (it turned back; `energy_clocks`)."""


def energy_clocks(
    q: np.ndarray, target: np.ndarray, dt: float, settling_time_s: float
) -> np.ndarray:
    """Per joint, when `energy_after_settling_j` starts counting it (s): the settling time,
    unless the joint is then still finishing a monotone approach from outside
    REACHED_TOL_RAD, in which case the first sample at which it is inside REACHED_TOL_RAD or
    turns back (its error APPROACH_TURN_RAD over its smallest since settling).

    The settling band grows with the step (2 %), a chatter's swing does not. Counted from the
    settling time, a long step behind high friction (E, 5 rad, 6.6 N m: a 100 mrad band)
    spent 6.6 x 0.1 = 0.66 J just finishing a straight approach, so a controller that came
    straight to rest failed the 0.5 J test whenever that joint settled last; inside 20 mrad
    the same approach costs at most 0.13 J. Any back-and-forth after settling, of any
    amplitude, still counts from its first turn. Never settled: the episode's end (0 J)."""
    q = np.asarray(q, dtype=float)
    target = np.asarray(target, dtype=float)
    n = q.shape[0]
    start = int(round(settling_time_s / dt))
    clocks = np.full(q.shape[1], settling_time_s)
    if start >= n - 1:
        return clocks
    error = np.abs(target[None, :] - q[start:])
    for j in range(q.shape[1]):
        seg = error[:, j]
        if seg[0] <= REACHED_TOL_RAD:
            continue
        turned = seg > np.minimum.accumulate(seg) + APPROACH_TURN_RAD
        ends = np.flatnonzero((seg <= REACHED_TOL_RAD) | turned)
        first = int(ends[0]) if ends.size else n - 1 - start
        clocks[j] = (start + first) * dt
    return clocks


def energy_after_clocks(trace: Trace, clocks: np.ndarray) -> float:
    """Energy each joint spent in the periods that end after its own clock (J)."""
    power = _joint_power(trace)
    total = 0.0
    for j, t in enumerate(np.asarray(clocks, dtype=float)):
        total += float(power[int(round(t / trace.dt)) + 1 :, j].sum())
    return total * trace.dt


def reached(errors: np.ndarray, tol: float = REACHED_TOL_RAD) -> bool:
    return bool(np.all(np.abs(np.asarray(errors, dtype=float)[-1]) < tol))


@dataclass(frozen=True)
class Rest:
    """Whether an episode came to rest, and the numbers behind the verdict."""

    speed_rms: float
    reversals: int
    energy_after_settling_j: float
    #: the arm's bound on `energy_after_settling_j` (`rest_energy_limit_j`)
    energy_limit_j: float = REST_ENERGY_AFTER_SETTLING_MAX_J

    @property
    def at_rest(self) -> bool:
        return (
            self.speed_rms <= REST_SPEED_RMS_MAX
            and self.reversals <= REST_REVERSALS_MAX
            and self.energy_after_settling_j <= self.energy_limit_j
        )


def rest_window(n_samples: int, dt: float, settling_time_s: float) -> int:
    """How many of the last samples the rest metric looks at: those of the last REST_WINDOW_S,
    but none before the settling time if the episode settled later than that (a short
    episode's window would otherwise hold its motion). Never settled: the last REST_WINDOW_S."""
    k = steady_state_samples(n_samples, dt, REST_WINDOW_S)
    settled_at = int(round(settling_time_s / dt))
    if settled_at < n_samples - 1:
        k = min(k, n_samples - settled_at)
    return k


def rest_speed_rms(qdot: np.ndarray, samples: int) -> float:
    """Worst joint's RMS speed over the last ``samples`` samples (rad/s)."""
    v = np.asarray(qdot, dtype=float)[-samples:]
    return float(np.sqrt(np.mean(v**2, axis=0)).max())


def command_reversals(
    command_mA: np.ndarray,
    samples: int,
    limits_mA: np.ndarray | tuple[float, ...] = DEFAULT_CURRENT_LIMITS_MA,
) -> int:
    """Worst joint's count of sign changes between successive commands whose magnitude
    exceeds REVERSAL_CURRENT_FRACTION of its limit, over the last ``samples`` samples.

    Bang-bang chatter reverses a large command every period; a joint holding still keeps
    its command's sign (gravity) or stays below the threshold (noise around zero)."""
    u = np.asarray(command_mA, dtype=float)[-samples:]
    threshold = REVERSAL_CURRENT_FRACTION * np.asarray(limits_mA, dtype=float)
    worst = 0
    for j in range(u.shape[1]):
        col = u[:, j]
        signs = np.sign(col[np.abs(col) > threshold[j]])
        worst = max(worst, int(np.count_nonzero(signs[1:] != signs[:-1])))
    return worst


def rest(trace: Trace, settling_time_s: float | None = None) -> Rest:
    """The rest metric of ``trace`` (docs/metrics.md, "Rest")."""
    if settling_time_s is None:
        settling_time_s = settling_time(trace.q, trace.target, trace.dt)
    model = trace.model
    if trace.command_mA is not None:
        command = np.asarray(trace.command_mA, dtype=float)
    else:
        command = np.asarray(trace.tau, dtype=float) / np.asarray(model.torque_per_amp_nm) * 1e3
    k = rest_window(trace.q.shape[0], trace.dt, settling_time_s)
    return Rest(
        speed_rms=rest_speed_rms(trace.qdot, k),
        reversals=command_reversals(command, k, model.current_limits_mA),
        energy_after_settling_j=energy_after_clocks(
            trace, energy_clocks(trace.q, trace.target, trace.dt, settling_time_s)
        ),
        energy_limit_j=rest_energy_limit_j(model),
    )


def compute_metrics(trace: Trace) -> Metrics:
    e = trace.errors
    settling = settling_time(trace.q, trace.target, trace.dt)
    still = rest(trace, settling)
    return Metrics(
        energy_j=energy(trace),
        rmse=rmse(e),
        mie=mean_integral_error(e, trace.dt),
        msse=mean_steady_state_error(e, trace.dt),
        overshoot_pct=overshoot_pct(trace.q, trace.target),
        settling_time_s=settling,
        reached=reached(e) and still.at_rest,
        at_rest=still.at_rest,
        rest_speed_rms=still.speed_rms,
        command_reversals=still.reversals,
        energy_after_settling_j=still.energy_after_settling_j,
    )


def ideal_trajectory(
    start: np.ndarray, target: np.ndarray, speed: np.ndarray, dt: float, n_steps: int
) -> np.ndarray:
    """Each joint moving straight to its target at ``speed`` (rad/s); (n_steps+1, 4)."""
    start = np.asarray(start, dtype=float)
    target = np.asarray(target, dtype=float)
    speed = np.asarray(speed, dtype=float)
    if np.any(speed <= 0):
        raise ValueError(f"speeds must be positive, got {speed}")
    t = np.arange(n_steps + 1)[:, None] * dt
    step = target - start
    travelled = np.minimum(speed[None, :] * t, np.abs(step)[None, :])
    return start[None, :] + np.sign(step)[None, :] * travelled


def rmse_floor(
    start: np.ndarray, target: np.ndarray, speed: np.ndarray, dt: float, n_steps: int
) -> float:
    """RMSE of an ideal controller that moves every joint at ``speed`` straight to target.

    No controller limited by the motors' no-load speed can do better than this (it ignores
    acceleration), so the ratio rmse / rmse_floor says how much tracking time a controller
    loses on top of what the actuators force.
    """
    q = ideal_trajectory(start, target, speed, dt, n_steps)
    return rmse(np.asarray(target, dtype=float)[None, :] - q)


def summarize(metrics: list[Metrics]) -> dict[str, float]:
    """Mean of every metric over episodes; ``reached`` and ``at_rest`` become fractions."""
    if not metrics:
        raise ValueError("no episodes to summarize")
    return {
        key: float(np.mean([float(getattr(m, key)) for m in metrics])) for key in ALL_METRIC_KEYS
    }
