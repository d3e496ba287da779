"""Goal relabelling: a replayed episode is exactly the episode the env would have given for
that goal (observations with their error integral, and rewards), and the trainer stores it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import tiny

from policy.rl.config import DDPGConfig
from policy.rl.env import ReachAlphaEnv, time_limited
from policy.rl.relabel import GoalRelabeller
from policy.rl.trainer import Trainer
from protocol.models import ALPHA5, BRAVO7, ArmModel

STEPS = 60


def _env_config(model: ArmModel = ALPHA5) -> DDPGConfig:
    """The `scratch` recipe's env (on `model`): noisy readings, memory channels, envelope arms
    with latency (the Alpha's), the shaped reward with every term it uses and the overshoot
    peak's (which depends on the episode's history); 3 s episodes."""
    cfg = DDPGConfig.scratch().on(model)
    reward = dataclasses.replace(cfg.env.reward, overshoot_peak_weight=50.0)
    env = dataclasses.replace(cfg.env, episode_s=STEPS / 20, reward=reward)
    return dataclasses.replace(cfg, env=env)


def _episode(
    seed: int, actions: np.ndarray, target: np.ndarray | None = None, model: ArmModel = ALPHA5
) -> tuple[ReachAlphaEnv, list[np.ndarray], list[float], GoalRelabeller]:
    """One traced episode of the given actions; `target` fixes the goal (the env's draws are
    made all the same, so the arm, its noise and its start do not change with it)."""
    env = ReachAlphaEnv(_env_config(model).env)
    timed = time_limited(env)
    relabeller = GoalRelabeller([env], goals=1, rng=np.random.default_rng(0))
    options = None if target is None else {"target": target}
    obs, _ = timed.reset(seed=seed, options=options)
    relabeller.started(0)
    observations, rewards = [obs], []
    for action in actions:
        obs, reward, _, _, info = timed.step(action)
        relabeller.stepped(0, action, info)
        observations.append(obs)
        rewards.append(float(reward))
    return env, observations, rewards, relabeller


@pytest.mark.parametrize(("seed", "model"), [(3, ALPHA5), (11, ALPHA5), (5, BRAVO7)])
def test_a_replay_for_another_goal_is_the_episode_the_env_gives_for_it(
    seed: int, model: ArmModel
) -> None:
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, size=(STEPS, model.n_joints)).astype(np.float32)
    env, obs, rewards, relabeller = _episode(seed, actions, model=model)
    trace = relabeller.traces[0]
    assert trace is not None and len(trace) == STEPS
    # for its own goal the replay is the episode itself
    own = relabeller.replay(0, trace, env.target.copy())
    np.testing.assert_array_equal(own.obs, np.array(obs[:-1]))
    np.testing.assert_array_equal(own.next_obs, np.array(obs[1:]))
    np.testing.assert_allclose(own.rewards, rewards, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(own.actions, actions)
    # for a goal the arm passed through: as if that had been the goal from the start
    goal = trace.true_q[STEPS // 2].copy()
    replay = relabeller.replay(0, trace, goal)
    _, obs_g, rewards_g, _ = _episode(seed, actions, target=goal, model=model)
    np.testing.assert_allclose(replay.obs, np.array(obs_g[:-1]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(replay.next_obs, np.array(obs_g[1:]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(replay.rewards, rewards_g, rtol=0, atol=1e-9)
    # the goal changed what the policy saw (error, integral) and what it was paid
    assert not np.allclose(replay.rewards, rewards)
    assert np.abs(replay.obs - own.obs).max() > 0.1


def test_finished_episodes_give_her_goals_replays_at_goals_the_arm_reached() -> None:
    rng = np.random.default_rng(5)
    actions = rng.uniform(-1, 1, size=(STEPS, 4)).astype(np.float32)
    env, _, _, relabeller = _episode(5, actions)
    trace = relabeller.traces[0]
    assert trace is not None
    relabeller.goals = 3
    replay = relabeller.finished(0)
    assert replay is not None and len(replay) == 3 * STEPS
    assert relabeller.traces[0] is None  # a new episode starts a new trace
    # each replay's goal (the observation's goal channels) is an angle the arm passed through
    reached = np.array(trace.true_q[1:])
    goal_channels = replay.obs[::STEPS, 8:12]
    for goal in goal_channels:
        assert np.min(np.abs(_normalised(env, reached) - goal).max(axis=1)) < 1e-6
    with pytest.raises(RuntimeError, match="before `started`"):
        relabeller.stepped(0, actions[0], {"q": env.arm.q, "qdot": env.arm.qdot})
    off = GoalRelabeller([env], goals=0, rng=np.random.default_rng(0))
    off.started(0)
    assert off.finished(0) is None
    with pytest.raises(ValueError, match="her_goals must be >= 0"):
        DDPGConfig.scratch(her_goals=-1)


def _normalised(env: ReachAlphaEnv, q: np.ndarray) -> np.ndarray:
    """Angles as the observation's goal channels hold them (float32, as stored)."""
    from policy.controllers.observation import WORKSPACE_CENTRE, WORKSPACE_HALF_RANGE

    assert env.config.observation.normalise
    return ((q - WORKSPACE_CENTRE) / WORKSPACE_HALF_RANGE).astype(np.float32)


@pytest.mark.parametrize("collector", [False, True], ids=["in-process", "collector"])
def test_the_trainer_stores_each_ended_episode_her_goals_times_more(
    tmp_path: Path, collector: bool
) -> None:
    cfg = tiny(
        DDPGConfig.scratch(hidden=(32, 32), batch_size=32, num_envs=2, eval_envelope_episodes=0),
        collector_process=collector,
        her_goals=2,
    )
    trainer = Trainer(cfg, tmp_path, log=lambda _: None)
    try:
        trainer.run()
    finally:
        trainer.close()
    # 400 env steps on 2 envs: 4 episodes of 100 steps ended, each stored 2 more times
    assert trainer.state.env_steps == 400
    assert len(trainer.buffer) == 400 + 2 * 400
    assert np.all(np.isfinite(trainer.buffer.rew[: len(trainer.buffer)]))
