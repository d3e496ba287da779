"""The Polyak-averaged actor (`actor_average_tau`): it follows the online actor by tau per actor
update, it is what checkpoints score and the run keeps, and the online actor is scored and kept
beside it, so one run measures what the averaging brings."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny

from policy.controllers.weights import ActorWeights
from policy.rl.agent import Agent
from policy.rl.config import DDPGConfig
from policy.rl.trainer import Trainer

TAU = 0.25


def _batch(rng: np.random.Generator, obs_dim: int) -> dict[str, np.ndarray]:
    return {
        "obs": rng.normal(size=(8, obs_dim)).astype(np.float32),
        "act": rng.uniform(-1, 1, size=(8, 4)).astype(np.float32),
        "rew": rng.normal(size=(8, 1)).astype(np.float32),
        "next_obs": rng.normal(size=(8, obs_dim)).astype(np.float32),
        "discount": np.full((8, 1), 0.9, np.float32),
        "expert": np.zeros((8, 4), np.float32),
    }


def _params(net: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in net.parameters()]


def test_the_average_moves_tau_of_the_way_to_the_actor_after_each_actor_update() -> None:
    cfg = dataclasses.replace(
        DDPGConfig.scratch(), hidden=(16, 16), batch_size=8, actor_average_tau=TAU
    )
    agent = Agent(cfg, 6)
    assert agent.actor_average is not None
    rng = np.random.default_rng(0)
    start = _params(agent.actor_average)
    for before, now in zip(start, _params(agent.actor), strict=True):
        torch.testing.assert_close(before, now)  # it starts as the actor
    agent.update(_batch(rng, 6), 0.0)
    after = _params(agent.actor)
    assert any(not torch.equal(a, b) for a, b in zip(start, after, strict=True))
    for avg, old, new in zip(_params(agent.actor_average), start, after, strict=True):
        torch.testing.assert_close(avg, old + TAU * (new - old))
    obs = rng.normal(size=(3, 6)).astype(np.float32)
    assert not np.allclose(agent.act_average(obs), agent.act(obs))
    # saved and restored with the agent
    other = Agent(cfg, 6)
    other.load_state_dict(agent.state_dict())
    np.testing.assert_array_equal(other.act_average(obs), agent.act_average(obs))


def test_without_averaging_there_is_no_averaged_actor() -> None:
    agent = Agent(dataclasses.replace(DDPGConfig.scratch(), hidden=(16, 16)), 6)
    assert agent.actor_average is None and "actor_average" not in agent.state_dict()
    with pytest.raises(ValueError, match="actor_average_tau is 0"):
        agent.act_average(np.zeros((1, 6), np.float32))


@pytest.mark.parametrize("tau", [-0.1, 1.0])
def test_a_rate_outside_zero_to_one_is_refused(tau: float) -> None:
    with pytest.raises(ValueError, match="actor_average_tau must be in"):
        DDPGConfig(actor_average_tau=tau)


def test_a_run_keeps_the_averaged_actor_and_the_online_one_beside_it(tmp_path: Path) -> None:
    cfg = tiny(
        DDPGConfig.scratch(hidden=(16, 16), batch_size=8, num_envs=2),
        eval_envelope_episodes=0,
        collector_process=False,
        eval_every=400,  # one checkpoint, at the end: the agent's weights now
        eval_episodes=2,
        actor_average_tau=TAU,
    )
    trainer = Trainer(cfg, tmp_path / "run", log=lambda _: None)
    try:
        trainer.run()
    finally:
        trainer.close()
    (record,) = [json.loads(line) for line in (tmp_path / "run" / "eval.jsonl").open()]
    assert record["env_steps"] == 400 and record["best"] and record["online"]["best"]
    assert trainer.state.best_score == record["score"]
    assert trainer.state.best_online_score == record["online"]["score"]
    # each file holds the actor its record scored: the averaged one and the online one
    kept = ActorWeights.load(tmp_path / "run" / "best_actor.npz")
    online = ActorWeights.load(tmp_path / "run" / "best_online_actor.npz")
    assert kept.metadata["eval"]["score"] == record["score"]
    assert online.metadata["eval"]["score"] == record["online"]["score"]
    obs = np.random.default_rng(1).normal(size=(4, trainer.obs_dim)).astype(np.float32)
    np.testing.assert_allclose(kept.forward(obs), trainer.agent.act_average(obs), atol=1e-5)
    np.testing.assert_allclose(online.forward(obs), trainer.agent.act(obs), atol=1e-5)
    assert not np.allclose(kept.forward(obs), online.forward(obs), atol=1e-3)
