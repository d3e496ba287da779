"""Per-joint PID on arm angles with current output (mA): the baseline controller.

Gravity and Coulomb friction are left to the integral (no model needed, so it works the same
on the virtual and a real arm). Derivative acts on the measured velocity, not the error, so
a new target gives no kick. Anti-windup by conditional integration: the integral only grows
while the output is not saturated in the direction the error pushes, and its share of the
output is bounded by the current limit.

One controller for any arm model: as many joints as the model has, with default gains per
model (`DEFAULT_GAINS`). Registered as `pid` in the `reach_stack.controllers` entry points
(`make_controller`), for the Alpha 5 and the Bravo 7.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver.controllers import ControlState, drives, engineered


@dataclass(frozen=True)
class DefaultGains:
    """One model's default PID, per joint in its order: gains (mA/rad, mA/(rad s),
    mA/(rad/s)) and the integral zone (rad: the integral only runs this close to the target;
    during a long, speed-limited approach it would otherwise wind up and overshoot, near the
    target it finds the current that gravity and friction need)."""

    kp: tuple[float, ...]
    ki: tuple[float, ...]
    kd: tuple[float, ...]
    integral_zone: tuple[float, ...]


#: Default gains per model (`ArmModel.name`), each tuned on its twin at 20 Hz in current mode.
DEFAULT_GAINS: Mapping[str, DefaultGains] = MappingProxyType(
    {
        # The virtual Alpha 5 (tests/test_driver_pid.py): E, D, C share a motor and gearbox
        # (20.2 N m/A, ~0.12 kg m^2 reflected inertia), B is much lighter.
        ALPHA5.name: DefaultGains(
            kp=(1500.0, 1500.0, 1500.0, 400.0),
            ki=(3000.0, 3000.0, 3000.0, 800.0),
            kd=(150.0, 150.0, 150.0, 15.0),
            integral_zone=(0.08, 0.08, 0.08, 0.08),
        ),
        # The virtual Bravo 7 (reach-sim --arm bravo7, in fresh water; tuned on the twin,
        # not on a real arm; tests/test_cli_bravo7.py), G F E D C B. Its joints are heavily
        # damped (20.6 N m s/rad) and stick (9.5 N m of friction, ~370 mA): kp is high so
        # the P term alone moves a joint 0.05 rad from its goal, the integral zone wider than
        # the friction's dead band (kp / 370 mA) so the integral finishes the move; F, the
        # shoulder holding the arm's weight (~530 mA), stiffer and more damped. Through the
        # driver at 20 Hz: 0.3 to 0.6 rad steps of every joint at once stay within 20 mrad
        # of the target after 2.4 s of arm time; overshoot up to 11 % (F moving down).
        BRAVO7.name: DefaultGains(
            kp=(8000.0, 12000.0, 8000.0, 8000.0, 8000.0, 8000.0),
            ki=(15000.0, 15000.0, 15000.0, 15000.0, 15000.0, 15000.0),
            kd=(300.0, 800.0, 400.0, 300.0, 300.0, 200.0),
            integral_zone=(0.15, 0.15, 0.15, 0.15, 0.15, 0.15),
        ),
    }
)
_ALPHA = DEFAULT_GAINS[ALPHA5.name]


def _per_joint(
    name: str, value: float | Sequence[float] | np.ndarray, model: ArmModel = ALPHA5
) -> np.ndarray:
    """One value for every joint of `model`, or one per joint in its order (ValueError)."""
    n = model.n_joints
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        order = " ".join(model.joint_letters)
        raise ValueError(f"{name} needs one value or {n} (joint order {order}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


@dataclass(frozen=True)
class PIDGains:
    """Per-joint gains for `model` (the Alpha 5's defaults unless given)."""

    kp: np.ndarray = field(default_factory=lambda: np.array(_ALPHA.kp))
    ki: np.ndarray = field(default_factory=lambda: np.array(_ALPHA.ki))
    kd: np.ndarray = field(default_factory=lambda: np.array(_ALPHA.kd))
    model: ArmModel = ALPHA5

    @classmethod
    def defaults(cls, model: ArmModel) -> PIDGains:
        """The model's default gains (`DEFAULT_GAINS`)."""
        d = DEFAULT_GAINS[model.name]
        return cls(np.array(d.kp), np.array(d.ki), np.array(d.kd), model)

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd"):
            arr = _per_joint(name, getattr(self, name), self.model)
            if np.any(arr < 0):
                raise ValueError(f"{name} must not be negative, got {arr}")
            object.__setattr__(self, name, arr)


class PIDController:
    """`act(state, target) -> currents (mA)`; time steps come from `state.t`. Unless given,
    the gains, current limits and integral zone are `model`'s defaults."""

    def __init__(
        self,
        gains: PIDGains | None = None,
        current_limits_mA: float | Sequence[float] | np.ndarray | None = None,
        period_s: float = 0.05,
        integral_zone: float | Sequence[float] | np.ndarray | None = None,
        *,
        model: ArmModel = ALPHA5,
    ) -> None:
        self.model = model
        self.gains = gains or PIDGains.defaults(model)
        if self.gains.model is not model:
            raise ValueError(
                f"gains for the {self.gains.model.title}, controller for the {model.title}"
            )
        zone = DEFAULT_GAINS[model.name].integral_zone if integral_zone is None else integral_zone
        limits = model.current_limits_mA if current_limits_mA is None else current_limits_mA
        self.integral_zone = _per_joint("integral_zone", zone, model)
        self.limits = _per_joint("current_limits_mA", limits, model)
        if np.any(self.limits <= 0):
            raise ValueError(f"current limits must be positive, got {self.limits}")
        if period_s <= 0:
            raise ValueError(f"period_s must be positive, got {period_s}")
        self.period_s = period_s
        self.integral = np.zeros(model.n_joints)  # rad s
        self._last_t: float | None = None

    def reset(self) -> None:
        self.integral = np.zeros(self.model.n_joints)
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
        i_max = np.divide(self.limits, g.ki, out=np.zeros(self.model.n_joints), where=g.ki > 0)
        candidate = np.clip(candidate, -i_max, i_max)
        trial = pd + g.ki * candidate
        saturated_same_way = (np.abs(trial) > self.limits) & (np.sign(trial) == np.sign(error))
        self.integral = np.where(saturated_same_way, self.integral, candidate)
        out = pd + g.ki * self.integral
        return np.clip(out, -self.limits, self.limits)


@engineered
@drives(ALPHA5, BRAVO7)
def make_controller(model: ArmModel = ALPHA5, **kwargs: Any) -> PIDController:
    """Per-joint PID; engineered, no learning.

    Entry point `pid`: `kp`, `ki`, `kd`, `integral_zone` (one value or one per joint each),
    `current_limits_mA`, `period_s`; the arm's model's defaults for what is not given."""
    d = DEFAULT_GAINS[model.name]
    gains = PIDGains(
        kp=_per_joint("kp", kwargs.pop("kp", d.kp), model),
        ki=_per_joint("ki", kwargs.pop("ki", d.ki), model),
        kd=_per_joint("kd", kwargs.pop("kd", d.kd), model),
        model=model,
    )
    limits = kwargs.pop("current_limits_mA", None)
    period_s = float(kwargs.pop("period_s", 0.05))
    zone = kwargs.pop("integral_zone", None)
    if kwargs:
        raise TypeError(f"unknown PID parameters: {', '.join(sorted(kwargs))}")
    return PIDController(gains, limits, period_s, zone, model=model)
