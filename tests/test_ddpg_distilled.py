"""The training side (DDPG / TD3 / TD3+BC agent, training loop, checkpoints, provenance) and the
distilled controller it made (`ddpg-distilled`: a numpy actor + reference integral)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import tiny

from policy.controllers.ddpg_distilled import make_controller
from policy.controllers.weights import DISTILLED_WEIGHTS, NONE, ActorWeights, TrainingStage
from policy.rl.batched import evaluate_batched as evaluate
from policy.rl.checkpoint import actor_arrays, load_actor_npz, save_actor_npz
from policy.rl.config import DDPGConfig
from policy.rl.env import EnvConfig, ReachAlphaEnv
from policy.rl.expert import PDExpert
from policy.rl.exploration import OUNoise
from policy.rl.networks import Actor
from policy.rl.replay import ReplayBuffer
from policy.rl.run_dir import ship
from policy.rl.trainer import Trainer, make_expert
from reach_driver.controllers import ControlState

ROOT = Path(__file__).resolve().parents[1]


def test_paper_hyperparameters() -> None:
    cfg = DDPGConfig.paper()
    assert cfg.hidden == (400, 300)
    assert (cfg.actor_lr, cfg.critic_lr, cfg.lr_decay, cfg.lr_decay_every) == (
        1e-4,
        1e-3,
        0.96,
        100_000,
    )
    assert (cfg.batch_size, cfg.tau, cfg.gamma) == (64, 0.001, 0.99)
    assert (cfg.eps_start, cfg.eps_end) == (1.0, 0.1)
    assert cfg.env.reward.sigma == 0.018 and cfg.env.reward.out_of_bounds == -10.0
    assert not cfg.twin_critics and cfg.bc_weight == 0 and cfg.demo_episodes == 0
    actor = Actor(12, 4, cfg.hidden)
    kinds = [type(m).__name__ for m in actor.net]
    assert kinds == ["Linear", "LeakyReLU", "Linear", "LeakyReLU", "Linear", "Tanh"]


def test_numpy_forward_equals_torch_actor(tmp_path: Path) -> None:
    torch.manual_seed(3)
    cfg = DDPGConfig.ours()
    actor = Actor(cfg.env.observation.size, 4, cfg.hidden)
    save_actor_npz(tmp_path / "a.npz", actor, cfg)
    weights = ActorWeights.load(tmp_path / "a.npz")
    obs = np.random.default_rng(0).uniform(-3, 3, size=(256, cfg.env.observation.size))
    with torch.no_grad():
        expected = actor(torch.from_numpy(obs.astype(np.float32))).numpy()
    np.testing.assert_allclose(weights.forward(obs), expected, atol=2e-6)
    np.testing.assert_allclose(weights.forward(obs[0]), expected[0], atol=2e-6)


def test_saved_weights_round_trip_bit_for_bit(tmp_path: Path) -> None:
    """policy.controllers.weights is the one owner of the format: what training saves, the
    controller and the trainer's `init_actor` load exactly."""
    torch.manual_seed(5)
    cfg = DDPGConfig.ours()
    actor = Actor(cfg.env.observation.size, 4, cfg.hidden)
    save_actor_npz(tmp_path / "a.npz", actor, cfg, extra={"note": np.float32(1.5)})
    loaded = ActorWeights.load(tmp_path / "a.npz")
    arrays = actor_arrays(actor)
    assert len(loaded.weights) == len(loaded.biases) == 3
    for i, (w, b) in enumerate(zip(loaded.weights, loaded.biases, strict=True)):
        np.testing.assert_array_equal(w, arrays[f"W{i}"])
        np.testing.assert_array_equal(b, arrays[f"b{i}"])
    assert loaded.observation == cfg.env.observation and loaded.metadata["note"] == 1.5
    assert DDPGConfig.from_dict(loaded.metadata["config"]) == cfg
    obs = np.random.default_rng(2).uniform(-2, 2, size=(64, cfg.env.observation.size))
    direct = ActorWeights(
        tuple(arrays[f"W{i}"] for i in range(3)),
        tuple(arrays[f"b{i}"] for i in range(3)),
        loaded.leaky_slope,
        loaded.observation,
        loaded.current_limits_mA,
        {},
    )
    np.testing.assert_array_equal(loaded.forward(obs), direct.forward(obs))
    again = Actor(cfg.env.observation.size, 4, cfg.hidden)
    load_actor_npz(again, tmp_path / "a.npz")
    x = torch.from_numpy(obs.astype(np.float32))
    with torch.no_grad():
        assert torch.equal(again(x), actor(x))
    for pa, pb in zip(actor.parameters(), again.parameters(), strict=True):
        assert torch.equal(pa, pb)


def test_controller_outputs_currents_and_rejects_bad_input(tmp_path: Path) -> None:
    torch.manual_seed(0)
    cfg = DDPGConfig.ours()
    actor = Actor(cfg.env.observation.size, 4, cfg.hidden)
    with torch.no_grad():
        actor.linears()[-1].bias.fill_(10.0)  # saturate: every output +1
    save_actor_npz(tmp_path / "a.npz", actor, cfg)
    ctrl = make_controller(tmp_path / "a.npz")
    ctrl.reset()
    state = ControlState(q=np.full(4, 1.5), qdot=np.zeros(4), t=0.0)
    np.testing.assert_allclose(ctrl.act(state, np.full(4, 1.6)), [600, 600, 600, 300], rtol=1e-6)
    with pytest.raises(ValueError, match="target"):
        ctrl.act(state, np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="finite"):
        ctrl.act(ControlState(q=np.array([np.nan, 1, 1, 1]), qdot=np.zeros(4), t=0.0), np.ones(4))
    with pytest.raises(FileNotFoundError):
        make_controller(tmp_path / "missing.npz")
    (tmp_path / "a.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="format"):
        make_controller(tmp_path / "a.npz")


def test_shipped_weights_load_with_their_metadata() -> None:
    ctrl = make_controller()
    meta = json.loads(DISTILLED_WEIGHTS.with_suffix(".json").read_text())
    for key in ("command", "seed", "config", "training_time_s", "eval"):
        assert key in meta, key
    assert DISTILLED_WEIGHTS.stat().st_size < 5_000_000
    state = ControlState(q=np.array([1.0, 1.0, 1.0, 1.0]), qdot=np.zeros(4), t=0.0)
    out = ctrl.act(state, np.array([2.0, 2.0, 2.0, 2.0]))
    assert out.shape == (4,) and np.all(np.abs(out) <= ctrl.current_limits_mA + 1e-9)


@pytest.mark.slow
def test_shipped_weights_drive_the_arm_to_target() -> None:
    """Closed loop on the MuJoCo arm at 20 Hz, the controller reading noisy sensors."""
    ctrl = make_controller()
    env = ReachAlphaEnv(EnvConfig(sensor_noise=True))
    for start, target in [
        ([1.0, 1.0, 2.5, 0.8], [4.5, 2.2, 1.0, 2.4]),
        ([5.0, 2.5, 1.0, 2.0], [2.0, 0.8, 2.6, 0.7]),
    ]:
        env.reset(seed=0, options={"start": start, "target": target})
        for k in range(env.config.steps_per_episode):
            q, qdot = env.last_reading
            reading = ControlState(q=q, qdot=qdot, t=k * env.control_dt)
            currents = ctrl.act(reading, env.target)
            env.step(currents / ctrl.current_limits_mA)
        assert np.all(np.abs(env.arm.q - np.array(target)) < 0.02), env.arm.q


def test_ou_noise_and_schedules(tmp_path: Path) -> None:
    noise = OUNoise((2, 4), 0.15, 0.2, np.random.default_rng(0))
    samples = np.array([noise.sample() for _ in range(2000)])
    assert abs(np.corrcoef(samples[:-1, 0, 0], samples[1:, 0, 0])[0, 1] - 0.85) < 0.05
    noise.reset(0)
    assert np.all(noise.state[0] == 0) and np.any(noise.state[1] != 0)
    cfg = tiny(DDPGConfig.paper(), total_steps=1000)
    trainer = Trainer(cfg, tmp_path)
    assert trainer.epsilon() == 1.0
    trainer.state.env_steps = 500
    assert trainer.epsilon() == pytest.approx(0.55)
    trainer.state.env_steps = 5000
    assert trainer.epsilon() == pytest.approx(0.1)
    trainer.agent.set_learning_rates(250_000)
    assert trainer.agent.actor_opt.param_groups[0]["lr"] == pytest.approx(1e-4 * 0.96**2)


def test_replay_buffer_wraps_and_round_trips() -> None:
    buf = ReplayBuffer(5, 3, 2)
    for k in range(3):
        n = 2
        buf.add(
            np.full((n, 3), k),
            np.full((n, 2), k),
            np.full(n, k),
            np.full((n, 3), k),
            np.zeros(n),
            np.zeros((n, 2)),
        )
    assert len(buf) == 5 and buf.pos == 1
    assert buf.rew[:, 0].tolist() == [2, 0, 1, 1, 2]  # the oldest transition was replaced
    other = ReplayBuffer(5, 3, 2)
    other.load(buf.state(), gamma=0.99)
    np.testing.assert_array_equal(other.obs, buf.obs)
    assert other.pos == buf.pos and len(other) == 5
    with pytest.raises(ValueError, match="capacity"):
        ReplayBuffer(6, 3, 2).load(buf.state(), gamma=0.99)


def _train(config: DDPGConfig, run_dir: Path) -> Trainer:
    expert = PDExpert() if config.bc_weight > 0 else None
    trainer = Trainer(config, run_dir, expert=expert, log=lambda _: None)
    trainer.run()
    return trainer


@pytest.mark.parametrize("preset", ["paper", "ours"])
def test_training_runs_and_is_deterministic_for_a_seed(tmp_path: Path, preset: str) -> None:
    overrides: dict[str, object] = {}
    if preset == "ours":
        overrides = dict(num_envs=2, demo_episodes=1, batch_size=64, eval_episodes=2)
    cfg = tiny(DDPGConfig.preset(preset), **overrides)
    a = _train(cfg, tmp_path / "a")
    b = _train(cfg, tmp_path / "b")
    c = _train(dataclasses.replace(cfg, seed=1), tmp_path / "c")
    assert a.state.env_steps == cfg.total_steps and a.agent.updates > 0
    for pa, pb in zip(a.agent.actor.parameters(), b.agent.actor.parameters(), strict=True):
        assert torch.equal(pa, pb)
    assert not all(
        torch.equal(pa, pc)
        for pa, pc in zip(a.agent.actor.parameters(), c.agent.actor.parameters(), strict=True)
    )


def test_checkpoint_resume_and_csv(tmp_path: Path) -> None:
    cfg = tiny(DDPGConfig.paper(), total_steps=300)
    trainer = Trainer(cfg, tmp_path, log=lambda _: None)
    trainer.run(until_steps=200, csv_path=tmp_path / "train.csv")
    trainer.evaluate_and_keep_best()
    trainer.save()
    resumed = Trainer(cfg, tmp_path, log=lambda _: None)
    resumed.load()
    assert resumed.state.env_steps == 200 and len(resumed.buffer) == len(trainer.buffer)
    for pa, pb in zip(
        trainer.agent.critics.parameters(), resumed.agent.critics.parameters(), strict=True
    ):
        assert torch.equal(pa, pb)
    assert resumed.agent.updates == trainer.agent.updates
    resumed.run(csv_path=tmp_path / "train.csv")
    assert resumed.state.env_steps == 300
    rows = (tmp_path / "train.csv").read_text().splitlines()
    assert rows[0].startswith("env_steps,episodes") and len(rows) >= 3  # 100-step episodes
    assert (tmp_path / "best_actor.npz").exists() and (tmp_path / "eval.jsonl").exists()
    different = dataclasses.replace(cfg, batch_size=32)
    with pytest.raises(ValueError, match="different configuration"):
        Trainer(different, tmp_path, log=lambda _: None).load()


def test_expert_needed_for_demonstrations(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="expert"):
        Trainer(tiny(DDPGConfig.ours()), tmp_path)


def test_evaluate_scores_the_expert_as_reaching() -> None:
    result = evaluate(None, EnvConfig(episode_s=10.0), episodes=3, seed=5, expert=PDExpert())
    assert result.reached_fraction == 1.0
    assert result.final_error < 0.02 and result.overshoot_pct < 2.0
    assert 1.0 <= result.rmse_floor_ratio < 1.3


def test_train_cli_help_and_bad_override(tmp_path: Path) -> None:
    py = sys.executable
    out = subprocess.run(
        [py, str(ROOT / "tools" / "train.py"), "--help"], capture_output=True, text=True, check=True
    )
    assert "--resume" in out.stdout and "checkpoint" in out.stdout
    bad = subprocess.run(
        [
            py,
            str(ROOT / "tools" / "train.py"),
            "--run",
            str(tmp_path / "r"),
            "--set",
            "no_such_key=1",
        ],
        capture_output=True,
        text=True,
    )
    assert bad.returncode != 0 and "unknown key" in bad.stderr
    missing = subprocess.run(
        [py, str(ROOT / "tools" / "train.py"), "--run", str(tmp_path / "none"), "--resume"],
        capture_output=True,
        text=True,
    )
    assert missing.returncode != 0 and "no checkpoint" in missing.stderr


def test_ship_copies_best_actor_with_provenance(tmp_path: Path) -> None:
    run = tmp_path / "run"
    cfg = tiny(DDPGConfig.paper(), total_steps=200)
    trainer = Trainer(cfg, run, log=lambda _: None)
    trainer.run()
    trainer.evaluate_and_keep_best()
    (run / "commands.txt").write_text("tools/train.py --config paper --run run\n")
    dest = ship(run, tmp_path / "w" / "actor.npz")
    meta = json.loads(dest.with_suffix(".json").read_text())
    assert meta["command"] == "tools/train.py --config paper --run run"
    assert meta["seed"] == 0 and meta["training_env_steps"] == 200
    assert meta["eval"]["env_steps"] == 200
    weights = ActorWeights.load(dest)
    assert weights.observation == cfg.env.observation
    with pytest.raises(SystemExit, match="does not exist"):
        ship(tmp_path / "empty", tmp_path / "w2" / "a.npz")


def test_evaluate_cli_scores_the_expert() -> None:
    out = subprocess.run(
        [
            sys.executable,
            str(ROOT / "tools" / "train.py"),
            "--evaluate",
            "expert",
            "--episodes",
            "2",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    result = json.loads(out.stdout)
    assert result["nominal"]["reached_fraction"] == 1.0
    assert result["torque_e_25pct"]["reached_fraction"] == 1.0


def test_init_actor_starts_from_shipped_weights(tmp_path: Path) -> None:
    cfg = tiny(
        DDPGConfig.ours(),
        num_envs=2,
        demo_episodes=0,
        eval_episodes=2,
        init_actor=str(DISTILLED_WEIGHTS),
    )
    trainer = Trainer(cfg, tmp_path, expert=make_expert(cfg), log=lambda _: None)
    shipped = ActorWeights.load(DISTILLED_WEIGHTS)
    obs = np.random.default_rng(1).uniform(-1, 1, size=(32, cfg.env.observation.size))
    np.testing.assert_allclose(
        trainer.agent.act(obs.astype(np.float32)), shipped.forward(obs), atol=1e-5
    )
    with torch.no_grad():
        target = trainer.agent.actor_target(torch.from_numpy(obs.astype(np.float32))).numpy()
    np.testing.assert_allclose(target, shipped.forward(obs), atol=1e-5)
    wrong = dataclasses.replace(cfg, hidden=(64, 64))
    with pytest.raises(ValueError, match="does not fit"):
        Trainer(wrong, tmp_path / "w", expert=make_expert(wrong), log=lambda _: None)


def test_make_expert_follows_the_config() -> None:
    assert make_expert(DDPGConfig.paper()) is None
    plain = make_expert(DDPGConfig.ours())
    assert isinstance(plain, PDExpert) and plain.energy_lambda is None
    saver = make_expert(DDPGConfig.ours(expert_energy_lambda=6.0))
    assert isinstance(saver, PDExpert) and saver.energy_lambda == 6.0


def test_score_counts_energy_only_when_asked() -> None:
    result = evaluate(None, EnvConfig(episode_s=5.0), episodes=2, seed=5, expert=PDExpert())
    assert result.energy_j > 0
    assert result.score(0.02) == pytest.approx(result.score() - 0.02 * result.energy_j)


def test_a_wider_training_workspace_keeps_the_evaluation_episodes(tmp_path: Path) -> None:
    from policy.controllers.observation import WORKSPACE_HIGH
    from policy.rl.batched import eval_envs

    wide_env = EnvConfig(episode_s=1.0, workspace_high=(5.8, 2.9, 2.9, 5.8))
    narrow = eval_envs(wide_env, 2)
    assert narrow[0].config.workspace_high is None  # scores stay comparable across runs
    assert np.allclose(narrow[0].workspace_high, WORKSPACE_HIGH)
    own = eval_envs(wide_env, 2, training_workspace=True)
    assert own[0].workspace_high[3] == pytest.approx(5.8)
    cfg = tiny(DDPGConfig.paper(), env=wide_env, eval_episodes=4, total_steps=200)
    trainer = Trainer(cfg, tmp_path, log=lambda _: None)
    assert len(trainer.eval_wide) == 4
    record = trainer.evaluate_and_keep_best()
    assert set(record["training_workspace"]) >= {"reached_fraction", "overshoot_pct"}
    plain = Trainer(tiny(DDPGConfig.paper()), tmp_path / "plain", log=lambda _: None)
    assert plain.eval_wide == [] and "training_workspace" not in plain.evaluate_and_keep_best()


def test_reference_integral_shifts_the_shown_target_near_the_goal_only() -> None:
    from policy.controllers.ddpg_distilled import ReferenceIntegral, make_pure_controller

    ctrl = make_controller()  # shipped: actor + reference integral (gain 1/s, band 0.02 rad)
    assert ctrl.integral == ReferenceIntegral()
    target = np.array([3.0, 1.5, 1.5, 1.5])
    error = np.array([0.005, -0.005, 0.05, 0.0])  # C is outside the band
    state = ControlState(q=target - error, qdot=np.zeros(4), t=0.0)
    shown = [
        ctrl.shown_target(ControlState(q=state.q, qdot=state.qdot, t=0.05 * k), target)
        for k in range(1, 11)
    ]
    offsets = np.array(shown) - target
    np.testing.assert_allclose(offsets[:, 0], 0.005 * 0.05 * np.arange(1, 11))  # gain e dt
    np.testing.assert_allclose(offsets[:, 1], -offsets[:, 0])
    assert np.all(offsets[:, 2:] == 0.0)  # outside the band, and at zero error: nothing
    for k in range(11, 200):  # held long enough, the shift stops at the cap
        ctrl.shown_target(ControlState(q=state.q, qdot=state.qdot, t=0.05 * k), target)
    np.testing.assert_allclose(ctrl.offset[:2], [0.01, -0.01])
    moved = ctrl.shown_target(state, target + 0.1) - (target + 0.1)  # a new goal: start over
    assert np.all(np.abs(moved) <= 0.05 * 0.2) and np.all(np.abs(moved[:2]) < 0.01)
    ctrl.reset()
    assert np.all(ctrl.offset == 0.0)
    # the pure policy is the network on the raw target; the shipped one differs once shifted
    pure = make_pure_controller()
    np.testing.assert_allclose(
        pure.act(state, target),
        pure.weights.forward(pure.observation(state, target)) * pure.current_limits_mA,
    )
    with pytest.raises(ValueError, match="gain >= 0"):
        ReferenceIntegral(gain=-1.0)


def test_reference_integral_removes_the_steady_error_friction_leaves() -> None:
    from policy.campaigns.evaluation import RunConfig, evaluate, random_episodes
    from policy.controllers.ddpg_distilled import make_pure_controller
    from reach_sim_bridge.model.sensors import SensorNoise

    episodes = random_episodes(3, seed=7)
    config = RunConfig(noise=SensorNoise(), seed=7, param_spread=0.2)
    pure = evaluate(make_pure_controller(), episodes, config, name="pure").summary()
    # the integral alone, without the settle supervisor that ships around it
    shipped = evaluate(
        make_controller(settle=False), episodes, config, name="ddpg-distilled"
    ).summary()
    assert shipped["reached"] == pure["reached"] == 1.0
    assert shipped["msse"] < 0.6 * pure["msse"]  # the bias near the goal goes
    assert shipped["rmse"] <= pure["rmse"] * 1.01  # and the approach is the policy's own


def test_robust_preset_screens_envelope_arms_and_masks_bc_on_latent_ones(tmp_path: Path) -> None:
    cfg = DDPGConfig.robust()
    assert cfg.env.envelope_fraction == 0.5 and cfg.env.reward.sign_flip_weight > 0
    assert cfg.init_actor == "policy/controllers/weights/ddpg_distilled_actor.npz"
    assert DDPGConfig.from_dict(cfg.to_dict()) == cfg
    small = tiny(
        cfg,
        num_envs=2,
        demo_episodes=1,
        batch_size=64,
        eval_episodes=2,
        eval_envelope_episodes=3,
        init_actor=None,
        env=dataclasses.replace(cfg.env, episode_s=1.0, envelope_fraction=1.0),
    )
    trainer = Trainer(small, tmp_path, expert=PDExpert(), log=lambda _: None)
    assert len(trainer.eval_envelope) == 3
    assert all(env.config.envelope_fraction == 1.0 for env in trainer.eval_envelope)
    assert trainer.eval_nominal[0].config.envelope_fraction == 0.0  # the nominal set stays
    # no BC label on an arm slower than bc_max_latency; the expert's label elsewhere
    env = trainer.envs[0]
    env.reset(seed=0)
    assert small.bc_max_latency == 1.5
    env.latency_substeps = 2 * env.n_substeps  # two periods
    assert np.all(np.isnan(trainer._label(env)))
    env.latency_substeps = env.n_substeps
    np.testing.assert_array_equal(trainer._label(env), PDExpert()(env))
    assert cfg.expert_kp is not None and cfg.expert_kd is not None  # the robust preset's gains
    assert make_expert(cfg) == PDExpert(kp=cfg.expert_kp, kd=cfg.expert_kd, energy_lambda=6.0)
    trainer.run()
    record = trainer.evaluate_and_keep_best()
    assert set(record["envelope"]) >= {"reached_fraction", "at_rest_fraction"}


def test_bc_ignores_unlabelled_rows() -> None:
    from policy.rl.agent import Agent

    cfg = dataclasses.replace(DDPGConfig.ours(), policy_delay=1, batch_size=4)
    rng = np.random.default_rng(0)
    batch = {
        "obs": rng.normal(size=(4, 20)).astype(np.float32),
        "act": rng.uniform(-1, 1, size=(4, 4)).astype(np.float32),
        "rew": np.zeros((4, 1), np.float32),
        "next_obs": rng.normal(size=(4, 20)).astype(np.float32),
        "discount": np.full((4, 1), 0.99, np.float32),
        "expert": rng.uniform(-1, 1, size=(4, 4)).astype(np.float32),
    }
    batch["expert"][2:] = np.nan  # the demonstrator is no teacher on these rows
    torch.manual_seed(0)
    agent = Agent(cfg, 20)
    with torch.no_grad():
        pi = agent.actor(torch.from_numpy(batch["obs"][:2]))
        label = torch.from_numpy(batch["expert"][:2])
        want = float((((pi - label) / (label.abs() + cfg.bc_relative)) ** 2).mean())
    info = agent.update(batch, 1.0)
    assert info["bc_loss"] == pytest.approx(want, rel=1e-5)
    assert all(torch.isfinite(w).all() for w in agent.actor.parameters())


def test_envelope_evaluation_runs_the_shipped_controller_on_envelope_arms() -> None:
    from policy.campaigns.selection import envelope_results, envelope_summary
    from policy.tasks.envelope import draws

    results = envelope_results(make_controller(), 2, seed=1, episode_seed=5)
    assert [v.name for v, _ in results] == [v.name for v in draws(2, 1).variants]
    for variant, result in results:  # each arm's weak joint is in the episode
        np.testing.assert_array_equal(result.episode.torque_scale, variant.torque_scale)
    summary = envelope_summary(results)
    assert summary["arms"] == 2 and 0 <= summary["at_rest"] <= 2
    assert summary["reached"] == 2 - len(summary["failed"])
    out = subprocess.run(
        [
            sys.executable,
            str(ROOT / "tools" / "train.py"),
            "--evaluate",
            "expert",
            "--envelope",
            "2",
        ],
        capture_output=True,
        text=True,
    )
    assert out.returncode != 0 and "true state" in out.stderr


def test_the_shipped_weights_say_they_were_distilled_from_a_privileged_expert() -> None:
    """The provenance in the shipped json: four stages, each with demonstrations of the PD
    expert, whose env steps and wall times add up to the totals; not learned from scratch."""
    provenance = ActorWeights.load(DISTILLED_WEIGHTS).provenance
    assert provenance is not None and provenance.complete
    assert "TD3" in provenance.algorithm and "behaviour cloning" in provenance.algorithm
    assert provenance.demonstrations != NONE and "PDExpert" in provenance.teacher
    assert "true state" in provenance.teacher and not provenance.from_scratch
    assert [s.run for s in provenance.stages] == ["ours-s1", "energy-b", "wide-s6", "fine-s10"]
    assert provenance.stages[0].init_actor is None
    assert provenance.env_steps == sum(s.env_steps for s in provenance.stages) == 625_000
    walls = [s.wall_s for s in provenance.stages if s.wall_s is not None]
    assert len(walls) == 4 and provenance.wall_s == pytest.approx(sum(walls), abs=0.1)
    meta = json.loads(DISTILLED_WEIGHTS.with_suffix(".json").read_text())
    assert provenance.seed == meta["seed"] and provenance.command == meta["command"]


def _stage(run: str, steps: int, wall: float, seed: int, init: str | None = None) -> TrainingStage:
    return TrainingStage(run, steps, wall, seed, f"tools/train.py --run runs/{run}", init)


def test_saved_actors_record_how_they_were_trained(tmp_path: Path) -> None:
    """DDPG without a teacher is from scratch; TD3+BC names the expert and its episodes; a
    fine-tune carries the earlier stages and adds them up, or says the lineage is incomplete."""
    actor = Actor(DDPGConfig.paper().env.observation.size, 4, DDPGConfig.paper().hidden)
    save_actor_npz(tmp_path / "p.npz", actor, DDPGConfig.paper(), stage=_stage("p", 800, 9.5, 0))
    paper = ActorWeights.load(tmp_path / "p.npz").provenance
    assert paper is not None and paper.algorithm == "DDPG" and paper.from_scratch
    assert (paper.demonstrations, paper.teacher) == (NONE, NONE)
    assert (paper.env_steps, paper.wall_s, paper.seed) == (800, 9.5, 0)
    assert paper.command == "tools/train.py --run runs/p"

    ours = DDPGConfig.ours(init_actor=str(tmp_path / "p.npz"))
    actor = Actor(ours.env.observation.size, 4, ours.hidden)
    stage = _stage("o", 200, 2.0, 3, ours.init_actor)
    save_actor_npz(tmp_path / "o.npz", actor, ours, stage=stage)
    tuned = ActorWeights.load(tmp_path / "o.npz").provenance
    assert tuned is not None and tuned.algorithm.startswith("TD3 + behaviour cloning")
    assert tuned.algorithm.endswith("earlier stages: DDPG")
    assert tuned.demonstrations.startswith("100 episodes of a privileged PD expert")
    assert tuned.teacher.startswith("PDExpert (privileged: true state, masses, torque scale)")
    assert [s.run for s in tuned.stages] == ["p", "o"] and tuned.complete
    assert (tuned.env_steps, tuned.wall_s, tuned.seed) == (1000, 11.5, 3)

    orphan = DDPGConfig.ours(init_actor=str(tmp_path / "nowhere.npz"))
    save_actor_npz(tmp_path / "x.npz", actor, orphan, stage=_stage("x", 50, 1.0, 4))
    lost = ActorWeights.load(tmp_path / "x.npz").provenance
    assert lost is not None and not lost.complete and "nowhere.npz" in lost.note
    assert lost.env_steps == 50


def test_a_trained_run_exports_its_provenance_with_the_command(tmp_path: Path) -> None:
    cfg = tiny(DDPGConfig.paper(), total_steps=200)
    trainer = Trainer(cfg, tmp_path / "run-a", log=lambda _: None, command="train.py --run a")
    trainer.run()
    trainer.evaluate_and_keep_best()
    provenance = ActorWeights.load(tmp_path / "run-a" / "best_actor.npz").provenance
    assert provenance is not None and provenance.from_scratch
    assert provenance.env_steps == 200 and provenance.command == "train.py --run a"
    assert provenance.stages[0].run == "run-a" and provenance.seed == cfg.seed
    assert provenance.wall_s == pytest.approx(trainer.state.wall_s, abs=0.05)
