"""The collector process: envs stepped in a child one round ahead of the learner."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny

from policy.rl.collector import CollectorProcess, EnvWorker
from policy.rl.config import DDPGConfig
from policy.rl.trainer import Trainer


def small_scratch(**overrides: object) -> DDPGConfig:
    cfg = DDPGConfig.scratch(hidden=(32, 32), batch_size=32, num_envs=2, eval_envelope_episodes=0)
    return tiny(cfg, collector_process=True, **overrides)


def test_worker_steps_every_env_and_ends_episodes() -> None:
    cfg = dataclasses.replace(
        small_scratch(), env=dataclasses.replace(small_scratch().env, episode_s=0.5)
    )
    worker = EnvWorker(cfg, from_step=0)
    rounds = [worker.round(0.0, uniform=True) for _ in range(10)]
    assert all(r.obs.shape == (2, cfg.env.observation.size) for r in rounds)
    assert all(np.all(np.abs(r.actions) <= 1.0) for r in rounds)
    # 0.5 s at 20 Hz: each env's episode ends on its 10th step, and restarts
    assert [len(r.returns) for r in rounds] == [0] * 9 + [2]
    assert np.allclose(sum(r.rewards for r in rounds), rounds[-1].returns)
    np.testing.assert_array_equal(rounds[1].obs, rounds[0].next_obs)
    with pytest.raises(RuntimeError, match="no actor"):
        worker.round(0.1, uniform=False)


def test_a_child_failure_is_raised_in_the_learner() -> None:
    with CollectorProcess(small_scratch(), from_step=0) as collector:
        collector.request([np.zeros((3, 3))], 0.1, uniform=False)  # not an actor
        with pytest.raises(RuntimeError, match="collector process failed"):
            collector.result()


def test_training_with_the_collector_is_deterministic_for_a_seed(tmp_path: Path) -> None:
    def train(seed: int, name: str) -> Trainer:
        trainer = Trainer(small_scratch(seed=seed), tmp_path / name, log=lambda _: None)
        try:  # in two sittings: the child and its episodes go on between them
            trainer.run(until_steps=200, csv_path=tmp_path / f"{name}.csv")
            trainer.run(csv_path=tmp_path / f"{name}.csv")
        finally:
            trainer.close()
        return trainer

    a, b, c = train(0, "a"), train(0, "b"), train(1, "c")
    assert a.state.env_steps == 400 and len(a.buffer) == 400 and a.agent.updates > 0
    assert a.state.episodes == 2 + 400 // 100  # 5 s episodes of 100 steps on 2 envs
    assert len((tmp_path / "a.csv").read_text().splitlines()) == 1 + 400 // 100
    for pa, pb in zip(a.agent.actor.parameters(), b.agent.actor.parameters(), strict=True):
        assert torch.equal(pa, pb)
    assert not all(
        torch.equal(pa, pc)
        for pa, pc in zip(a.agent.actor.parameters(), c.agent.actor.parameters(), strict=True)
    )


def test_the_collector_refuses_what_needs_the_envs_in_the_learner(tmp_path: Path) -> None:
    cfg = small_scratch(curriculum_start=0.5)
    with pytest.raises(ValueError, match="curriculum"):
        Trainer(cfg, tmp_path, log=lambda _: None).run()
