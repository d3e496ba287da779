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

from dataclasses import asdict, dataclass

import numpy as np

OVERSHOOT_MIN_STEP_RAD = 0.05
"""Joints whose step is smaller than this are left out of the overshoot (ratio is noise)."""
SETTLING_BAND_FRACTION = 0.02
"""Settling band: this fraction of the joint's step ..."""
SETTLING_BAND_MIN_RAD = 0.01
"""... but never narrower than this (rad)."""
STEADY_STATE_WINDOW_S = 2.0
"""MSSE averages |e| over the last this many seconds."""
REACHED_TOL_RAD = 0.02
"""An episode reached its target when every final |e_j| is below this (rad)."""

METRIC_KEYS = (
    "energy_j",
    "rmse",
    "mie",
    "msse",
    "overshoot_pct",
    "settling_time_s",
    "reached",
)


@dataclass(frozen=True)
class Trace:
    """A uniformly sampled episode: arrays of N+1 rows, row 0 at t = 0 (arm order E D C B)."""

    dt: float
    q: np.ndarray  # (N+1, 4) rad
    qdot: np.ndarray  # (N+1, 4) rad/s
    tau: np.ndarray  # (N+1, 4) N m, torque applied over the period ending at each sample
    target: np.ndarray  # (4,) rad
    power: np.ndarray | None = None
    """(N+1, 4) mean |tau qdot| over the period ending at each sample (W), integrated at the
    physics rate by the runner; without it |tau qdot| at the samples stands in for it."""

    def __post_init__(self) -> None:
        if not self.dt > 0:
            raise ValueError(f"dt must be positive, got {self.dt}")
        q = np.asarray(self.q, dtype=float)
        if q.ndim != 2 or q.shape[0] < 2:
            raise ValueError(f"q must be (N+1, joints) with N >= 1, got shape {q.shape}")
        for name in ("qdot", "tau", "power"):
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

    def as_dict(self) -> dict[str, float | bool]:
        return asdict(self)


def energy(trace: Trace) -> float:
    """Mechanical energy delivered by the motors, sum |tau qdot| dt (J); braking counts too."""
    if trace.power is not None:
        power = np.abs(np.asarray(trace.power, dtype=float)[1:])
    else:
        power = np.abs(np.asarray(trace.tau)[1:] * np.asarray(trace.qdot)[1:])
    return float(power.sum() * trace.dt)


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
    q = np.asarray(q, dtype=float)
    step = np.asarray(target, dtype=float) - q[0]
    worst = 0.0
    for j in np.flatnonzero(np.abs(step) >= OVERSHOOT_MIN_STEP_RAD):
        progress = (q[:, j] - q[0, j]) / step[j]
        worst = max(worst, float(progress.max()) - 1.0)
    return worst * 100.0


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


def reached(errors: np.ndarray, tol: float = REACHED_TOL_RAD) -> bool:
    return bool(np.all(np.abs(np.asarray(errors, dtype=float)[-1]) < tol))


def compute_metrics(trace: Trace) -> Metrics:
    e = trace.errors
    return Metrics(
        energy_j=energy(trace),
        rmse=rmse(e),
        mie=mean_integral_error(e, trace.dt),
        msse=mean_steady_state_error(e, trace.dt),
        overshoot_pct=overshoot_pct(trace.q, trace.target),
        settling_time_s=settling_time(trace.q, trace.target, trace.dt),
        reached=reached(e),
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
    """Mean of every metric over episodes; ``reached`` becomes the reached fraction."""
    if not metrics:
        raise ValueError("no episodes to summarize")
    return {key: float(np.mean([float(getattr(m, key)) for m in metrics])) for key in METRIC_KEYS}
