"""The Reach Bravo 7 twin's MJCF (model/bravo7.xml) and what is needed to use it.

A first brick: the model loads, with buoyancy for a chosen water density, and reports the
static torque gravity and buoyancy put on each joint. Nothing steps it with motor currents
yet (the Alpha's `Alpha5Arm` does that for the Alpha 5). Sources: model/bravo7.md.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol.bravo7 import JOINT_LETTERS

__all__ = [
    "BUOYANCY_GRAVCOMP",
    "JOINTS",
    "LINK_BODIES",
    "LINK_VOLUME_L",
    "MODEL_PATH",
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
