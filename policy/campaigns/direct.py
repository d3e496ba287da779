"""The direct backend: the controller steps `Alpha5Arm` itself at the control period.

The controller's currents are held for the period (zero-order hold) while the physics runs
its substeps, the way the firmware holds the last CURRENT packet. The controller sees only
(optionally noisy) readings; the trace is the simulator's true state.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from policy.tasks.arm import ArmLike, nominal_arm
from policy.tasks.episodes import (
    Episode,
    EpisodeResult,
    RunConfig,
    check_inside_limits,
    reading,
    score,
)
from protocol.alpha5 import N_JOINTS
from reach_driver.controllers import Controller, ControlState
from reach_driver.metrics import Trace
from reach_sim_bridge.model.params import ArmParams

ArmFactory = Callable[[int], ArmLike]
"""Builds a fresh arm for an episode from its seed."""


@dataclass(frozen=True)
class DirectArm:
    """Backend: a fresh arm from `arm_factory(episode_seed)` per episode."""

    arm_factory: ArmFactory = field(default=nominal_arm)

    def run(
        self, controller: Controller, episode: Episode, config: RunConfig, episode_seed: int
    ) -> EpisodeResult:
        arm = self.arm_factory(episode_seed)
        if abs(config.physics_dt - float(getattr(arm, "dt", config.physics_dt))) > 1e-12:
            raise ValueError("the arm's physics step differs from RunConfig.physics_dt")
        if config.params is not None:
            use_params(arm, config.params)
        check_inside_limits(arm.position_limits, episode.start, "start")
        check_inside_limits(arm.position_limits, episode.target, "target")
        if config.param_spread > 0:
            arm.randomize(config.param_spread, rng=config.perturbation_rng(episode_seed))
        arm.reset(q=episode.start.copy())
        arm.torque_scale = episode.torque_scale.copy()
        acting = reading(controller, config, episode_seed)
        acting.reset()
        n = config.n_steps
        q = np.empty((n + 1, N_JOINTS))
        qdot = np.empty((n + 1, N_JOINTS))
        tau = np.zeros((n + 1, N_JOINTS))
        power = np.zeros((n + 1, N_JOINTS))
        currents = np.zeros((n + 1, N_JOINTS))
        q[0], qdot[0] = arm.q, arm.qdot
        target = episode.target.copy()
        # Commands in flight (control latency): (physics step they take effect at, currents).
        delay = config.latency_substeps
        pending: deque[tuple[int, np.ndarray]] = deque()
        applied = np.zeros(N_JOINTS)
        for k in range(n):
            state = ControlState(q[k].copy(), qdot[k].copy(), k * config.period)
            action = acting.act(state, target.copy())
            u = np.asarray(action, dtype=float)
            if u.shape != (N_JOINTS,) or not np.all(np.isfinite(u)):
                raise ValueError(
                    f"controller returned {action!r} at step {k}: expected 4 finite currents (mA)"
                )
            # Physics steps one at a time so the energy integrates |tau qdot| at the physics
            # rate (the back-EMF makes the torque vary within a held period).
            energy = np.zeros(N_JOINTS)
            pending.append((k * config.substeps + delay, u))
            for i in range(config.substeps):
                while pending and pending[0][0] <= k * config.substeps + i:
                    applied = pending.popleft()[1]
                arm.step(applied, n=1)
                energy += np.abs(arm.tau * arm.qdot)
            power[k + 1] = energy / config.substeps
            q[k + 1], qdot[k + 1] = arm.q, arm.qdot
            tau[k + 1] = arm.tau
            currents[k + 1] = u
        trace = Trace(dt=config.period, q=q, qdot=qdot, tau=tau, target=target, power=power)
        return score(episode, trace, currents)

    def stats(self) -> dict[str, Any]:
        return {}


def use_params(arm: ArmLike, params: ArmParams) -> None:
    """Make `arm` the arm `params` describes, and the one `randomize` perturbs around."""
    set_params = getattr(arm, "set_params", None)
    if set_params is None:
        raise ValueError("RunConfig.params needs an arm with set_params (Alpha5Arm)")
    set_params(params)
    arm.nominal_params = params  # type: ignore[attr-defined]
