"""Per-joint PID on arm angles with current output (mA): the baseline controller.

Gravity and Coulomb friction are left to the integral (no model needed, so it works the same
on the virtual and a real arm). Derivative acts on the measured velocity, not the error, so
a new target gives no kick. Anti-windup by conditional integration: the integral only grows
while the output is not saturated in the direction the error pushes, and its share of the
output is bounded by the current limit.

Registered as `pid` in the `reach_stack.controllers` entry points (`make_controller`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.alpha5 import DEFAULT_CURRENT_LIMITS_MA, N_JOINTS
from reach_driver.controllers import ControlState, engineered

# Tuned on the virtual arm at 20 Hz in current mode (tests/test_driver_pid.py): E, D, C share
# a motor and gearbox (20.2 N m/A, ~0.12 kg m^2 reflected inertia), B is much lighter.
DEFAULT_KP = (1500.0, 1500.0, 1500.0, 400.0)  # mA/rad
DEFAULT_KI = (3000.0, 3000.0, 3000.0, 800.0)  # mA/(rad s)
DEFAULT_KD = (150.0, 150.0, 150.0, 15.0)  # mA/(rad/s)
# The integral only runs this close to the target (rad): during a long, speed-limited
# approach it would otherwise wind up and overshoot; near the target it finds the current
# that gravity and friction need.
DEFAULT_INTEGRAL_ZONE = (0.08, 0.08, 0.08, 0.08)


def _four(name: str, value: float | Sequence[float] | np.ndarray) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(N_JOINTS, float(arr))
    if arr.shape != (N_JOINTS,):
        raise ValueError(f"{name} needs one value or 4 (joint order E D C B), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


@dataclass(frozen=True)
class PIDGains:
    kp: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_KP))
    ki: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_KI))
    kd: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_KD))

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd"):
            arr = _four(name, getattr(self, name))
            if np.any(arr < 0):
                raise ValueError(f"{name} must not be negative, got {arr}")
            object.__setattr__(self, name, arr)


class PIDController:
    """`act(state, target) -> currents (mA)`; time steps come from `state.t`."""

    def __init__(
        self,
        gains: PIDGains | None = None,
        current_limits_mA: float | Sequence[float] | np.ndarray = DEFAULT_CURRENT_LIMITS_MA,
        period_s: float = 0.05,
        integral_zone: float | Sequence[float] | np.ndarray = DEFAULT_INTEGRAL_ZONE,
    ) -> None:
        self.gains = gains or PIDGains()
        self.integral_zone = _four("integral_zone", integral_zone)
        self.limits = _four("current_limits_mA", current_limits_mA)
        if np.any(self.limits <= 0):
            raise ValueError(f"current limits must be positive, got {self.limits}")
        if period_s <= 0:
            raise ValueError(f"period_s must be positive, got {period_s}")
        self.period_s = period_s
        self.integral = np.zeros(N_JOINTS)  # rad s
        self._last_t: float | None = None

    def reset(self) -> None:
        self.integral = np.zeros(N_JOINTS)
        self._last_t = None

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q = np.asarray(state.q, dtype=float)
        qdot = np.asarray(state.qdot, dtype=float)
        error = np.asarray(target, dtype=float) - q
        # The first step and any gap (a stalled loop) count as one nominal period, so a
        # late state never dumps a large slug into the integral.
        dt = self.period_s if self._last_t is None else float(state.t) - self._last_t
        dt = min(max(dt, 0.0), 2.0 * self.period_s)
        self._last_t = float(state.t)
        g = self.gains
        pd = g.kp * error - g.kd * qdot
        near = np.abs(error) < self.integral_zone
        candidate = self.integral + np.where(near, error * dt, 0.0)
        # Bound the integral's share of the output by the current limit.
        i_max = np.divide(self.limits, g.ki, out=np.zeros(N_JOINTS), where=g.ki > 0)
        candidate = np.clip(candidate, -i_max, i_max)
        trial = pd + g.ki * candidate
        saturated_same_way = (np.abs(trial) > self.limits) & (np.sign(trial) == np.sign(error))
        self.integral = np.where(saturated_same_way, self.integral, candidate)
        out = pd + g.ki * self.integral
        return np.clip(out, -self.limits, self.limits)


@engineered
def make_controller(**kwargs: Any) -> PIDController:
    """Per-joint PID; engineered, no learning.

    Entry point `pid`: `kp`, `ki`, `kd`, `integral_zone` (one value or 4 each),
    `current_limits_mA`, `period_s`."""
    gains = PIDGains(
        kp=_four("kp", kwargs.pop("kp", DEFAULT_KP)),
        ki=_four("ki", kwargs.pop("ki", DEFAULT_KI)),
        kd=_four("kd", kwargs.pop("kd", DEFAULT_KD)),
    )
    limits = kwargs.pop("current_limits_mA", DEFAULT_CURRENT_LIMITS_MA)
    period_s = float(kwargs.pop("period_s", 0.05))
    zone = kwargs.pop("integral_zone", DEFAULT_INTEGRAL_ZONE)
    if kwargs:
        raise TypeError(f"unknown PID parameters: {', '.join(sorted(kwargs))}")
    return PIDController(gains, limits, period_s, zone)
