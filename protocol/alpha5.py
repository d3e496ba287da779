"""The Reach Alpha 5's facts that both ends of the wire need, each stated once.

The codec needs none of this. It lives in `protocol` because that is the one package the
driver and the simulator share (neither may import the other), and both must agree on which
device is which joint, the factory limits, and how much torque an amp of motor current makes.
Sources and derivations: docs/protocol.md (ids, slots) and reach_sim_bridge/model/README.md
(motors, limits). `protocol.models.ALPHA5` gathers them into the arm's model entry.

Arrays of four are always in joint order E D C B (base yaw, shoulder, elbow, wrist roll).
"""

from __future__ import annotations

import math

from .ids import DeviceID

#: The four controlled joints in the project's fixed order.
JOINTS: tuple[DeviceID, ...] = (DeviceID.E, DeviceID.D, DeviceID.C, DeviceID.B)
#: Their letters, as the CLI takes angles (`move E D C B`) and recordings name them.
JOINT_LETTERS: tuple[str, ...] = tuple(d.name for d in JOINTS)
N_JOINTS = len(JOINTS)
#: The jaws: a slide in mm, handled apart from the four rotary joints.
JAW = DeviceID.A
ALL_DEVICES: tuple[DeviceID, ...] = (*JOINTS, JAW)
#: The device that answers for the arm as a whole (the base, E, on the Alpha 5).
BASE = DeviceID.E

Range = tuple[float, float]  # (minimum, maximum)

#: The arm's serial line rate, bits/s, 8N1 (docs/protocol.md section 9).
SERIAL_BAUD = 115200

#: Factory position envelope per device (rad; mm for the jaws), as shipped from the factory.
FACTORY_POSITION_LIMITS: dict[DeviceID, Range] = {
    DeviceID.E: (0.0175, 6.143),
    DeviceID.D: (0.0175, 3.4034),
    DeviceID.C: (0.0175, 3.4034),
    DeviceID.B: (0.0, 2.0 * math.pi),
    DeviceID.A: (0.0, 15.0),
}
#: The middle of the factory envelope, E D C B (rad): where an identification starts and
#: ends, and the pose its reports give a joint's inertia at.
FACTORY_MIDDLE: tuple[float, ...] = tuple(
    0.5 * (FACTORY_POSITION_LIMITS[d][0] + FACTORY_POSITION_LIMITS[d][1]) for d in JOINTS
)
#: Factory velocity limits per device (rad/s; mm/s for the jaws).
FACTORY_VELOCITY_LIMITS: dict[DeviceID, Range] = {
    DeviceID.E: (-0.5236, 0.5236),
    DeviceID.D: (-0.5236, 0.5236),
    DeviceID.C: (-0.5236, 0.5236),
    DeviceID.B: (-0.8727, 0.8727),
    DeviceID.A: (-3.0, 3.0),
}
#: The fastest each joint can physically turn (rad/s), E D C B: above the motors' no-load
#: speed at 24 V (1.18, 1.18, 1.18, 1.29 rad/s, `reach_sim_bridge.model.motor.no_load_speed`)
#: with margin for a supply at its upper rating and outside forces. The driver's feedback
#: check (`reach_driver.plausibility`) refuses a reported jump faster than this.
MAX_JOINT_SPEED: tuple[float, float, float, float] = (2.0, 2.0, 2.0, 2.0)
#: Default motor current limits (mA), E D C B, and the jaws'.
DEFAULT_CURRENT_LIMITS_MA: tuple[float, float, float, float] = (600.0, 600.0, 600.0, 300.0)
DEFAULT_JAW_CURRENT_LIMIT_MA = 300.0
FACTORY_CURRENT_LIMITS: dict[DeviceID, Range] = {
    **{d: (-mA, mA) for d, mA in zip(JOINTS, DEFAULT_CURRENT_LIMITS_MA, strict=True)},
    JAW: (-DEFAULT_JAW_CURRENT_LIMIT_MA, DEFAULT_JAW_CURRENT_LIMIT_MA),
}

# Motor and gearbox datasheet constants, E D C B (E, D and C share one motor and gearbox).
MOTOR_RESISTANCE_OHM = (3.22, 3.22, 3.22, 38.6)
MOTOR_TORQUE_CONSTANT_NM_PER_A = (0.0134, 0.0134, 0.0134, 0.0271)  # at the motor shaft
MOTOR_BACKEMF_V_S_PER_RAD = (0.0116, 0.0116, 0.0116, 0.0545)  # at the motor shaft
GEAR_RATIO = (1754.4, 1754.4, 1754.4, 340.4)
GEAR_EFFICIENCY = (0.86, 0.86, 0.86, 0.77)
#: Joint output torque per amp of motor current, Kt x gear ratio x efficiency (about
#: 20.2 N m/A for E, D, C and 7.1 for B). On a real arm this is the only torque estimate.
TORQUE_PER_AMP_NM: tuple[float, ...] = tuple(
    k * g * e
    for k, g, e in zip(MOTOR_TORQUE_CONSTANT_NM_PER_A, GEAR_RATIO, GEAR_EFFICIENCY, strict=True)
)
NOMINAL_SUPPLY_V = 24.0
SUPPLY_RANGE_V = (18.0, 30.0)
