"""The direct backend: the controller steps the arm's twin itself at the control period.

The controller's currents are held for the period (zero-order hold) while the physics runs
its substeps, the way the firmware holds the last CURRENT packet. The controller sees only
(optionally noisy) readings; the trace is the simulator's true state.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from policy.tasks.arm import ArmLike, CommandsInFlight, nominal_arm
from policy.tasks.episodes import (
    Episode,
    EpisodeResult,
    RunConfig,
    check_inside_limits,
    reading,
    score,
)
from protocol.models import ALPHA5, ArmModel
from reach_driver.controllers import Controller, ControlState
from reach_driver.metrics import Trace
from reach_sim_bridge.model.params import ArmParams

ArmFactory = Callable[[int], ArmLike]
"""Builds a fresh arm for an episode from its seed."""


@dataclass(frozen=True)
class DirectArm:
    """Backend for episodes of `model`: a fresh arm from `arm_factory(episode_seed)` per
    episode (None: `model`'s twin at its nominal parameters)."""

    arm_factory: ArmFactory | None = None
    model: ArmModel = ALPHA5

    def _arm(self, episode: Episode, episode_seed: int) -> ArmLike:
        if episode.model.name != self.model.name:
            raise ValueError(
                f"an episode of the {episode.model.title} on a runner of the {self.model.title}"
            )
        factory = self.arm_factory or partial(nominal_arm, model=self.model)
        arm = factory(episode_seed)
        joints = np.shape(arm.position_limits)[0]
        if joints != self.model.n_joints:
            raise ValueError(
                f"the arm factory built an arm of {joints} joints for the {self.model.title} "
                f"({self.model.n_joints})"
            )
        return arm

    def run(
        self, controller: Controller, episode: Episode, config: RunConfig, episode_seed: int
    ) -> EpisodeResult:
        arm = self._arm(episode, episode_seed)
        if abs(config.physics_dt - float(getattr(arm, "dt", config.physics_dt))) > 1e-12:
            raise ValueError("the arm's physics step differs from RunConfig.physics_dt")
        if config.params is not None:
            use_params(arm, config.params)
        check_inside_limits(arm.position_limits, episode.start, "start", self.model)
        check_inside_limits(arm.position_limits, episode.target, "target", self.model)
        if config.param_spread > 0:
            arm.randomize(config.param_spread, rng=config.perturbation_rng(episode_seed))
        arm.reset(q=episode.start.copy())
        arm.torque_scale = episode.torque_scale.copy()
        acting = reading(controller, config, episode_seed)
        acting.reset()
        n, joints = config.n_steps, self.model.n_joints
        q = np.empty((n + 1, joints))
        qdot = np.empty((n + 1, joints))
        tau = np.zeros((n + 1, joints))
        power = np.zeros((n + 1, joints))
        currents = np.zeros((n + 1, joints))
        q[0], qdot[0] = arm.q, arm.qdot
        target = episode.target.copy()
        in_flight = CommandsInFlight(config.latency_substeps, joints)
        for k in range(n):
            state = ControlState(q[k].copy(), qdot[k].copy(), k * config.period)
            action = acting.act(state, target.copy())
            u = np.asarray(action, dtype=float)
            if u.shape != (joints,) or not np.all(np.isfinite(u)):
                raise ValueError(
                    f"controller returned {action!r} at step {k}: expected {joints} finite "
                    f"currents (mA) for the {self.model.title}"
                )
            # The energy integrates |tau qdot| at the physics rate (the back-EMF makes the
            # torque vary within a held period): the arm sums it over each held command.
            energy = np.zeros(joints)
            in_flight.advance(arm, u, k * config.substeps, config.substeps, work=energy)
            power[k + 1] = energy / config.substeps
            q[k + 1], qdot[k + 1] = arm.q, arm.qdot
            tau[k + 1] = arm.tau
            currents[k + 1] = u
        trace = Trace(
            dt=config.period, q=q, qdot=qdot, tau=tau, target=target, power=power, model=self.model
        )
        return score(episode, trace, currents)

    def stats(self) -> dict[str, Any]:
        return {}


def use_params(arm: ArmLike, params: ArmParams) -> None:
    """Make `arm` the arm `params` describes, and the one `randomize` perturbs around."""
    set_params = getattr(arm, "set_params", None)
    if set_params is None:
        raise ValueError("RunConfig.params needs an arm with set_params (a MuJoCo twin)")
    set_params(params)
    arm.nominal_params = params  # type: ignore[attr-defined]
