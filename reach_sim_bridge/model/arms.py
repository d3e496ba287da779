"""The MuJoCo arm of each arm model, for the simulator and for a controller that needs a twin
of the arm it drives, and the nominal `ArmParams` of each.

Every twin takes run-time parameters (`ArmParams`: nominal, a file, a fit): the Alpha 5's
nominal values are `ArmParams()`, the Bravo 7's its MJCF's as written (model/bravo7.md,
`Bravo7Arm.nominal`). Parameters for another number of joints than the model's are refused
in one line naming the arm they fit.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from protocol.models import ALPHA5, BRAVO7, MODELS, ArmModel
from reach_sim_bridge.model.arm import Alpha5Arm, MotorArm
from reach_sim_bridge.model.bravo7 import Bravo7Arm
from reach_sim_bridge.model.params import ArmParams, joint_order, load_arm_params

__all__ = ["TWINS", "arm_twin", "load_params", "nominal_params"]

#: Each model's twin: (params, physics dt, seed of `randomize`) -> the arm.
TWINS: dict[str, Callable[[ArmParams | None, float, int | None], MotorArm]] = {
    ALPHA5.name: lambda p, dt, seed: Alpha5Arm(params=p, dt=dt, seed=seed),
    BRAVO7.name: lambda p, dt, seed: Bravo7Arm(params=p, dt=dt, seed=seed),
}
#: Each model's nominal arm parameters.
_NOMINAL: dict[str, Callable[[], ArmParams]] = {
    ALPHA5.name: ArmParams,
    BRAVO7.name: Bravo7Arm.nominal,
}


def _known(model: ArmModel) -> None:
    if model.name not in TWINS:
        raise ValueError(f"no twin of the {model.title} (twins: {', '.join(TWINS)})")


def nominal_params(model: ArmModel) -> ArmParams:
    """The nominal parameters of `model`'s twin (ValueError for a model with no twin)."""
    _known(model)
    return _NOMINAL[model.name]()


def params_problem(params: ArmParams, model: ArmModel) -> str | None:
    """Why `params` cannot describe `model` (another number of joints), or None."""
    if params.n_joints == model.n_joints:
        return None
    order = joint_order(params.n_joints)
    return (
        f"arm parameters of {params.n_joints} joints ({order}) describe "
        + next(
            (f"a {m.title}" for m in MODELS.values() if m.n_joints == params.n_joints),
            "another arm",
        )
        + f", not the {model.title} ({model.n_joints} joints {' '.join(model.joint_letters)})"
    )


def load_params(path: str | Path, model: ArmModel) -> ArmParams:
    """The arm of `model` a `--params FILE.json` describes, the rest `model`'s nominal
    (`ParamsFileError`, one line, for a file of another arm's joints)."""
    return load_arm_params(path, model, nominal_params(model))


def arm_twin(
    model: ArmModel, params: ArmParams | None = None, dt: float = 0.002, seed: int | None = None
) -> MotorArm:
    """The twin of `model` with `params` (nominal if None); ValueError for parameters of
    another arm, or a model with no twin."""
    _known(model)
    if params is not None:
        problem = params_problem(params, model)
        if problem:
            raise ValueError(problem)
    return TWINS[model.name](params, dt, seed)
