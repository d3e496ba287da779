"""Physical parameters of the simulated Alpha 5 that vary between arms, fluids and faults.

The MJCF (model/alpha5.xml) holds the nominal arm; ``ArmParams()`` holds the same nominal
values (a test keeps the two equal) so they can be perturbed, read by MPC, and applied to a
compiled model without recompiling. Arrays of four are in joint order E D C B; the link
arrays name the body each joint moves (E -> m2_1_1, D -> m2, C -> m2_1_3, B -> m1 + jaws).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from reach_sim_bridge.motor import (
    ALPHA5_MOTORS,
    DEFAULT_CURRENT_LIMITS_MA,
    DEFAULT_JAW_CURRENT_LIMIT_MA,
    DEFAULT_SUPPLY_VOLTAGE,
    JAW_MOTOR,
    MotorParams,
)

LINK_BODIES = ("m2_1_1", "m2", "m2_1_3", "m1")  # the body each of E D C B moves

Vec4 = tuple[float, float, float, float]

_VEC4_FIELDS = (
    "armature",
    "damping",
    "frictionloss",
    "link_mass_kg",
    "link_volume_l",
    "torque_scale",
    "current_limits_mA",
)


@dataclass(frozen=True)
class ArmParams:
    """Everything about one simulated arm that a run may change (see model/README.md)."""

    # Joints E D C B: reflected rotor inertia (kg m^2), viscous (N m s/rad), Coulomb (N m).
    armature: Vec4 = (0.12, 0.12, 0.12, 0.007)
    damping: Vec4 = (2.40, 2.24, 0.82, 0.36)
    frictionloss: Vec4 = (0.7, 0.7, 0.7, 0.075)
    # Links moved by E D C B: mass (kg) and displaced volume (litres) from the datasheet.
    link_mass_kg: Vec4 = (0.161, 0.380, 0.142, 0.355)
    link_volume_l: Vec4 = (0.032, 0.218, 0.032, 0.134)
    # Medium: water density 0 means in air (no buoyancy, no drag).
    water_density: float = 1000.0  # kg/m^3 (1000 fresh, ~1025 sea)
    fluid_viscosity: float = 0.0009  # Pa s
    fluid_drag: bool = True  # MuJoCo's ellipsoid drag model; off for speed
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)  # in the base frame (z up)
    # Motors and drive.
    motors: MotorParams = ALPHA5_MOTORS
    supply_voltage: float = DEFAULT_SUPPLY_VOLTAGE
    current_limits_mA: Vec4 = DEFAULT_CURRENT_LIMITS_MA  # type: ignore[assignment]
    torque_scale: Vec4 = (1.0, 1.0, 1.0, 1.0)
    # Jaw (slide joint A, metres): assumed values, see model/README.md.
    jaw_motor: MotorParams = JAW_MOTOR
    jaw_current_limit_mA: float = DEFAULT_JAW_CURRENT_LIMIT_MA
    jaw_armature: float = 725.0  # kg: B's rotor inertia reflected through jaw gear + screw
    jaw_damping: float = 5000.0  # N s/m
    jaw_frictionloss: float = 10.0  # N
    # The real wrist B turns without end stops and reports 0..2pi; by default the model
    # gives it stops at 0 and 2pi so the reported angle never jumps.
    wrist_continuous: bool = False
    # Contacts between the links and the base. Off by default: the link cylinders are
    # sized by displaced volume, fatter than the real links (see model/README.md).
    self_collision: bool = False

    def __post_init__(self) -> None:
        for name in _VEC4_FIELDS:
            vec = tuple(float(v) for v in np.asarray(getattr(self, name), float).reshape(-1))
            if len(vec) != 4 or not all(math.isfinite(v) for v in vec):
                raise ValueError(f"{name} needs 4 finite values (E D C B), got {vec}")
            object.__setattr__(self, name, vec)
        for name in ("armature", "link_mass_kg"):
            if any(v <= 0.0 for v in getattr(self, name)):
                raise ValueError(f"{name} must be > 0 for every joint, got {getattr(self, name)}")
        for name in ("damping", "frictionloss", "link_volume_l", "current_limits_mA"):
            if any(v < 0.0 for v in getattr(self, name)):
                raise ValueError(f"{name} must be >= 0 for every joint, got {getattr(self, name)}")
        if any(not 0.0 <= v <= 1.0 for v in self.torque_scale):
            raise ValueError(f"torque_scale must be in [0, 1] per joint, got {self.torque_scale}")
        gravity = tuple(float(v) for v in self.gravity)
        if len(gravity) != 3 or not all(math.isfinite(v) for v in gravity):
            raise ValueError(f"gravity needs 3 finite values (m/s^2), got {self.gravity}")
        object.__setattr__(self, "gravity", gravity)
        for name in (
            "water_density",
            "fluid_viscosity",
            "jaw_current_limit_mA",
            "jaw_damping",
            "jaw_frictionloss",
        ):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
            object.__setattr__(self, name, value)
        for name in ("supply_voltage", "jaw_armature"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a finite number > 0, got {value}")
            object.__setattr__(self, name, value)
        if self.motors.count != 4 or self.jaw_motor.count != 1:
            raise ValueError("motors needs 4 entries (E D C B) and jaw_motor 1")

    @property
    def in_water(self) -> bool:
        return self.water_density > 0.0

    def buoyancy_kg(self) -> np.ndarray:
        """Mass of water each link displaces (kg), E D C B."""
        return np.asarray(self.link_volume_l) * 1e-3 * self.water_density

    def in_air(self) -> ArmParams:
        """The same arm out of the water (no buoyancy, no drag)."""
        return replace(self, water_density=0.0)

    def randomized(self, rng: np.random.Generator | int | None, spread: float = 0.2) -> ArmParams:
        """A perturbed copy: friction, armature, link masses and buoyancy each scaled by an
        independent uniform factor in [1 - spread, 1 + spread] (per joint)."""
        if not (math.isfinite(spread) and 0.0 <= spread < 1.0):
            raise ValueError(f"spread must be in [0, 1), got {spread}")
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)

        def scaled(values: Vec4) -> Vec4:
            f = gen.uniform(1.0 - spread, 1.0 + spread, size=4)
            out = np.asarray(values) * f
            return (float(out[0]), float(out[1]), float(out[2]), float(out[3]))

        return replace(
            self,
            damping=scaled(self.damping),
            frictionloss=scaled(self.frictionloss),
            armature=scaled(self.armature),
            link_mass_kg=scaled(self.link_mass_kg),
            link_volume_l=scaled(self.link_volume_l),
        )

    def as_dict(self) -> dict[str, object]:
        """Plain values for logs and recordings."""
        return {f.name: getattr(self, f.name) for f in fields(self)}
