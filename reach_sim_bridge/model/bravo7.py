"""The Reach Bravo 7 twin: its MJCF (model/bravo7.xml), stepped with motor currents.

`load()` gives the model with buoyancy for a chosen water density, `gravity_torque()` the
static torque on each joint, and `Bravo7Arm` the arm the virtual Bravo (`reach-sim --arm
bravo7`) steps: the Alpha's motor law (`MotorArm`) on the Bravo's joints, and the wrench its
jaws put on the wrist, which the optional force-torque sensor reads. Sources: model/bravo7.md.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol.bravo7 import (
    DEFAULT_CURRENT_LIMITS_MA,
    DEFAULT_JAW_CURRENT_LIMIT_MA,
    JOINT_LETTERS,
    NOMINAL_SUPPLY_V,
)
from protocol.models import BRAVO7
from reach_sim_bridge.model.arm import MotorArm, check_dt
from reach_sim_bridge.model.motor import BRAVO7_JAW_MOTOR, BRAVO7_MOTORS, MotorModel
from reach_sim_bridge.model.params import ArmParams

__all__ = [
    "BUOYANCY_GRAVCOMP",
    "FT_SITE",
    "JOINTS",
    "LINK_BODIES",
    "LINK_VOLUME_L",
    "MODEL_PATH",
    "Bravo7Arm",
    "gravity_torque",
    "load",
]

MODEL_PATH = Path(__file__).resolve().parent / "bravo7.xml"
JOINTS = JOINT_LETTERS  # G F E D C B, then the jaw A
#: The moving links with displaced volume: link i is moved by joint i (G..B), link 7 is the
#: jaws, fixed to link 6.
LINK_BODIES = ("link1", "link2", "link3", "link4", "link5", "link6", "link7")
#: Datasheet displaced volume of each of `LINK_BODIES` (litres).
LINK_VOLUME_L = (0.74, 1.96, 0.44, 0.59, 0.39, 0.53, 0.16)
#: gravcomp of the buoyancy bodies: a body of mass m_b pushes up with (g_c - 1) m_b g.
BUOYANCY_GRAVCOMP = 1001.0
#: The force-torque sensor's frame: at the wrist flange, z along the wrist axis towards the
#: jaws (the vendor: "the Z axis is along the axis of the sensor"), x the flange's x [A].
FT_SITE = "ft"
#: The body whose load on the wrist the sensor reads: the jaws (link 7) and all below it.
FT_BODY = "link7"

FloatArray = NDArray[np.float64]


def load(water_density: float = 1000.0, fluid_drag: bool = True) -> mujoco.MjModel:
    """The Bravo 7 in water of this density (kg/m^3: 1000 fresh, ~1025 sea, 0 for air).

    Buoyancy is rho V g up at each link's centre of buoyancy; drag is MuJoCo's ellipsoid model
    on the link cylinders (off in air or when `fluid_drag` is False)."""
    rho = float(water_density)
    if not (math.isfinite(rho) and 0.0 <= rho <= 2000.0):
        raise ValueError(f"water_density is kg/m^3 (1000 fresh, ~1025 sea, 0 air), got {rho}")
    model = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    for name, litres in zip(LINK_BODIES, LINK_VOLUME_L, strict=True):
        body = model.body(name + "_buoyancy").id
        model.body_mass[body] = rho * litres * 1e-3 / (BUOYANCY_GRAVCOMP - 1.0)
    drag = fluid_drag and rho > 0.0
    model.opt.density = rho if drag else 0.0
    if not drag:
        model.opt.viscosity = 0.0
    return model


def gravity_torque(model: mujoco.MjModel, q: ArrayLike) -> FloatArray:
    """Torque gravity and buoyancy exert on G F E D C B at rest at q (N m); a controller holds
    the arm still by applying its negative."""
    angles = np.asarray(q, dtype=np.float64).reshape(-1)
    if angles.shape != (len(JOINTS),) or not np.all(np.isfinite(angles)):
        raise ValueError(f"q needs {len(JOINTS)} finite angles (G F E D C B), got {q!r}")
    data = mujoco.MjData(model)
    data.qpos[: len(JOINTS)] = angles
    mujoco.mj_forward(model, data)
    n = len(JOINTS)
    return np.asarray(data.qfrc_gravcomp[:n] - data.qfrc_bias[:n], dtype=np.float64)


class Bravo7Arm(MotorArm):
    """The Bravo 7's six joints (G F E D C B) and jaws, stepped with motor currents (mA)
    through the motors' current limit and back-EMF envelope, as the Alpha's are; state in
    the arm's units. Friction, damping and armature are the MJCF's (model/bravo7.md) unless
    `params` (an identified arm, `ArmParams` of six joints) say otherwise; `params`, when
    given, also hold the medium and the supply."""

    def __init__(
        self,
        water_density: float = 1000.0,
        fluid_drag: bool = True,
        dt: float = 0.002,
        seed: int | None = None,
        supply_voltage: float = NOMINAL_SUPPLY_V,
        params: ArmParams | None = None,
    ) -> None:
        check_dt(dt)
        p = params or self.nominal(water_density, fluid_drag, supply_voltage)
        super().__init__(
            load(p.water_density, p.fluid_drag),
            BRAVO7,
            MotorModel(p.motors, p.supply_voltage, p.current_limits_mA, p.torque_scale),
            MotorModel(p.jaw_motor, p.supply_voltage, (p.jaw_current_limit_mA,)),
            dt,
            seed,
            LINK_BODIES,
        )
        m = self.model
        # the jaws' link (7) floats but is no parameter: its volume follows the water
        fixed = tuple(zip(LINK_BODIES[len(JOINTS) :], LINK_VOLUME_L[len(JOINTS) :], strict=True))
        self._init_params(p, ("link0", *LINK_BODIES), fixed)
        self._ft_site = m.site(FT_SITE).id
        root = m.body(FT_BODY).id
        below = [root]
        for body in range(root + 1, m.nbody):  # MuJoCo numbers a subtree after its root
            if m.body_parentid[body] in below:
                below.append(body)
        self._ft_bodies = np.array(below)
        self._ft_root = root
        self.reset()

    @property
    def water_density(self) -> float:
        return self._params.water_density

    @staticmethod
    def nominal(
        water_density: float = 1000.0,
        fluid_drag: bool = True,
        supply_voltage: float = NOMINAL_SUPPLY_V,
    ) -> ArmParams:
        """The nominal Bravo 7 as `ArmParams`: read from its MJCF (friction, damping,
        armature, link masses, the jaw's slide) and `protocol.bravo7` (motors, current
        limits), volumes from the datasheet (`LINK_VOLUME_L`); what a `--params` file for a
        Bravo does not name."""
        m = mujoco.MjModel.from_xml_path(str(MODEL_PATH))  # as written: the medium is ours
        n = len(JOINTS)
        dof = [m.jnt_dofadr[m.joint(name).id] for name in (*JOINTS, BRAVO7.jaw.name)]
        links = [m.body(name).id for name in LINK_BODIES[:n]]

        def per_joint(values: NDArray[np.float64]) -> tuple[float, ...]:
            return tuple(float(v) for v in values)

        return ArmParams(
            armature=per_joint(m.dof_armature[dof[:n]]),
            damping=per_joint(m.dof_damping[dof[:n]]),
            frictionloss=per_joint(m.dof_frictionloss[dof[:n]]),
            link_mass_kg=per_joint(m.body_mass[links]),
            link_volume_l=LINK_VOLUME_L[:n],
            water_density=float(water_density),
            fluid_viscosity=float(m.opt.viscosity),
            fluid_drag=fluid_drag,
            gravity=(float(m.opt.gravity[0]), float(m.opt.gravity[1]), float(m.opt.gravity[2])),
            motors=BRAVO7_MOTORS,
            supply_voltage=supply_voltage,
            current_limits_mA=DEFAULT_CURRENT_LIMITS_MA,
            torque_scale=(1.0,) * n,
            jaw_motor=BRAVO7_JAW_MOTOR,
            jaw_current_limit_mA=DEFAULT_JAW_CURRENT_LIMIT_MA,
            jaw_armature=float(m.dof_armature[dof[n]]),
            jaw_damping=float(m.dof_damping[dof[n]]),
            jaw_frictionloss=float(m.dof_frictionloss[dof[n]]),
            wrist_continuous=not bool(m.jnt_limited[m.joint(JOINTS[-1]).id]),
        )

    def force_torque(self) -> FloatArray:
        """The wrench the jaws put on the wrist, as the force-torque sensor reads it: force
        (N) then torque about the sensor's origin (N m), in the sensor's frame (`FT_SITE`).
        At rest in air the force is the jaws' weight; in water, less their buoyancy.

        From MuJoCo's interaction force between the wrist and the jaws' subtree at the last
        physics step's accelerations (`mj_rnePostConstraint`), with the buoyancy bodies' lift
        added (MuJoCo applies gravity compensation in joint space, not as a body force). The
        water's drag on the jaws is not in it."""
        m, d, s = self.model, self.data, self._scratch
        s.qpos[:] = d.qpos
        s.qvel[:] = d.qvel
        mujoco.mj_kinematics(m, s)
        mujoco.mj_comPos(m, s)
        mujoco.mj_comVel(m, s)
        s.qacc[:] = d.qacc
        mujoco.mj_rnePostConstraint(m, s)
        # cfrc_int: the spatial force (torque, force) the wrist exerts on the subtree, about
        # the centre of mass of the kinematic tree.
        origin = s.subtree_com[m.body_rootid[self._ft_root]]
        torque = s.cfrc_int[self._ft_root, :3].copy()
        force = s.cfrc_int[self._ft_root, 3:].copy()
        gravity = np.asarray(m.opt.gravity)
        for body in self._ft_bodies.tolist():
            # gravity compensation (the buoyancy): a load the wrist does not carry
            unheld = m.body_gravcomp[body] * m.body_mass[body] * gravity
            if unheld.any():
                force += unheld
                torque += np.cross(s.xipos[body] - origin, unheld)
        point = s.site_xpos[self._ft_site]
        torque += np.cross(origin - point, force)
        frame = s.site_xmat[self._ft_site].reshape(3, 3)
        # What the jaws put on the sensor: the opposite of what the wrist puts on them.
        return np.concatenate([frame.T @ -force, frame.T @ -torque])
