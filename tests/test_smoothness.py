"""CAPS's smoothness terms in the actor's loss (policy/rl/smoothness.py): the inputs' noise is
what the sensors' noise does to each input, and each term, weighted, makes the trained actor
answer that noise (spatial) or the next state (temporal) less than the same updates without it."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
import torch

from policy.controllers.observation import Workspace
from policy.rl.agent import Agent
from policy.rl.config import Algorithm, DDPGConfig
from policy.rl.env import SENSOR_NOISE
from policy.rl.smoothness import input_noise_std
from protocol.models import ALPHA5, BRAVO7

OBS = DDPGConfig.scratch().env.observation.size_for(4)  # 28: five groups, action, integral


def test_each_input_carries_what_the_sensor_noise_does_to_it() -> None:
    env = DDPGConfig.scratch().env
    std = input_noise_std(env, samples=4096)
    assert std.shape == (OBS,)
    half = Workspace.of(ALPHA5).half_range
    q, qdot, goal, err, fine, prev, integral = (std[k * 4 : (k + 1) * 4] for k in range(7))
    np.testing.assert_allclose(q, SENSOR_NOISE.position_std / half, rtol=0.06)
    np.testing.assert_allclose(
        qdot, SENSOR_NOISE.velocity_std / env.observation.qdot_scale, rtol=0.06
    )
    np.testing.assert_allclose(err, SENSOR_NOISE.position_std / half, rtol=0.06)
    assert np.all(goal == 0) and np.all(prev == 0)  # the goal and the actions are not read
    # the fine channel is steepest: 0.002 / 0.05 at the goal, less where tanh bends
    assert np.all(fine > 0.6 * SENSOR_NOISE.position_std / env.observation.fine_error_scale)
    assert np.all(fine < SENSOR_NOISE.position_std / env.observation.fine_error_scale)
    assert np.all(integral > 0) and np.all(integral < fine)  # one period of a leaky mean
    # twice the noise, twice the spread
    loud = input_noise_std(dataclasses.replace(env, noise_scale=2.0), samples=4096)
    np.testing.assert_allclose(loud[4:8], 2 * qdot, rtol=0.06)


def test_the_window_carries_the_noise_of_the_speeds_it_holds() -> None:
    base = DDPGConfig.scratch().env
    env = dataclasses.replace(base, observation=dataclasses.replace(base.observation, history=2))
    std = input_noise_std(env, samples=2048)
    window = std[28:].reshape(2, 8)
    expected = SENSOR_NOISE.velocity_std / env.observation.qdot_scale
    np.testing.assert_allclose(window[:, :4], expected, rtol=0.08)  # speeds read
    assert np.all(window[:, 4:] == 0)  # actions taken (zero here)


def test_the_bravo_has_six_of_each() -> None:
    env = DDPGConfig.scratch().on(BRAVO7).env
    std = input_noise_std(env, samples=512)
    assert std.shape == (env.observation.size_for(6),) and np.all(std[6:12] > 0)


def _sensitivity(agent: Agent, obs: torch.Tensor, noise: torch.Tensor) -> float:
    gen = torch.Generator().manual_seed(7)
    with torch.no_grad():
        nearby = obs + torch.randn(obs.shape, generator=gen) * noise
        return float((agent.actor(obs) - agent.actor(nearby)).norm(dim=1).mean())


def _train(cfg: DDPGConfig, updates: int = 50) -> tuple[Agent, dict[str, float]]:
    agent = Agent(cfg, OBS)
    rng = np.random.default_rng(3)
    info: dict[str, float] = {}
    for _ in range(updates):
        obs = rng.normal(size=(32, OBS)).astype(np.float32)
        batch = {
            "obs": obs,
            "act": rng.uniform(-1, 1, size=(32, 4)).astype(np.float32),
            "rew": rng.normal(size=(32, 1)).astype(np.float32),
            "next_obs": (obs + 0.3 * rng.normal(size=obs.shape)).astype(np.float32),
            "discount": np.full((32, 1), 0.95, np.float32),
        }
        info = agent.update(batch, 0.0)
    return agent, info


def test_the_spatial_term_makes_the_actor_answer_the_noise_less() -> None:
    base = DDPGConfig.scratch(hidden=(32, 32), batch_size=32, actor_lr=1e-3)
    plain, info = _train(base)
    assert "spatial_loss" not in info
    smooth, info = _train(dataclasses.replace(base, smooth_spatial_weight=20.0))
    assert info["spatial_loss"] > 0
    assert smooth.input_noise is not None
    noise = smooth.input_noise * 10  # ten sigmas: a difference the untrained actor shows
    obs = torch.from_numpy(np.random.default_rng(9).normal(size=(256, OBS)).astype(np.float32))
    # the same updates without the term make the actor steeper than it started; with it, flatter
    untrained = _sensitivity(Agent(base, OBS), obs, noise)
    assert _sensitivity(plain, obs, noise) > untrained > _sensitivity(smooth, obs, noise)
    assert _sensitivity(smooth, obs, noise) < 0.5 * _sensitivity(plain, obs, noise)


def test_the_temporal_term_makes_consecutive_actions_closer() -> None:
    base = DDPGConfig.scratch(hidden=(32, 32), batch_size=32, actor_lr=1e-3)
    rng = np.random.default_rng(11)
    obs = torch.from_numpy(rng.normal(size=(256, OBS)).astype(np.float32))
    step = torch.from_numpy(0.3 * rng.normal(size=(256, OBS)).astype(np.float32))

    def change(agent: Agent) -> float:
        with torch.no_grad():
            return float((agent.actor(obs) - agent.actor(obs + step)).norm(dim=1).mean())

    plain, _ = _train(base)
    smooth, info = _train(dataclasses.replace(base, smooth_temporal_weight=20.0))
    assert info["temporal_loss"] > 0
    assert change(smooth) < 0.5 * change(plain)


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf")])
@pytest.mark.parametrize("name", ["smooth_spatial_weight", "smooth_temporal_weight"])
def test_a_bad_weight_is_refused(name: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"{name} must be a finite number >= 0"):
        overrides: dict[str, Any] = {name: value}
        DDPGConfig(**overrides)


def test_sac_keeps_its_own_loss() -> None:
    with pytest.raises(ValueError, match="smoothness terms are DDPG's"):
        DDPGConfig(algorithm=Algorithm.SAC, smooth_spatial_weight=1.0)
