"""The Reach Bravo 7's facts that both ends of the wire will need, each stated once.

The Bravo counterpart of `protocol.alpha5` (nothing uses it yet but the Bravo 7 twin). Sources,
and which values are assumptions because the vendor does not publish them:
reach_sim_bridge/model/bravo7.md.

Arrays of six are always in joint order G F E D C B (base yaw, shoulder, elbow, forearm roll,
wrist pitch, wrist roll), base to tip, as the Alpha's are E D C B.
"""

from __future__ import annotations

import math

from .ids import DeviceID

#: The six rotary joints, base to tip (the datasheet's actuators 1..6 are devices 0x07..0x02).
JOINTS: tuple[DeviceID, ...] = (
    DeviceID.G,
    DeviceID.F,
    DeviceID.E,
    DeviceID.D,
    DeviceID.C,
    DeviceID.B,
)
JOINT_LETTERS: tuple[str, ...] = tuple(d.name for d in JOINTS)
N_JOINTS = len(JOINTS)
#: The jaws: a linear axis in mm (datasheet actuator 7), handled apart from the rotary joints.
JAW = DeviceID.A
ALL_DEVICES: tuple[DeviceID, ...] = (*JOINTS, JAW)
#: The Ethernet router in the base: arm-wide settings and the optional force-torque reading.
ROUTER = DeviceID.ROUTER
#: The compute module in the base: kinematic (end-effector) demands and pose replies.
COMPUTE = DeviceID.COMPUTE

Range = tuple[float, float]  # (minimum, maximum)

_TWO_PI = 2.0 * math.pi

#: Position envelope per device (rad; mm for the jaws). Not published: F, E, C from the
#: vendor's MKII URDF (0..3.2 rad); G, D, B turn continuously there and are given stops at 0
#: and 2pi, as the Alpha's wrist; jaws 0..10 mm (MKII URDF; the MKI URDF says 35 mm).
FACTORY_POSITION_LIMITS: dict[DeviceID, Range] = {
    DeviceID.G: (0.0, _TWO_PI),
    DeviceID.F: (0.0, 3.2),
    DeviceID.E: (0.0, 3.2),
    DeviceID.D: (0.0, _TWO_PI),
    DeviceID.C: (0.0, 3.2),
    DeviceID.B: (0.0, _TWO_PI),
    DeviceID.A: (0.0, 10.0),
}
#: Velocity limits (rad/s; mm/s for the jaws). Assumed: not published (0.5 rad/s is an
#: older vendor URDF's joint limit; 3 mm/s sits below the jaw's no-load speed).
FACTORY_VELOCITY_LIMITS: dict[DeviceID, Range] = {
    **{d: (-0.5, 0.5) for d in JOINTS},
    DeviceID.A: (-3.0, 3.0),
}
#: Default motor current limits (mA), G F E D C B, and the jaws'. Assumed: not published.
DEFAULT_CURRENT_LIMITS_MA: tuple[float, ...] = (2000.0, 2000.0, 1500.0, 1500.0, 1500.0, 1000.0)
DEFAULT_JAW_CURRENT_LIMIT_MA = 1000.0
FACTORY_CURRENT_LIMITS: dict[DeviceID, Range] = {
    **{d: (-mA, mA) for d, mA in zip(JOINTS, DEFAULT_CURRENT_LIMITS_MA, strict=True)},
    JAW: (-DEFAULT_JAW_CURRENT_LIMIT_MA, DEFAULT_JAW_CURRENT_LIMIT_MA),
}

# Motor and gearbox datasheet constants, G F E D C B (G and F share one motor; E, D, C another).
MOTOR_RESISTANCE_OHM = (1.0, 1.0, 2.3, 2.3, 2.3, 5.9)
MOTOR_TORQUE_CONSTANT_NM_PER_A = (0.222, 0.222, 0.215, 0.215, 0.215, 0.209)  # motor shaft
MOTOR_BACKEMF_V_S_PER_RAD = (0.181, 0.181, 0.176, 0.176, 0.176, 0.171)  # motor shaft
GEAR_RATIO = (120.0, 120.0, 120.0, 120.0, 120.0, 120.0)
#: Not published; 1 because the datasheet's friction and damping were fitted to motor current,
#: so they already hold the gearbox's losses.
GEAR_EFFICIENCY = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
#: Joint output torque per amp of motor current, Kt x gear ratio x efficiency (26.6 N m/A for
#: G and F, 25.8 for E, D, C, 25.1 for B).
TORQUE_PER_AMP_NM: tuple[float, ...] = tuple(
    k * g * e
    for k, g, e in zip(MOTOR_TORQUE_CONSTANT_NM_PER_A, GEAR_RATIO, GEAR_EFFICIENCY, strict=True)
)
# The jaws' actuator: the same motor constants as B, and a ratio read as motor radians per mm
# of travel (the datasheet prints the bare number 39.27).
JAW_MOTOR_RESISTANCE_OHM = 5.9
JAW_MOTOR_TORQUE_CONSTANT_NM_PER_A = 0.209
JAW_MOTOR_BACKEMF_V_S_PER_RAD = 0.171
JAW_GEAR_RATIO_RAD_PER_MM = 39.27
JAW_GEAR_EFFICIENCY = 1.0
#: Jaw force per amp (N/A): Kt x ratio (per metre) x efficiency, about 8.2 kN/A.
JAW_FORCE_PER_AMP_N = (
    JAW_MOTOR_TORQUE_CONSTANT_NM_PER_A * JAW_GEAR_RATIO_RAD_PER_MM * 1000.0 * JAW_GEAR_EFFICIENCY
)
#: Not published; the Alpha's nominal supply is taken.
NOMINAL_SUPPLY_V = 24.0
