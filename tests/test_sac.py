"""SAC (`algorithm=sac`): the Gaussian actor's density, the collector's numpy sampler against
torch's, an update that learns and steers its temperature, and a run whose kept actor is the
mean action in the shipped format."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import cast

import numpy as np
import pytest
import torch
from conftest import tiny, train_quietly

from policy.controllers.weights import LEAKY_RELU_SLOPE, ActorWeights
from policy.rl.agent import Agent
from policy.rl.checkpoint import algorithm
from policy.rl.collector import EnvWorker
from policy.rl.config import Algorithm, DDPGConfig
from policy.rl.exploration import GaussianSampler
from policy.rl.networks import GaussianActor
from policy.rl.overrides import apply_overrides


def _sac(**overrides: object) -> DDPGConfig:
    base = dataclasses.replace(
        DDPGConfig.scratch(), algorithm=Algorithm.SAC, twin_critics=True, hidden=(32, 32)
    )
    return dataclasses.replace(base, **overrides)  # type: ignore[arg-type]


def test_the_log_density_is_the_tanh_squashed_gaussian_one() -> None:
    torch.manual_seed(0)
    actor = GaussianActor(5, 3, (16, 16))
    obs = torch.randn(64, 5)
    action, log_prob = actor.sample(obs, torch.Generator().manual_seed(1))
    features = actor.net[:4](obs)
    mean = actor.net[4](features)
    from policy.rl.networks import squash_log_std

    std = squash_log_std(actor.log_std(features)).exp()
    dist = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mean, std), [torch.distributions.TanhTransform()]
    )
    # clamp away from +-1, where torch's inverse tanh loses the digits our form keeps
    inside = action.abs().max(dim=1).values < 0.999
    expected = dist.log_prob(action).sum(dim=1, keepdim=True)
    torch.testing.assert_close(log_prob[inside], expected[inside], atol=1e-3, rtol=1e-4)
    # the deterministic action, which ships, is tanh of the mean
    torch.testing.assert_close(actor(obs), torch.tanh(mean))


class _FixedNormal:
    """Stands in for a numpy Generator: the noise the torch side drew."""

    def __init__(self, noise: np.ndarray) -> None:
        self.noise = noise

    def standard_normal(self, shape: tuple[int, ...]) -> np.ndarray:
        assert tuple(shape) == self.noise.shape
        return self.noise


def test_the_collectors_numpy_sampler_draws_what_the_torch_actor_draws() -> None:
    torch.manual_seed(3)
    actor = GaussianActor(7, 4, (16, 8))
    obs = torch.randn(10, 7)
    gen = torch.Generator().manual_seed(5)
    noise = torch.randn(10, 4, generator=torch.Generator().manual_seed(5))
    action, _ = actor.sample(obs, gen)
    layers = [*actor.linears(), actor.log_std]
    arrays = [t.detach().numpy() for layer in layers for t in (layer.weight, layer.bias)]
    rng = cast(np.random.Generator, _FixedNormal(noise.numpy().astype(np.float64)))
    sampled = GaussianSampler(arrays, LEAKY_RELU_SLOPE, rng).sample(obs.numpy())
    np.testing.assert_allclose(sampled, action.detach().numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="4 layers"):
        GaussianSampler(arrays[:6], LEAKY_RELU_SLOPE, np.random.default_rng(0))


def test_sac_learns_a_one_step_task_and_its_temperature_follows_the_entropy() -> None:
    """Reward -(sum of (a - 0.4)^2), nothing after it: the mean action must go to 0.4, and
    with a target entropy far below the start the temperature must fall."""
    cfg = _sac(
        batch_size=64, sac_target_entropy=-8.0, sac_alpha_lr=1e-2, critic_lr=3e-3, actor_lr=3e-3
    )
    agent = Agent(cfg, 3, 2)
    rng = np.random.default_rng(0)
    obs = np.ones((64, 3), np.float32)
    alpha0 = float(agent.log_alpha.detach().exp())
    for _ in range(600):
        act = rng.uniform(-1, 1, size=(64, 2)).astype(np.float32)
        batch = {
            "obs": obs,
            "act": act,
            "rew": -((act - 0.4) ** 2).sum(axis=1, keepdims=True).astype(np.float32),
            "next_obs": obs,
            "discount": np.zeros((64, 1), np.float32),
            "expert": np.zeros((64, 2), np.float32),
        }
        info = agent.update(batch, 0.0)
    np.testing.assert_allclose(agent.act(obs[:1]), [[0.4, 0.4]], atol=0.08)
    assert info["alpha"] < 0.5 * alpha0
    # the state round-trips, temperature included
    other = Agent(cfg, 3, 2)
    other.load_state_dict(agent.state_dict())
    assert float(other.log_alpha.detach()) == float(agent.log_alpha.detach())
    np.testing.assert_array_equal(other.act(obs[:1]), agent.act(obs[:1]))


def test_the_config_names_and_refuses() -> None:
    cfg = apply_overrides(DDPGConfig.scratch(), ["algorithm=sac", "twin_critics=true"])
    assert cfg.algorithm is Algorithm.SAC
    assert DDPGConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert algorithm(cfg).startswith("SAC (twin critics")
    assert algorithm(DDPGConfig.scratch()) == "DDPG"
    with pytest.raises(SystemExit, match="algorithm must be one of ddpg, sac, got 'sak'"):
        apply_overrides(DDPGConfig.scratch(), ["algorithm=sak"])
    with pytest.raises(ValueError, match="target_noise is TD3's"):
        _sac(target_noise=0.1)
    with pytest.raises(ValueError, match="reward alone"):
        _sac(bc_weight=1.0)


def test_the_collector_explores_by_the_actors_samples(tmp_path: Path) -> None:
    cfg = tiny(_sac(num_envs=3))
    worker = EnvWorker(cfg, 0)
    agent = Agent(cfg, worker.obs.shape[1], 4)
    layers = [*agent.actor.linears(), agent.gaussian_actor().log_std]
    worker.set_actor([t.detach().numpy() for lay in layers for t in (lay.weight, lay.bias)])
    assert worker.actor is not None and worker.sampler is not None
    obs = worker.obs.copy()
    got = worker.round(epsilon=0.0, uniform=False)
    np.testing.assert_array_equal(got.obs, obs)
    mean = worker.actor.forward(obs)
    assert not np.allclose(got.actions, mean, atol=1e-3)  # eps 0 would give the mean with OU
    assert np.all(np.abs(got.actions) < 1.0)


def test_a_sac_run_keeps_the_mean_action_in_the_shipped_format(tmp_path: Path) -> None:
    cfg = tiny(
        _sac(hidden=(16, 16), batch_size=8, num_envs=2),
        eval_envelope_episodes=0,
        collector_process=False,
        eval_every=400,  # one checkpoint, at the end: the agent's weights now
        eval_episodes=2,
    )
    trainer = train_quietly(cfg, tmp_path / "run")
    kept = ActorWeights.load(tmp_path / "run" / "best_actor.npz")
    obs = np.random.default_rng(1).normal(size=(4, trainer.obs_dim)).astype(np.float32)
    np.testing.assert_allclose(kept.forward(obs), trainer.agent.act(obs), atol=1e-5)
    rows = (tmp_path / "run" / "train.csv").read_text().splitlines()
    header, last = rows[0].split(","), rows[-1].split(",")
    assert last[header.index("epsilon")] == "nan"  # SAC explores by its own samples
    meta = json.loads((tmp_path / "run" / "best_actor.json").read_text())
    assert meta["provenance"]["algorithm"].startswith("SAC")
    assert meta["provenance"]["demonstrations"] == "none"
