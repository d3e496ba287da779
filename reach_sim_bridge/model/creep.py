"""How fast the twin's joints creep under a torque their Coulomb friction should hold.

MuJoCo's ``frictionloss`` is a soft constraint: below breakaway it acts as a stiff viscous
damper rather than a lock, so a joint pushed at a fraction of its friction slides at a speed
proportional to the push, where a real gearbox holds. `creep_speed` measures the slide (the arm
held still against gravity and buoyancy, one joint pushed beyond its hold); `ArmParams`'
`friction_holds` makes the friction hold. tools/creep.py prints the figures.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams

POSE = (3.0, 1.5, 1.5, 1.5)  # rad, E D C B: mid-range, forearm out, gravity on D and C
SETTLE_S = 1.0
MEASURE_S = 4.0


def creep_speed(friction: float, joint: int, fraction: float, holds: bool = False) -> float:
    """Mean speed (rad/s) of `joint` pushed at `fraction` of `friction` (N m) beyond its hold,
    on the twin as shipped or (`holds`) with `ArmParams.friction_holds`: over `MEASURE_S` after
    a `SETTLE_S` transient, the other joints' commands their holds."""
    base = ArmParams()
    on_edc = (friction, friction, friction, base.frictionloss[3])
    arm = Alpha5Arm(replace(base, frictionloss=on_edc, friction_holds=holds))
    q0 = np.asarray(POSE, dtype=float)
    arm.reset(q=q0.copy())
    tau = -arm.gravity_torque(q0)
    tau[joint] += fraction * friction
    per_amp = np.asarray(arm.motor.torque_per_amp) * np.asarray(arm.motor.torque_scale)
    currents_mA = tau / per_amp * 1000.0
    arm.step(currents_mA, n=int(round(SETTLE_S / arm.dt)))
    start = float(arm.q[joint])
    arm.step(currents_mA, n=int(round(MEASURE_S / arm.dt)))
    return (float(arm.q[joint]) - start) / MEASURE_S
