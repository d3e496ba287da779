"""CrossQ's critic under DDPG (`crossq_critic`): batch renormalisation that is batch
normalisation during its warm-up and clips its corrections after it, a TD target from the
online critic's value of (s', pi(s')) in the same batch (no target networks move), an
update that learns, and a run whose provenance names the critic."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny, train_quietly
from torch.nn import functional

from policy.rl.agent import Agent
from policy.rl.checkpoint import algorithm
from policy.rl.config import Algorithm, DDPGConfig
from policy.rl.networks import BatchRenorm
from policy.rl.overrides import apply_overrides


def _crossq(**overrides: object) -> DDPGConfig:
    base = dataclasses.replace(DDPGConfig.scratch(), crossq_critic=True, hidden=(32, 32))
    return dataclasses.replace(base, **overrides)  # type: ignore[arg-type]


def test_batch_renorm_is_batch_norm_in_its_warm_up_then_clips_towards_the_running_stats() -> None:
    torch.manual_seed(0)
    layer = BatchRenorm(3, warmup=10)
    x = torch.randn(256, 3) * torch.tensor([1.0, 5.0, 0.1]) + torch.tensor([2.0, -1.0, 0.0])
    # warm-up: r = 1, d = 0, so the batch's own statistics normalise it
    expected = functional.batch_norm(x, None, None, training=True, eps=1e-3)
    torch.testing.assert_close(layer(x), expected, atol=1e-5, rtol=1e-5)
    assert int(layer.batches) == 1
    # the running mean moved 1 % of the way to the batch's
    torch.testing.assert_close(layer.running_mean, 0.01 * x.mean(dim=0))
    # opened fully: a batch far from the running statistics is pulled back by d <= 5
    layer.batches.fill_(10)
    far = torch.randn(256, 3) + 100.0
    out = layer(far)
    torch.testing.assert_close(out.mean(dim=0), torch.full((3,), 5.0), atol=1e-4, rtol=0)
    # eval mode: the running statistics alone, so a row's output does not depend on its batch
    layer.eval()
    one = layer(far[:1])
    torch.testing.assert_close(layer(far)[:1], one)


def _batch(rng: np.random.Generator, n: int = 64) -> dict[str, np.ndarray]:
    act = rng.uniform(-1, 1, size=(n, 2)).astype(np.float32)
    # states the reward ignores, spread as real inputs are (a constant input has no spread
    # for the normalisation to work with)
    obs = rng.normal(size=(n, 3)).astype(np.float32)
    return {
        "obs": obs,
        "act": act,
        "rew": -((act - 0.4) ** 2).sum(axis=1, keepdims=True).astype(np.float32),
        "next_obs": rng.normal(size=(n, 3)).astype(np.float32),
        "discount": np.zeros((n, 1), np.float32),
        "expert": np.zeros((n, 2), np.float32),
    }


def test_the_update_learns_without_moving_any_target_network() -> None:
    """Reward -(sum of (a - 0.4)^2), nothing after it: the actor must go to 0.4 whatever the
    state. The target
    networks CrossQ does without stay as they were built; the state round-trips with the
    renormalisation's running statistics."""
    cfg = _crossq(batch_size=64, critic_lr=3e-3, actor_lr=3e-3, adam_beta1=0.5)
    agent = Agent(cfg, 3, 2)
    targets = [p.detach().clone() for p in agent.critics_target.parameters()]
    actor_target = [p.detach().clone() for p in agent.actor_target.parameters()]
    rng = np.random.default_rng(0)
    # over states it never saw, the mean action error (measured 0.06 after 600 updates)
    obs = np.random.default_rng(9).normal(size=(50, 3)).astype(np.float32)
    assert np.abs(agent.act(obs) - 0.4).mean() > 0.2
    for _ in range(600):
        info = agent.update(_batch(rng), 0.0)
    assert np.abs(agent.act(obs) - 0.4).mean() < 0.1
    assert np.isfinite(info["critic_loss"])
    for before, after in zip(targets, agent.critics_target.parameters(), strict=True):
        torch.testing.assert_close(before, after)
    for before, after in zip(actor_target, agent.actor_target.parameters(), strict=True):
        torch.testing.assert_close(before, after)
    renorms = [m for m in agent.critics[0].modules() if isinstance(m, BatchRenorm)]
    assert len(renorms) == 3 and int(renorms[0].batches) == 600
    assert agent.critics.training  # back in training mode after the actor's step
    other = Agent(cfg, 3, 2)
    other.load_state_dict(agent.state_dict())
    torch.testing.assert_close(
        [m for m in other.critics[0].modules() if isinstance(m, BatchRenorm)][1].running_var,
        renorms[1].running_var,
    )
    np.testing.assert_array_equal(other.act(obs), agent.act(obs))


def test_the_td_target_is_the_online_critics_value_of_the_next_state() -> None:
    """With discount 1 and a reward of 0, one critic step moves Q(s, a) towards the online
    critic's value of (s', pi(s')) computed in the same batch (train mode), not towards a
    target network's."""
    cfg = _crossq(batch_size=8, critic_lr=1e-3)
    agent = Agent(cfg, 3, 2)
    rng = np.random.default_rng(1)
    obs = torch.from_numpy(rng.normal(size=(8, 3)).astype(np.float32))
    nxt = torch.from_numpy(rng.normal(size=(8, 3)).astype(np.float32))
    act = torch.from_numpy(rng.uniform(-1, 1, size=(8, 2)).astype(np.float32))
    with torch.no_grad():
        next_act = agent.actor(nxt)
        probe = Agent(cfg, 3, 2)
        probe.load_state_dict(agent.state_dict())
        both = probe.critics[0](torch.cat([obs, nxt]), torch.cat([act, next_act]))
        q_now, q_next = both[:8], both[8:]
    expected_loss = float(((q_now - q_next) ** 2).mean())
    info = agent._crossq_critic_step(obs, act, torch.zeros(8, 1), torch.ones(8, 1), nxt, next_act)
    assert info["critic_loss"] == pytest.approx(expected_loss, rel=1e-5)


def test_the_config_names_and_refuses() -> None:
    cfg = apply_overrides(DDPGConfig.scratch(), ["crossq_critic=true", "policy_delay=3"])
    assert cfg.crossq_critic and cfg.policy_delay == 3
    assert DDPGConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert algorithm(cfg) == "TD3 with CrossQ's critic (batch renormalisation, no target networks)"
    assert (
        algorithm(_crossq())
        == "DDPG with CrossQ's critic (batch renormalisation, no target networks)"
    )
    with pytest.raises(ValueError, match="not with SAC"):
        _crossq(algorithm=Algorithm.SAC, twin_critics=True)
    with pytest.raises(ValueError, match="critic_layer_norm"):
        _crossq(critic_layer_norm=True)
    with pytest.raises(ValueError, match="crossq_warmup_updates"):
        _crossq(crossq_warmup_updates=-1)
    with pytest.raises(ValueError, match="adam_beta1"):
        _crossq(adam_beta1=1.0)


def test_a_crossq_run_trains_and_records_its_critic(tmp_path: Path) -> None:
    cfg = tiny(
        _crossq(hidden=(16, 16), batch_size=8, num_envs=2),
        eval_envelope_episodes=0,
        collector_process=False,
        eval_every=400,
        eval_episodes=2,
    )
    train_quietly(cfg, tmp_path / "run")
    meta = json.loads((tmp_path / "run" / "best_actor.json").read_text())
    assert "CrossQ's critic" in meta["provenance"]["algorithm"]
    assert meta["provenance"]["demonstrations"] == "none"
