"""n-step returns (`n_step`): each stored transition sums n rewards and bootstraps gamma^n later."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny

from policy.rl.agent import Agent
from policy.rl.config import DDPGConfig
from policy.rl.nstep import NStepReturns
from policy.rl.trainer import Trainer

GAMMA = 0.9


def _push(acc: NStepReturns, t: int, done: bool = False, term: bool = False):  # type: ignore[no-untyped-def]
    """Step t of one env: obs t, action t, reward 10^t (each sum is readable digit by digit),
    next obs t + 1."""
    return acc.push(
        np.array([[t]], np.float32),
        np.array([[t]], np.float32),
        np.array([10.0**t]),
        np.array([[t + 1]], np.float32),
        np.array([float(term)]),
        np.array([done]),
    )


def test_a_transition_sums_n_rewards_and_bootstraps_from_n_steps_later() -> None:
    acc = NStepReturns(1, 3, GAMMA)
    assert len(_push(acc, 0).obs) == 0 and len(_push(acc, 1).obs) == 0  # not complete yet
    out = _push(acc, 2)
    assert out.obs[:, 0].tolist() == [0] and out.next_obs[:, 0].tolist() == [3]
    assert out.rewards[0] == pytest.approx(1 + GAMMA * 10 + GAMMA**2 * 100)
    assert out.discounts[0] == pytest.approx(GAMMA**3)
    out = _push(acc, 3)
    assert out.obs[:, 0].tolist() == [1] and out.next_obs[:, 0].tolist() == [4]
    assert out.rewards[0] == pytest.approx(10 + GAMMA * 100 + GAMMA**2 * 1000)


def test_the_end_of_an_episode_stores_every_open_step_with_fewer_rewards() -> None:
    acc = NStepReturns(1, 3, GAMMA)
    for t in range(3):
        _push(acc, t)
    out = _push(acc, 3, done=True)  # truncated: the last states still bootstrap
    assert out.obs[:, 0].tolist() == [1, 2, 3]
    assert np.all(out.next_obs[:, 0] == 4)
    np.testing.assert_allclose(
        out.rewards, [10 + GAMMA * 100 + GAMMA**2 * 1000, 100 + GAMMA * 1000, 1000]
    )
    np.testing.assert_allclose(out.discounts, [GAMMA**3, GAMMA**2, GAMMA])
    assert len(_push(acc, 10).obs) == 0  # a new episode starts empty


def test_a_terminated_episode_does_not_bootstrap_and_one_step_passes_through() -> None:
    acc = NStepReturns(1, 3, GAMMA)
    _push(acc, 0)
    out = _push(acc, 1, done=True, term=True)
    np.testing.assert_allclose(out.rewards, [1 + GAMMA * 10, 10])
    assert out.discounts.tolist() == [0.0, 0.0]
    one = NStepReturns(2, 1, GAMMA)
    obs = np.arange(4, dtype=np.float32).reshape(2, 2)
    out = one.push(obs, obs, np.array([1.0, 2.0]), obs + 1, np.array([0.0, 1.0]), np.ones(2))
    assert out.obs is obs and out.rewards.tolist() == [1.0, 2.0]
    np.testing.assert_allclose(out.discounts, [GAMMA, 0.0])


def test_the_critic_target_uses_the_stored_discount() -> None:
    cfg = dataclasses.replace(DDPGConfig.scratch(), hidden=(16, 16), batch_size=8)
    agent = Agent(cfg, 6)
    rng = np.random.default_rng(0)
    batch = {
        "obs": rng.normal(size=(8, 6)).astype(np.float32),
        "act": rng.uniform(-1, 1, size=(8, 4)).astype(np.float32),
        "rew": rng.normal(size=(8, 1)).astype(np.float32),
        "next_obs": rng.normal(size=(8, 6)).astype(np.float32),
        "discount": np.full((8, 1), 0.5, np.float32),
        "expert": np.zeros((8, 4), np.float32),
    }
    with torch.no_grad():
        next_obs = torch.from_numpy(batch["next_obs"])
        q_next = agent.critics_target[0](next_obs, agent.actor_target(next_obs))
        target = torch.from_numpy(batch["rew"]) + 0.5 * q_next
        q = agent.critics[0](torch.from_numpy(batch["obs"]), torch.from_numpy(batch["act"]))
        want = float(((q - target) ** 2).mean())
    assert agent.update(batch, 0.0)["critic_loss"] == pytest.approx(want, rel=1e-5)


@pytest.mark.parametrize("collector", [False, True], ids=["in-process", "collector"])
def test_the_trainer_stores_the_n_step_returns_of_the_steps_it_took(
    tmp_path: Path, collector: bool
) -> None:
    """Two runs of one seed take the same (uniform random) steps; the n = 3 run's buffer must
    hold exactly the 3-step returns of the n = 1 run's transitions, episode ends included."""

    def buffer(n_step: int) -> dict[str, np.ndarray]:
        cfg = tiny(
            DDPGConfig.scratch(hidden=(16, 16), batch_size=8, num_envs=2),
            eval_envelope_episodes=0,
            collector_process=collector,
            learning_starts=10**6,  # uniform actions all run: the same steps for both
            n_step=n_step,
            gamma=GAMMA,
        )
        trainer = Trainer(cfg, tmp_path / f"n{n_step}", log=lambda _: None)
        try:
            trainer.run()
        finally:
            trainer.close()
        size = len(trainer.buffer)
        return {k: v[:size] for k, v in trainer.buffer.state().items() if k != "meta"}

    one, three = buffer(1), buffer(3)
    # 400 steps on 2 envs: two 100-step episodes each, all ended, so every step is stored
    assert len(one["obs"]) == len(three["obs"]) == 400
    np.testing.assert_allclose(one["discount"], GAMMA)
    per_env = [np.arange(i, 400, 2) for i in range(2)]  # the one-step buffer, env i's steps
    row_of = {one["obs"][r].tobytes(): (i, k) for i in range(2) for k, r in enumerate(per_env[i])}
    seen = set()
    for r in range(400):
        i, k = row_of[three["obs"][r].tobytes()]
        seen.add((i, k))
        m = min(3, 100 - k % 100)  # rewards left before the episode ends
        rows = per_env[i][k : k + m]
        np.testing.assert_array_equal(three["act"][r], one["act"][rows[0]])
        want = sum(GAMMA**j * one["rew"][row, 0] for j, row in enumerate(rows))
        assert three["rew"][r, 0] == pytest.approx(want, rel=1e-5)
        np.testing.assert_array_equal(three["next_obs"][r], one["next_obs"][rows[-1]])
        assert three["discount"][r, 0] == pytest.approx(GAMMA**m)
    assert len(seen) == 400


def test_n_step_refuses_what_it_would_store_as_one_step() -> None:
    with pytest.raises(ValueError, match="her_goals"):
        DDPGConfig.scratch(n_step=3, her_goals=2)
    with pytest.raises(ValueError, match="n_step"):
        DDPGConfig.scratch(n_step=0)


def test_a_buffer_saved_with_terminal_flags_loads_as_one_step_discounts() -> None:
    from policy.rl.replay import ReplayBuffer

    buf = ReplayBuffer(4, 2, 1)
    ones = np.ones((3, 2))
    buf.add(ones, ones[:, :1], np.ones(3), ones, np.array([GAMMA, 0.0, GAMMA]), ones[:, :1])
    saved = buf.state()
    older = {k: v for k, v in saved.items() if k != "discount"}
    older["term"] = (saved["discount"] == 0).astype(np.float32)  # what runs saved before
    loaded = ReplayBuffer(4, 2, 1)
    loaded.load(older, gamma=GAMMA)
    np.testing.assert_allclose(loaded.discount[:3, 0], [GAMMA, 0.0, GAMMA])
