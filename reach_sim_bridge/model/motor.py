"""The Alpha 5's motors: commanded current (mA) in, joint torque (N m) out.

One model for every part of the project (simulator, training environment, MPC), so a
controller tuned against one sees the same actuator limits in the others. A joint's motor is
a brushed DC motor behind a gearbox: output torque per amp is ``Kt * Gr * eta``. The drive
regulates current, but only within what the supply can push through the winding against the
back-EMF, ``(V - Kv * Gr * w) / R`` along the motion and ``(-V - Kv * Gr * w) / R`` against
it, and within the configured current limit. A per-joint torque scale models a degraded
actuator (scale 0.25 is the paper's 75 % torque loss); it scales the delivered torque, not the
current drawn, so the no-load speed is unchanged.

Everything is vectorised over joints; arrays are in the order the motors were given (the
arm model's joint order: E D C B for the Alpha 5). The joints' constants are the arm model's
(`protocol.models.ArmModel.motors`, `MotorParams.of`); the jaws' are here. The Reach Bravo 7's
motors are `BRAVO7_MOTORS` (G F E D C B) and `BRAVO7_JAW_MOTOR`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol import alpha5, bravo7
from protocol.models import ALPHA5, BRAVO7, ArmModel, MotorConstants

FloatArray = NDArray[np.float64]

DEFAULT_SUPPLY_VOLTAGE = alpha5.NOMINAL_SUPPLY_V
SUPPLY_VOLTAGE_RANGE = alpha5.SUPPLY_RANGE_V  # the arm's rated supply, volts


def _as_tuple(values: Sequence[float] | ArrayLike, name: str) -> tuple[float, ...]:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.size == 0 or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be a non-empty sequence of finite numbers, got {values!r}")
    return tuple(float(v) for v in array)


@dataclass(frozen=True)
class MotorParams:
    """Datasheet constants of a set of motors, one entry per joint.

    ``gear_ratio`` is motor radians per unit of output motion: plain gearbox ratio for a
    rotary joint, gearbox ratio x 2 pi / lead for a lead-screw (the jaw), so the same
    formulas give N m or N, rad/s or m/s.
    """

    resistance_ohm: tuple[float, ...]
    torque_constant: tuple[float, ...]  # N m / A at the motor shaft
    backemf_constant: tuple[float, ...]  # V s / rad at the motor shaft
    gear_ratio: tuple[float, ...]
    efficiency: tuple[float, ...]  # gearbox (and screw) efficiency, 0..1

    def __post_init__(self) -> None:
        sizes = set()
        for name in (
            "resistance_ohm",
            "torque_constant",
            "backemf_constant",
            "gear_ratio",
            "efficiency",
        ):
            values = _as_tuple(getattr(self, name), name)
            if any(v <= 0.0 for v in values):
                raise ValueError(f"motor {name} must be > 0, got {values}")
            object.__setattr__(self, name, values)
            sizes.add(len(values))
        if len(sizes) != 1:
            raise ValueError("all motor constant arrays need the same length (one per joint)")
        if any(v > 1.0 for v in self.efficiency):
            raise ValueError(f"motor efficiency is a fraction in (0, 1], got {self.efficiency}")

    @classmethod
    def of(cls, constants: MotorConstants) -> MotorParams:
        """An arm model's joint motors (`protocol.models.ArmModel.motors`)."""
        return cls(
            resistance_ohm=constants.resistance_ohm,
            torque_constant=constants.torque_constant_nm_per_a,
            backemf_constant=constants.backemf_v_s_per_rad,
            gear_ratio=constants.gear_ratio,
            efficiency=constants.gear_efficiency,
        )

    @property
    def count(self) -> int:
        return len(self.resistance_ohm)

    def torque_per_amp(self) -> FloatArray:
        """Output torque (N m, or N for the jaw) per amp: Kt x Gr x eta."""
        return (
            np.array(self.torque_constant) * np.array(self.gear_ratio) * np.array(self.efficiency)
        )

    def backemf_per_speed(self) -> FloatArray:
        """Back-EMF volts per unit of output speed: Kv x Gr."""
        return np.array(self.backemf_constant) * np.array(self.gear_ratio)


# Datasheet values (model/README.md, "Motors"), held once in protocol.alpha5.
ALPHA5_MOTORS = MotorParams.of(ALPHA5.motors)

# The jaw's lead screw is not published. Assumed: 20 mm lead, 40 % screw efficiency, so
# the stall force at 24 V (~570 N) matches the rated 600 N jaw force and the no-load speed
# (~4 mm/s) is above the firmware's 3 mm/s rate limit. Back-EMF constant assumed equal to
# B's (same motor: same R and Kt).
JAW_SCREW_LEAD_M = 0.020
JAW_SCREW_EFFICIENCY = 0.40
JAW_GEAR_RATIO = 348.7  # the jaw gearbox, before the screw
_B = alpha5.JOINTS.index(alpha5.DeviceID.B)  # the jaw's motor is B's
JAW_MOTOR = MotorParams(
    resistance_ohm=(alpha5.MOTOR_RESISTANCE_OHM[_B],),
    torque_constant=(alpha5.MOTOR_TORQUE_CONSTANT_NM_PER_A[_B],),
    backemf_constant=(alpha5.MOTOR_BACKEMF_V_S_PER_RAD[_B],),
    gear_ratio=(JAW_GEAR_RATIO * 2.0 * math.pi / JAW_SCREW_LEAD_M,),
    efficiency=(alpha5.GEAR_EFFICIENCY[_B] * JAW_SCREW_EFFICIENCY,),
)

# The Reach Bravo 7 (model/bravo7.md, "Motors"), held once in protocol.bravo7: six rotary
# joints G F E D C B and the jaws, whose ratio is motor radians per mm of travel.
BRAVO7_MOTORS = MotorParams.of(BRAVO7.motors)
BRAVO7_JAW_MOTOR = MotorParams(
    resistance_ohm=(bravo7.JAW_MOTOR_RESISTANCE_OHM,),
    torque_constant=(bravo7.JAW_MOTOR_TORQUE_CONSTANT_NM_PER_A,),
    backemf_constant=(bravo7.JAW_MOTOR_BACKEMF_V_S_PER_RAD,),
    gear_ratio=(bravo7.JAW_GEAR_RATIO_RAD_PER_MM * 1000.0,),  # motor rad per metre
    efficiency=(bravo7.JAW_GEAR_EFFICIENCY,),
)

DEFAULT_CURRENT_LIMITS_MA = alpha5.DEFAULT_CURRENT_LIMITS_MA
DEFAULT_JAW_CURRENT_LIMIT_MA = alpha5.DEFAULT_JAW_CURRENT_LIMIT_MA  # assumed: same motor as B


class MotorModel:
    """Vectorised current -> torque for a set of motors, with limit, back-EMF and scale.

    Mutable on purpose: the firmware changes current limits at run time (CURRENT_LIMITS
    packets) and fault injection changes the torque scale. One instance per arm.
    """

    def __init__(
        self,
        params: MotorParams = ALPHA5_MOTORS,
        supply_voltage: float = DEFAULT_SUPPLY_VOLTAGE,
        current_limits_mA: Sequence[float] | ArrayLike | None = None,
        torque_scale: Sequence[float] | ArrayLike | None = None,
    ) -> None:
        self.params = params
        n = params.count
        self._resistance = np.array(params.resistance_ohm)
        self._torque_per_amp = params.torque_per_amp()
        self._backemf = params.backemf_per_speed()
        self._supply = 0.0
        self.supply_voltage = supply_voltage
        default_limits = DEFAULT_CURRENT_LIMITS_MA if n == 4 else (1000.0,) * n
        self._limits_mA = np.empty(n)
        self.current_limits_mA = default_limits if current_limits_mA is None else current_limits_mA
        self._scale = np.ones(n)
        if torque_scale is not None:
            self.torque_scale = torque_scale

    # -- configuration -------------------------------------------------------------------
    @property
    def count(self) -> int:
        return self.params.count

    @property
    def supply_voltage(self) -> float:
        return self._supply

    @supply_voltage.setter
    def supply_voltage(self, volts: float) -> None:
        volts = float(volts)
        if not (math.isfinite(volts) and volts > 0.0):
            raise ValueError(f"supply voltage must be a finite number > 0 V, got {volts}")
        self._supply = volts

    @property
    def current_limits_mA(self) -> FloatArray:
        """Symmetric current limit per motor (mA); assign a sequence to change it."""
        return self._limits_mA

    @current_limits_mA.setter
    def current_limits_mA(self, limits: Sequence[float] | ArrayLike) -> None:
        array = self._checked(limits, "current limits (mA)")
        if np.any(array < 0.0):
            raise ValueError(f"current limits must be >= 0 mA, got {array.tolist()}")
        self._limits_mA[:] = array

    @property
    def torque_scale(self) -> FloatArray:
        """Fraction of the nominal torque each motor delivers (1 healthy, 0.25 = 75 % loss)."""
        return self._scale

    @torque_scale.setter
    def torque_scale(self, scale: Sequence[float] | ArrayLike) -> None:
        array = self._checked(scale, "torque scale")
        if np.any(array < 0.0) or np.any(array > 1.0):
            raise ValueError(f"torque scale must be in [0, 1] per joint, got {array.tolist()}")
        self._scale[:] = array

    def state_key(self) -> tuple[float, bytes, bytes]:
        """What the run-time settings are now (supply, limits, scale), cheap to compare: a
        stepper caches constants derived from them, and the arrays may be edited in place."""
        return (self._supply, self._limits_mA.tobytes(), self._scale.tobytes())

    def _checked(self, values: Sequence[float] | ArrayLike, what: str) -> FloatArray:
        array = np.asarray(values, dtype=np.float64)
        if array.shape != (self.count,):
            raise ValueError(f"{what} needs {self.count} values, got shape {array.shape}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{what} must be finite, got {array.tolist()}")
        return array

    # -- constants derived from the datasheet -------------------------------------------
    @property
    def resistance(self) -> FloatArray:
        return self._resistance.copy()

    @property
    def torque_per_amp(self) -> FloatArray:
        """Nominal output torque per amp (Kt Gr eta), before the torque scale."""
        return self._torque_per_amp.copy()

    @property
    def backemf_per_speed(self) -> FloatArray:
        """Back-EMF volts per unit of output speed (Kv Gr)."""
        return self._backemf.copy()

    def no_load_speed(self) -> FloatArray:
        """Output speed at which the back-EMF equals the supply (no current can flow)."""
        return self._supply / self._backemf

    def stall_torque(self) -> FloatArray:
        """Largest torque at rest: the smaller of the current limit and the supply's V/R."""
        amps = np.minimum(self._limits_mA / 1000.0, self._supply / self._resistance)
        return self._scale * self._torque_per_amp * amps

    def backemf_damping(self) -> FloatArray:
        """Slope of the voltage-limited speed-torque line (N m per rad/s): Kt Gr eta Kv Gr / R."""
        return self._scale * self._torque_per_amp * self._backemf / self._resistance

    # -- the model ------------------------------------------------------------------------
    def current_bounds_mA(self, velocity: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(lowest, highest) current the drive can put through each motor at this speed."""
        w = np.asarray(velocity, dtype=np.float64)
        emf = self._backemf * w
        hi = np.minimum(self._limits_mA, 1000.0 * (self._supply - emf) / self._resistance)
        lo = np.maximum(-self._limits_mA, 1000.0 * (-self._supply - emf) / self._resistance)
        return lo, hi

    def current_mA(self, command_mA: ArrayLike, velocity: ArrayLike) -> FloatArray:
        """Current actually drawn for a commanded current at the given output speeds."""
        lo, hi = self.current_bounds_mA(velocity)
        # Past the no-load speed lo > hi; the back-EMF bound wins (the motor brakes).
        return np.minimum(np.maximum(np.asarray(command_mA, dtype=np.float64), lo), hi)

    def torque(self, command_mA: ArrayLike, velocity: ArrayLike) -> FloatArray:
        """Output torque (N m) for a commanded current (mA) at the given output speeds."""
        return self._scale * self._torque_per_amp * self.current_mA(command_mA, velocity) / 1000.0


def no_load_speed(
    params: MotorParams = ALPHA5_MOTORS, supply_voltage: float = DEFAULT_SUPPLY_VOLTAGE
) -> FloatArray:
    """No-load output speed per joint (rad/s): ~1.18 for E, D, C and ~1.29 for B at 24 V."""
    return MotorModel(params, supply_voltage).no_load_speed()


def model_no_load_speed(model: ArmModel) -> FloatArray:
    """No-load output speed of each of `model`'s joints (rad/s) at its nominal supply."""
    return no_load_speed(MotorParams.of(model.motors), model.nominal_supply_v)
