"""The one view of the simulated arm that the env and the evaluation backends step.

`reach_sim_bridge.model.arm.Alpha5Arm` is the implementation; tests and tools may pass anything with
the same shape (a fake arm, an arm in air), so the policy code depends on this Protocol only.
"""

from __future__ import annotations

from collections import deque
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


class CommandsInFlight:
    """Commands on their way to the arm (control latency): each takes effect `delay` physics
    steps after the state it was computed from, and the one in force holds until the next
    takes over. The env trains and the direct backend evaluates through this one queue, so
    both hold a late command alike."""

    def __init__(self, delay: int, joints: int) -> None:
        if delay < 0:
            raise ValueError(f"delay must be >= 0 physics steps, got {delay}")
        self.delay = delay
        self.applied = np.zeros(joints)  # the command in force (zero current before the first)
        self._pending: deque[tuple[int, np.ndarray]] = deque()

    def advance(
        self, arm: ArmLike, command: np.ndarray, start: int, n: int, work: Any = None
    ) -> None:
        """Send `command`, computed at physics step `start`, and step `arm` n physics steps,
        switching to each command in flight at the step it lands on (`work`: `arm.step`'s,
        summed over the whole span)."""
        pending = self._pending
        pending.append((start + self.delay, command))
        i = 0
        while i < n:
            while pending and pending[0][0] <= start + i:
                self.applied = pending.popleft()[1]
            # hold the command in force up to the next switch
            until = n if not pending else min(n, pending[0][0] - start)
            arm.step(self.applied, n=until - i, work=work)
            i = until


def nominal_arm(seed: int = 0, dt: float = PHYSICS_DT, model: ArmModel = ALPHA5) -> ArmLike:
    """The MuJoCo twin of `model` at its nominal parameters (its own seed drives any
    randomness it has)."""
    from reach_sim_bridge.model.arms import arm_twin

    arm: ArmLike = arm_twin(model, None, dt, seed)
    return arm
