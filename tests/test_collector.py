"""The collector process: envs stepped in a child one round ahead of the learner."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny

from policy.controllers.ddpg import make_controller
from policy.rl.collector import CollectorProcess, EnvWorker
from policy.rl.config import DDPGConfig
from policy.rl.trainer import Trainer
from protocol.models import BRAVO7
from reach_driver.controllers import ControlState


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


@pytest.mark.parametrize("collector_process", [False, True])
def test_a_tiny_bravo_run_trains_its_six_joints_and_exports_a_bravo_actor(
    tmp_path: Path, collector_process: bool
) -> None:
    cfg = tiny(
        DDPGConfig.scratch(hidden=(32, 32), batch_size=32, num_envs=2).on(BRAVO7),
        collector_process=collector_process,
        eval_episodes=2,
    )
    assert cfg.eval_envelope_episodes == 0 and cfg.env.envelope_fraction == 0.0
    trainer = Trainer(cfg, tmp_path, log=lambda _: None)
    try:
        trainer.run()
    finally:
        trainer.close()
    assert trainer.state.env_steps == 400 and trainer.agent.updates > 0
    data = trainer.buffer.state()
    assert data["obs"].shape[1] == 42 and data["act"].shape[1] == 6
    record = trainer.evaluate_and_keep_best()
    assert "torque_g_25pct" in record  # the weak set's joint: the Bravo's base joint
    meta = json.loads((tmp_path / "best_actor.json").read_text())
    assert meta["arm"] == "bravo7" and meta["env"]["arm"] == "bravo7"
    assert meta["current_limits_mA"] == list(BRAVO7.current_limits_mA)
    controller = make_controller(tmp_path / "best_actor.npz", model=BRAVO7)
    state = ControlState(q=np.full(6, 1.5), qdot=np.zeros(6), t=0.0)
    currents = controller.act(state, np.full(6, 1.6))
    assert currents.shape == (6,)
    assert np.all(np.abs(currents) <= np.asarray(BRAVO7.current_limits_mA))
