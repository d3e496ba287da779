"""The critic's optional LayerNorm: it normalises, it trains, and the shipped actor is unchanged."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from policy.rl.agent import Agent
from policy.rl.config import DDPGConfig
from policy.rl.networks import Critic


def test_layer_norm_makes_q_blind_to_the_first_layers_scale() -> None:
    torch.manual_seed(0)
    obs, act = torch.randn(8, 20), torch.rand(8, 4) * 2 - 1
    for layer_norm, invariant in ((True, True), (False, False)):
        critic = Critic(20, 4, (32, 32), layer_norm=layer_norm)
        before = critic(obs, act).detach()
        first = critic.net[0]
        assert isinstance(first, torch.nn.Linear)
        with torch.no_grad():
            first.weight.mul_(10.0)
            first.bias.mul_(10.0)
        after = critic(obs, act).detach()
        assert torch.allclose(before, after, atol=1e-4) is invariant


def test_an_agent_with_layer_norm_critics_updates_and_keeps_the_actor_format() -> None:
    cfg = dataclasses.replace(
        DDPGConfig.scratch(), critic_layer_norm=True, batch_size=16, hidden=(32, 32)
    )
    agent = Agent(cfg, 20)
    critic = agent.critics[0]
    assert isinstance(critic, Critic)
    assert any(isinstance(m, torch.nn.LayerNorm) for m in critic.net)
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in agent.actor.net)
    assert len(agent.actor.linears()) == 3  # what the weights file stores
    rng = np.random.default_rng(0)
    batch = {
        "obs": rng.normal(size=(16, 20)).astype(np.float32),
        "act": rng.uniform(-1, 1, size=(16, 4)).astype(np.float32),
        "rew": rng.normal(size=(16, 1)).astype(np.float32),
        "next_obs": rng.normal(size=(16, 20)).astype(np.float32),
        "discount": np.full((16, 1), 0.99, np.float32),
        "expert": np.full((16, 4), np.nan, np.float32),
    }
    losses = [agent.update(batch, 0.0)["critic_loss"] for _ in range(30)]
    assert np.isfinite(losses).all() and losses[-1] < losses[0]
