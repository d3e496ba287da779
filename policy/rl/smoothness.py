"""A smooth actor: CAPS's two regularisers of the actor's loss (Mysore et al., "Regularizing
action policies for smooth control with reinforcement learning", ICRA 2021).

Why: a learned actor that holds the goal to the milliradian has a high gain there, and the same
gain turns the sensors' noise (2 mrad, 0.02 rad/s) into currents, so the arm moves at rest
(docs/ablation.md). The reward pays for that motion only through its effect on the true state,
one step at a time, and the critic barely resolves it. CAPS asks for smoothness in the loss the
actor itself is trained on:

- spatial: `|| pi(s) - pi(s~) ||`, s~ the observation of the same state read with fresh sensor
  noise, so the actor learns to answer the noise as little as it can afford;
- temporal: `|| pi(s_t) - pi(s_t+1) ||`, consecutive observations of the replayed transition.

Both are Euclidean norms (not squared: a squared norm gives a small dither almost no gradient),
averaged over the batch and weighted by `DDPGConfig.smooth_spatial_weight` /
`smooth_temporal_weight` (0: off). Nothing runs around the network at control time: what the
actor computes is learned. The spatial term's noise is drawn per input with
`input_noise_std`, measured once from the observation function itself, so each input's
perturbation is what the sensors' noise does to it (the fine-error channel most, the goal none).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from policy.controllers.observation import InputMemory, Workspace
from policy.rl.env import SENSOR_NOISE, EnvConfig

#: rad: goals drawn this far (1 sigma) from the state when measuring the inputs' noise: near
#: the goal, where the fine-error channel is steepest and the dither happens
NEAR_GOAL_STD = 0.02
#: rad/s: the speeds the states are drawn with (1 sigma): an arm settling
SETTLING_SPEED_STD = 0.1
#: avoids the norm's undefined gradient at zero
_NORM_EPS = 1e-12


def input_noise_std(env: EnvConfig, samples: int = 2048, seed: int = 0) -> np.ndarray:
    """Per input of `env`'s observation, the standard deviation of its change when the
    readings carry sensor noise (Table I's sigmas times `noise_scale`, whether or not the env
    applies it: the arm will) instead of none, over states near the goal. The memory channels
    are filled over the window's length (history + 1 periods) with the same readings, so the
    integral and the window carry the noise of as many periods as the window holds; the
    previous actions carry none."""
    model = env.model
    workspace = Workspace.of(model)
    rng = np.random.default_rng(seed)
    noise = SENSOR_NOISE.scaled(env.noise_scale)
    dt = 1.0 / env.control_hz
    n = model.n_joints
    periods = env.observation.history + 1
    diffs = np.empty((samples, env.observation.size_for(n)))
    low, high = np.asarray(workspace.low), np.asarray(workspace.high)
    for k in range(samples):
        q = rng.uniform(low, high)
        qdot = rng.normal(0.0, SETTLING_SPEED_STD, n)
        target = np.clip(q + rng.normal(0.0, NEAR_GOAL_STD, n), low, high)
        exact = InputMemory(env.observation, dt, workspace)
        noisy = InputMemory(env.observation, dt, workspace)
        for _ in range(periods):
            obs = exact.observe(q, qdot, target)
            q_n, qdot_n = noise.apply(q, qdot, rng)
            obs_n = noisy.observe(q_n, qdot_n, target)
            exact.acted(np.zeros(n))
            noisy.acted(np.zeros(n))
        diffs[k] = obs_n - obs
    std: np.ndarray = np.sqrt(np.mean(diffs**2, axis=0)).astype(np.float32)
    return std


def _mean_norm(diff: torch.Tensor) -> torch.Tensor:
    return torch.sqrt((diff**2).sum(dim=1) + _NORM_EPS).mean()


def spatial_loss(
    actor: nn.Module,
    obs: torch.Tensor,
    pi: torch.Tensor,
    noise_std: torch.Tensor,
    gen: torch.Generator,
) -> torch.Tensor:
    """Mean `|| pi(s) - pi(s~) ||` over the batch, s~ = s + noise_std * N(0, 1) per input."""
    nearby = obs + torch.randn(obs.shape, generator=gen) * noise_std
    return _mean_norm(pi - actor(nearby))


def temporal_loss(actor: nn.Module, pi: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """Mean `|| pi(s_t) - pi(s_t+1) ||` over the batch (s_t+1: the transition's next
    observation, n steps on with n-step returns)."""
    return _mean_norm(pi - actor(next_obs))
