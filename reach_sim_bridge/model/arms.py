"""The MuJoCo arm of each arm model, for a controller that needs a twin of the arm it drives.

The Alpha 5's takes run-time parameters (`ArmParams`: nominal, a file, a fit); the Bravo 7's
is its MJCF as written (model/bravo7.md), in fresh water: no parameter file describes a Bravo
yet, so one given for it is refused rather than read as an Alpha's.
"""

from __future__ import annotations

from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_sim_bridge.model.arm import Alpha5Arm, MotorArm
from reach_sim_bridge.model.bravo7 import Bravo7Arm
from reach_sim_bridge.model.params import ArmParams

__all__ = ["arm_twin", "takes_params"]


def takes_params(model: ArmModel) -> bool:
    """Whether the twin of `model` takes `ArmParams` (friction, masses, buoyancy... that an
    identification fits and the uncertainty envelope perturbs): the Alpha 5's only."""
    return model is ALPHA5


def arm_twin(model: ArmModel, params: ArmParams | None = None, dt: float = 0.002) -> MotorArm:
    """The twin of `model`, with `params` on the Alpha 5 (nominal if None), stepped every
    `dt` s; ValueError for parameters given for another model, or a model with no twin."""
    if takes_params(model):
        return Alpha5Arm(params=params or ArmParams(), dt=dt)
    if params is not None:
        raise ValueError(
            f"arm parameters (params) describe a {ALPHA5.title}; the twin of the "
            f"{model.title} is its MJCF's"
        )
    if model is BRAVO7:
        return Bravo7Arm(dt=dt)
    raise ValueError(f"no twin of the {model.title}")
