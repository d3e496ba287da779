"""Thermal derating of the current limit, as motor firmware protects a winding.

A motor held at high current against an end stop heats its winding; firmware without a
winding sensor estimates that heat from the current it measures (an I^2 t estimate) and
lowers the current limit before the winding overheats. The virtual arm keeps one estimate per
device, a first-order thermal load in units of the winding's rated temperature rise:

    tau dL/dt = (I / I_cont)^2 - L        (L = 0 cold; L = 1 at the rated rise)

so a current at I_cont settles at L = 1, and one above it gets there in a time that shrinks
with the overload (600 mA on E, D or C, 1.5 I_cont, crosses `DERATING_START` after 0.44 tau,
13 s). Above `DERATING_START` the device's current limit falls linearly from its factory limit
to I_cont at L = 1 and stays there; a joint stalled at the limit thus settles at I_cont, and
one at rest cools back to its full limit (from L = 1 below `DERATING_START` in 0.22 tau, 7 s).
The limit the host set (CURRENT_LIMITS) is kept and reported as set: derating only caps it.

The vendor documents no derating, so every number here is an assumption [A] of the emulator
(model/README.md, "Thermal derating"), not a datasheet figure. A real arm's CURRENT reading is
how a host sees it: the current falls to I_cont while the command asks for more. The housing
temperature the devices report (INTERNAL_TEMPERATURE, `monitor`) rises with the same current.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Thermal time constant of the winding estimate (s) [A]: small geared DC motors' windings
#: are quoted at 10 to 40 s.
DERATING_TIME_CONSTANT_S = 30.0
#: Continuous current as a fraction of the device's factory current limit [A]: E, D and C
#: 400 of 600 mA, B and the jaws 200 of 300 mA (the identified simulation of this arm also
#: runs D, C and B at 400 mA, model/README.md [ID]).
CONTINUOUS_FRACTION = 2.0 / 3.0
#: Thermal load at which the limit starts to fall [A]; at 1.0 it has reached I_cont.
DERATING_START = 0.8


@dataclass(frozen=True)
class CurrentDerating:
    """The derating model's constants (module docstring); `FirmwareConfig.derating`."""

    time_constant_s: float = DERATING_TIME_CONSTANT_S
    continuous_fraction: float = CONTINUOUS_FRACTION
    start: float = DERATING_START

    def __post_init__(self) -> None:
        if not (math.isfinite(self.time_constant_s) and self.time_constant_s > 0.0):
            raise ValueError(f"derating time constant must be > 0 s, got {self.time_constant_s}")
        if not (0.0 < self.continuous_fraction <= 1.0):
            raise ValueError(
                f"continuous current fraction must be in (0, 1], got {self.continuous_fraction}"
            )
        if not (0.0 <= self.start < 1.0):
            raise ValueError(f"derating start must be in [0, 1), got {self.start}")

    def step_factor(self, h: float) -> float:
        """How far the load moves towards its target in a step of h seconds (exact lag)."""
        return -math.expm1(-h / self.time_constant_s)

    def ceiling(self, load: float, peak_mA: float) -> float:
        """The current (mA, either sign) the device allows at thermal `load`: unbounded
        (the set limit rules) below `start`, then down to the continuous current at 1."""
        if load <= self.start:
            return math.inf
        cont = self.continuous_fraction * peak_mA
        if load >= 1.0:
            return cont
        return peak_mA - (peak_mA - cont) * (load - self.start) / (1.0 - self.start)
