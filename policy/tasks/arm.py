"""The one view of the simulated arm that the env and the evaluation backends step.

`reach_sim_bridge.model.arm.Alpha5Arm` is the implementation; tests and tools may pass anything with
the same shape (a fake arm, an arm in air), so the policy code depends on this Protocol only.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from protocol.models import ALPHA5, ArmModel

PHYSICS_DT = 0.002
"""s: the MuJoCo step every runner uses (a control period is a whole number of them)."""


class ArmLike(Protocol):
    """The part of `Alpha5Arm` the env and the direct backend use (docs/architecture.md)."""

    @property
    def q(self) -> np.ndarray: ...

    @property
    def qdot(self) -> np.ndarray: ...

    @property
    def tau(self) -> np.ndarray: ...

    @property
    def position_limits(self) -> np.ndarray: ...

    @property
    def current_limits_mA(self) -> np.ndarray: ...

    @property
    def torque_scale(self) -> np.ndarray: ...

    @torque_scale.setter
    def torque_scale(self, scale: Any) -> None: ...

    def reset(self, q: Any = ..., qdot: Any = ..., jaw_mm: float = ...) -> Any: ...

    def step(
        self, currents_mA: Any, jaw_current_mA: float = ..., n: int = ..., work: Any = ...
    ) -> Any: ...

    def randomize(
        self, spread: float = ..., rng: np.random.Generator | int | None = ...
    ) -> Any: ...


def nominal_arm(seed: int = 0, dt: float = PHYSICS_DT, model: ArmModel = ALPHA5) -> ArmLike:
    """The MuJoCo twin of `model` at its nominal parameters (its own seed drives any
    randomness it has)."""
    from reach_sim_bridge.model.arms import arm_twin

    arm: ArmLike = arm_twin(model, None, dt, seed)
    return arm
