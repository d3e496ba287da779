"""ReachAlpha-v0: API conformance, rewards, bounds, options and the shared observation."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from policy.controllers.observation import (
    WORKSPACE_HIGH,
    WORKSPACE_INSET_RAD,
    WORKSPACE_LOW,
    ObservationConfig,
    build_observation,
    observation_bounds,
)
from policy.rl.config import DDPGConfig
from policy.rl.env import (
    ENV_ID,
    NO_LOAD_SPEEDS,
    REWARD_TERMS,
    EnvConfig,
    ReachAlphaEnv,
    RewardConfig,
    RewardMode,
    compute_reward,
    reward_terms,
    time_limited,
)
from policy.rl.expert import PDExpert
from protocol.models import ALPHA5, BRAVO7, ArmModelName
from reach_driver.controllers import ControlState
from reach_sim_bridge.model.motor import model_no_load_speed

if TYPE_CHECKING:
    from reach_sim_bridge.model.arm import Alpha5Arm

OURS_OBS = ObservationConfig()
SHAPED = RewardConfig(
    mode=RewardMode.SHAPED,
    distance_weight=2.0,
    velocity_weight=0.5,
    action_change_weight=0.1,
    near_scale=0.05,
)


def mujoco_arm(env: ReachAlphaEnv) -> Alpha5Arm:
    """The env's arm as what it is here: the MuJoCo `Alpha5Arm` (the default factory's, or a
    test's factory's), with its parameters and commanded currents."""
    return cast("Alpha5Arm", env.arm)


@pytest.mark.parametrize("obs_config", [ObservationConfig.paper(), OURS_OBS])
def test_check_env_passes(obs_config: ObservationConfig) -> None:
    env = ReachAlphaEnv(EnvConfig(observation=obs_config, sensor_noise=True))
    check_env(env, skip_render_check=True)
    space = env.observation_space
    assert isinstance(space, gym.spaces.Box)
    assert np.all(np.isfinite(space.low))
    assert np.all(np.isfinite(space.high))


def test_registered_and_makeable() -> None:
    env = gym.make(ENV_ID)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (12,)
    env2 = gym.make("policy.rl.env:ReachAlpha-v0", config=EnvConfig(observation=OURS_OBS))
    assert env2.reset(seed=1)[0].shape == (20,)


def test_paper_reward_values() -> None:
    z = np.zeros(4)
    q_req = np.array([1.0, 1.0, 1.0, 1.0])
    cfg = RewardConfig()
    assert compute_reward(q_req, z, q_req, z, z, True, cfg) == pytest.approx(0.0)
    # |e| = sigma in norm: -1 + exp(-1/2)
    q = q_req - np.array([0.018, 0.0, 0.0, 0.0])
    assert compute_reward(q, z, q_req, z, z, True, cfg) == pytest.approx(-1 + np.exp(-0.5))
    q = q_req - np.array([0.009, 0.0, 0.0, 0.009 * np.sqrt(3)])  # norm 0.018
    assert compute_reward(q, z, q_req, z, z, True, cfg) == pytest.approx(-1 + np.exp(-0.5))
    assert compute_reward(q_req - 1.0, z, q_req, z, z, True, cfg) == pytest.approx(-1.0)
    assert compute_reward(q_req, z, q_req, z, z, False, cfg) == -10.0


def test_shaped_reward_values() -> None:
    z = np.zeros(4)
    q_req = np.array([3.0, 1.7, 1.7, 1.65])
    assert compute_reward(q_req, z, q_req, z, z, True, SHAPED) == pytest.approx(0.0)
    # one joint off by its half-range: no bonus there, distance term 2 * 1/4
    half = (WORKSPACE_HIGH - WORKSPACE_LOW) / 2
    q = q_req.copy()
    q[1] -= half[1]
    expected = -1 + 3 / 4 - 2.0 * 0.25
    assert compute_reward(q, z, q_req, z, z, True, SHAPED) == pytest.approx(expected, abs=1e-9)
    # at the target, moving and twitching costs; far from it, it does not
    qdot = np.array([NO_LOAD_SPEEDS[0], 0.0, 0.0, 0.0])  # the no-load speed
    act = np.array([1.0, 0.0, 0.0, 0.0])
    assert compute_reward(q_req, qdot, q_req, act, z, True, SHAPED) == pytest.approx(
        -0.5 * 0.25 - 0.1 * 0.25
    )
    far = q_req.copy()
    far[0] -= 1.0
    r_still = compute_reward(far, z, q_req, z, z, True, SHAPED)
    r_moving = compute_reward(far, qdot, q_req, act, z, True, SHAPED)
    assert r_moving == pytest.approx(r_still, abs=1e-9)
    assert compute_reward(q_req, z, q_req, z, z, False, SHAPED) == -10.0


def test_out_of_bounds_costs_minus_ten_per_step_and_episode_goes_on() -> None:
    env = ReachAlphaEnv(EnvConfig())
    start = np.array([0.4, 1.5, 1.5, 1.5])
    env.reset(seed=0, options={"start": start, "target": start})
    rewards, terminated = [], []
    for _ in range(30):  # E drives below its bound (0.4 - 0.3 rad)
        _, r, term, trunc, info = env.step(np.array([-1.0, 0.0, 0.0, 0.0]))
        rewards.append(r)
        terminated.append(term or trunc)
    assert not any(terminated)
    assert env.arm.q[0] < env.bounds_low[0]
    out = [r for r in rewards if r == -10.0]
    assert len(out) >= 5  # every step outside pays, not just the first
    assert rewards[0] > -10.0
    # coming back inside ends the penalty
    for _ in range(30):
        _, r, *_ = env.step(np.array([1.0, 0.0, 0.0, 0.0]))
    assert r > -10.0


def test_truncates_at_episode_length() -> None:
    """Truncation is TimeLimit's, as for Gymnasium's own envs; the env itself never ends."""
    config = EnvConfig(episode_s=1.0, control_hz=20.0)
    raw = ReachAlphaEnv(config)
    env = time_limited(raw)
    env.reset(seed=0)
    flags = [env.step(np.zeros(4))[3] for _ in range(20)]
    assert flags == [False] * 19 + [True]
    assert raw.control_dt == pytest.approx(0.05)
    env.reset(seed=0)  # a reset restarts the count
    assert [env.step(np.zeros(4))[3] for _ in range(20)] == [False] * 19 + [True]
    assert not any(raw.step(np.zeros(4))[3] for _ in range(30))  # past 20 steps: goes on
    made = gym.make(ENV_ID, config=config, max_episode_steps=config.steps_per_episode)
    made.reset(seed=0)
    assert [made.step(np.zeros(4))[3] for _ in range(20)] == [False] * 19 + [True]


def test_gym_make_wraps_in_time_limit_at_the_default_episode() -> None:
    env = gym.make(ENV_ID)
    assert env.spec is not None and env.spec.max_episode_steps == 400
    assert EnvConfig().steps_per_episode == 400
    wrapper: object = env
    while not isinstance(wrapper, gym.wrappers.TimeLimit):
        assert isinstance(wrapper, gym.Wrapper), "gym.make added no TimeLimit"
        wrapper = wrapper.env


@pytest.mark.parametrize("reward", [RewardConfig(), SHAPED], ids=["paper", "shaped"])
def test_reward_terms_in_info_sum_to_the_reward(reward: RewardConfig) -> None:
    env = ReachAlphaEnv(EnvConfig(reward=reward))
    start = np.array([0.45, 1.5, 1.5, 1.5])
    env.reset(seed=0, options={"start": start, "target": start + 0.03})
    seen_out = seen_in = False
    for k in range(40):  # E drives out of bounds and comes back
        action = np.array([-1.0 if k < 15 else 1.0, 0.3, -0.2, 0.1])
        _, r, _, _, info = env.step(action)
        terms = info["reward_terms"]
        assert tuple(terms) == REWARD_TERMS
        assert sum(terms.values()) == r  # exactly: the reward is this sum
        if info["in_bounds"]:
            seen_in = True
            assert terms["out_of_bounds"] == 0.0
        else:
            seen_out = True
            assert terms == {**dict.fromkeys(REWARD_TERMS, 0.0), "out_of_bounds": -10.0}
        if reward.mode is RewardMode.PAPER:
            assert terms["distance"] == terms["velocity"] == terms["action_change"] == 0.0
    assert seen_in and seen_out
    z = np.zeros(4)
    q_req = np.array([3.0, 1.7, 1.7, 1.65])
    shaped = reward_terms(q_req - 0.1, np.ones(4), q_req, np.ones(4), z, True, SHAPED)
    assert all(shaped[k] < 0 for k in ("precision", "distance", "velocity", "action_change"))
    assert sum(shaped.values()) == compute_reward(
        q_req - 0.1, np.ones(4), q_req, np.ones(4), z, True, SHAPED
    )


def test_overshoot_term_is_the_metrics_ratio_past_the_goal() -> None:
    cfg = dataclasses.replace(SHAPED, overshoot_weight=4.0, overshoot_floor=0.1)
    start = np.array([1.0, 1.0, 1.0, 1.0])
    goal = np.array([1.5, 0.95, 1.02, 1.0])  # E steps +0.5, D -0.05, C 0.02 (too short), B 0
    z = np.zeros(4)

    def term(q: np.ndarray) -> float:
        return reward_terms(q, z, goal, z, z, True, cfg, start=start)["overshoot"]

    assert term(start) == 0.0  # nowhere near the goal
    assert term(goal) == 0.0
    # E 0.05 past (10 % of its 0.5 step), D 0.005 past (its 0.05 step under the 0.1 floor)
    past = goal + np.array([0.05, -0.005, 0.5, 0.3])  # C and B: no step, never overshoot
    assert term(past) == pytest.approx(-4.0 * (0.05 / 0.5 + 0.005 / 0.1) / 4)
    assert term(goal + np.array([5.0, 0, 0, 0])) == pytest.approx(-1.0)  # clipped at 1
    assert term(goal - np.array([0.05, -0.005, 0, 0])) == 0.0  # short of the goal: not past
    assert reward_terms(past, z, goal, z, z, True, SHAPED, start=start)["overshoot"] == 0.0
    env = ReachAlphaEnv(EnvConfig(reward=cfg))
    env.reset(seed=0, options={"start": start, "target": start + np.array([0.2, 0, 0, 0])})
    paid = [env.step(np.array([1.0, 0, 0, 0]))[4]["reward_terms"]["overshoot"] for _ in range(30)]
    assert paid[0] == 0.0 and min(paid) < 0.0  # E driven through its goal pays once past it


def test_overshoot_peak_term_pays_the_metric_once_as_it_is_made() -> None:
    """Over an episode the term sums to -w x mean_j (joint j's largest ratio past its goal):
    driven through its goal and held there, E pays for its largest excursion, and no more for
    the steps it stays past."""
    w = 40.0
    cfg = dataclasses.replace(SHAPED, overshoot_peak_weight=w, overshoot_floor=0.1)
    start = np.array([1.0, 1.0, 1.0, 1.0])
    env = ReachAlphaEnv(EnvConfig(reward=cfg))
    env.reset(seed=0, options={"start": start, "target": start + np.array([0.5, 0, 0, 0])})
    paid, ratios = [], []
    for k in range(40):
        action = np.array([1.0 if k < 10 else 0.0, 0, 0, 0])
        info = env.step(action)[4]
        paid.append(info["reward_terms"]["overshoot_peak"])
        ratios.append(float(np.clip((info["q"][0] - env.target[0]) / 0.5, 0.0, 1.0)))
    assert 0.05 < max(ratios) < 1.0  # driven well past its goal, not to the clip
    assert sum(paid) == pytest.approx(-w * max(ratios) / 4, rel=1e-9)
    # paid only on the steps its largest excursion grew
    grew = np.diff(np.maximum.accumulate([0.0, *ratios])) > 0
    assert all((p < 0) == g for p, g in zip(paid, grew, strict=True))
    assert (
        reward_terms(start, np.zeros(4), env.target, start, start, True, cfg)["overshoot_peak"]
        == 0.0
    )  # without a start and a peak: off


def test_control_rate_is_a_parameter() -> None:
    env = ReachAlphaEnv(EnvConfig(control_hz=50.0, episode_s=2.0))
    assert env.n_substeps == 10
    assert env.config.steps_per_episode == 100


def test_random_starts_and_goals_in_workspace_and_seeded() -> None:
    env = ReachAlphaEnv(EnvConfig())
    starts, targets = [], []
    for seed in range(20):
        env.reset(seed=seed)
        starts.append(env.start)
        targets.append(env.target)
    for arr in (np.array(starts), np.array(targets)):
        assert np.all(arr >= WORKSPACE_LOW) and np.all(arr <= WORKSPACE_HIGH)
    assert len({tuple(np.round(t, 6)) for t in targets}) == 20
    env.reset(seed=3)
    assert np.array_equal(env.target, targets[3])
    np.testing.assert_allclose(env.arm.q, starts[3])


def test_goal_every_draws_new_goals_within_the_episode_from_where_the_arm_is() -> None:
    env = ReachAlphaEnv(EnvConfig(goal_every_s=1.0, max_step=0.3))
    env.reset(seed=5)
    goals = [env.target.copy()]
    memory_before = None
    for k in range(1, 61):
        env.step(np.full(4, 0.05))
        if k % 20 == 19:
            memory_before = env.memory.prev_action.copy()
        if k % 20 == 0:
            assert not np.array_equal(env.target, goals[-1]), f"no new goal at step {k}"
            np.testing.assert_allclose(env.start, env.arm.q)
            inside = np.clip(env.start, WORKSPACE_LOW, WORKSPACE_HIGH)
            assert np.all(np.abs(env.target - inside) <= 0.3 + 1e-12)
            assert memory_before is not None and np.any(env.memory.prev_action != 0)
            goals.append(env.target.copy())
        else:
            np.testing.assert_array_equal(env.target, goals[-1])
    assert len(goals) == 4
    with pytest.raises(ValueError, match="goal_every_s"):
        EnvConfig(goal_every_s=0.0)
    # evaluation always runs one goal per episode
    from policy.rl.batched import eval_envs

    assert eval_envs(EnvConfig(goal_every_s=1.0), 1)[0].config.goal_every_s is None


def test_small_steps_draw_that_share_of_goals_near_the_start_and_leave_the_rest_alone() -> None:
    """`small_step_fraction`: per joint, that share of goals within `small_step` of the start;
    at 0 the episodes are the ones the env always drew; evaluation draws uniformly."""
    cfg = DDPGConfig.scratch().env
    small = dataclasses.replace(cfg, small_step_fraction=0.25, small_step=0.3)
    plain, near = ReachAlphaEnv(cfg), ReachAlphaEnv(small)
    steps, plain_steps = [], []
    for seed in range(400):
        near.reset(seed=seed)
        plain.reset(seed=seed)
        steps.append(np.abs(near.target - near.start))
        plain_steps.append(np.abs(plain.target - plain.start))
        low, high = near.workspace_low, near.workspace_high
        assert np.all(near.target >= low) and np.all(near.target <= high)
    share = (np.array(steps) <= 0.3).mean(axis=0)
    plain_share = (np.array(plain_steps) <= 0.3).mean(axis=0)
    # uniform goals put 0.1-0.24 of steps within 0.3 rad (B over 5.3 rad, D C over 2.4);
    # a quarter more drawn there lifts that to about 0.25 + 0.75 x those
    assert np.all(share > plain_share + 0.12), (share, plain_share)
    assert np.all(share < plain_share + 0.32), (share, plain_share)
    # at 0 the draw is untouched: start and goal are the env's first two uniform draws, as
    # they were before the option (runs and their seeds replay)
    zero = ReachAlphaEnv(EnvConfig(small_step_fraction=0.0))
    for seed in (1, 2, 3):
        zero.reset(seed=seed)
        rng, _ = gym.utils.seeding.np_random(seed)
        np.testing.assert_array_equal(
            zero.start, rng.uniform(zero.workspace_low, zero.workspace_high)
        )
        np.testing.assert_array_equal(
            zero.target, rng.uniform(zero.workspace_low, zero.workspace_high)
        )
    with pytest.raises(ValueError, match="small_step_fraction"):
        dataclasses.replace(cfg, small_step_fraction=1.5)
    with pytest.raises(ValueError, match="small_step must be"):
        dataclasses.replace(cfg, small_step=0.0)
    from policy.rl.batched import eval_envs

    assert eval_envs(small, 1)[0].config.small_step_fraction == 0.0


def test_action_scaled_to_current_limits() -> None:
    env = ReachAlphaEnv(EnvConfig())
    env.reset(seed=0, options={"start": [3.0, 1.7, 1.7, 1.6], "target": [3.0, 1.7, 1.7, 1.6]})
    env.step(np.array([0.5, -0.25, 0.0, 2.0]))  # B clipped to 1
    np.testing.assert_allclose(env.arm.current_limits_mA, [600, 600, 600, 300])
    commanded = np.asarray(mujoco_arm(env)._command_mA[:4])  # noqa: SLF001 (what reached the arm)
    np.testing.assert_allclose(commanded, [300.0, -150.0, 0.0, 300.0])


def test_bad_input_is_rejected() -> None:
    env = ReachAlphaEnv(EnvConfig())
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0, 0, 0]))
    with pytest.raises(ValueError, match="target"):
        env.reset(options={"target": [1.0, 2.0]})
    with pytest.raises(ValueError, match="control_hz"):
        ReachAlphaEnv(EnvConfig(control_hz=0.0))
    # 40 Hz is 12.5 physics steps of 2 ms: refused, naming the rates that are whole numbers
    with pytest.raises(ValueError, match=r"not a whole number .* 41\.6667 Hz \(12 steps\)"):
        ReachAlphaEnv(EnvConfig(control_hz=40.0))
    env = ReachAlphaEnv(EnvConfig(control_hz=1 / (12 * 0.002), episode_s=1.0))
    assert env.n_substeps == 12 and env.config.steps_per_episode == 42


def test_sensor_noise_only_on_readings() -> None:
    env = ReachAlphaEnv(EnvConfig(sensor_noise=True))
    env.reset(seed=0)
    obs, *_ = env.step(np.zeros(4))
    q_seen = obs[:4]
    diff = q_seen - env.arm.q
    assert 0 < np.max(np.abs(diff)) < 0.02
    quiet = ReachAlphaEnv(EnvConfig())
    quiet.reset(seed=0)
    obs, *_ = quiet.step(np.zeros(4))
    np.testing.assert_allclose(obs[:4], quiet.arm.q, atol=1e-6)


def test_torque_scale_and_parameter_perturbation() -> None:
    env = ReachAlphaEnv(EnvConfig(torque_scale_low=(0.25, 1.0, 1.0, 1.0)))
    scales = []
    for seed in range(10):
        env.reset(seed=seed)
        scales.append(env.arm.torque_scale.copy())
    scales_arr = np.array(scales)
    assert np.all((scales_arr[:, 0] >= 0.25) & (scales_arr[:, 0] <= 1.0))
    assert np.ptp(scales_arr[:, 0]) > 0.1
    np.testing.assert_array_equal(scales_arr[:, 1:], 1.0)
    env.reset(seed=0, options={"torque_scale": [0.25, 1, 1, 1]})
    np.testing.assert_allclose(env.arm.torque_scale, [0.25, 1, 1, 1])

    pert = ReachAlphaEnv(EnvConfig(param_perturbation=0.2))
    nominal = np.array(mujoco_arm(pert).params.damping)
    pert.reset(seed=0)
    first = np.array(mujoco_arm(pert).params.damping)
    pert.reset(seed=1)
    second = np.array(mujoco_arm(pert).params.damping)
    assert not np.allclose(first, nominal) and not np.allclose(first, second)
    assert np.all(np.abs(first / nominal - 1) <= 0.2 + 1e-9)


def test_observation_features_and_bounds() -> None:
    q = np.array([1.0, 1.0, 1.0, 1.0])
    q_req = q + np.array([0.05, -0.05, 0.0, 1.0])
    obs = build_observation(q, np.zeros(4), q_req, OURS_OBS)
    assert obs.dtype == np.float32 and obs.shape == (OURS_OBS.size,)
    np.testing.assert_allclose(obs[16:], np.tanh(np.array([1.0, -1.0, 0.0, 20.0])), atol=1e-6)
    paper = build_observation(q, np.ones(4), q_req, ObservationConfig.paper())
    np.testing.assert_allclose(paper, np.concatenate([q, np.ones(4), q_req]), atol=1e-6)
    for cfg in (OURS_OBS, ObservationConfig.paper()):
        low, high = observation_bounds(cfg)
        extreme = build_observation(np.full(4, 99.0), np.full(4, -99.0), np.full(4, -99.0), cfg)
        assert np.all(extreme >= low) and np.all(extreme <= high)
    with pytest.raises(ValueError, match="shape"):
        build_observation(np.zeros(3), np.zeros(4), np.zeros(4), OURS_OBS)


def test_controller_sees_the_same_observation_as_the_env(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import torch

    from policy.controllers.ddpg_distilled import make_controller
    from policy.rl.checkpoint import save_actor_npz
    from policy.rl.config import DDPGConfig
    from policy.rl.networks import Actor

    config = DDPGConfig.ours()
    actor = Actor(OURS_OBS.size, 4, (16, 8))
    torch.manual_seed(0)
    save_actor_npz(tmp_path / "a.npz", actor, config)
    ctrl = make_controller(tmp_path / "a.npz")
    env = ReachAlphaEnv(dataclasses.replace(config.env, sensor_noise=False))
    obs, _ = env.reset(seed=4)
    for _ in range(5):
        obs, *_ = env.step(env.action_space.sample())
        state = ControlState(q=env.arm.q, qdot=env.arm.qdot, t=0.0)
        np.testing.assert_array_equal(ctrl.observation(state, env.target), obs)


def test_expert_solves_the_task() -> None:
    """The environment is solvable at 20 Hz: the demonstrator reaches every goal calmly."""
    env = ReachAlphaEnv(EnvConfig(sensor_noise=True))
    expert = PDExpert()
    for seed in range(3):
        env.reset(seed=100 + seed)
        q0 = env.arm.q.copy()
        progress = []
        for _ in range(env.config.steps_per_episode):
            env.step(expert(env))
            progress.append((env.arm.q - q0) / (env.target - q0))
        assert np.all(np.abs(env.target - env.arm.q) < 0.02)
        big = np.abs(env.target - q0) > 0.05
        assert np.max(np.array(progress)[:, big]) < 1.02  # under 2 % overshoot


def test_training_workspace_can_be_widened() -> None:
    wide = EnvConfig(workspace_high=(5.8, 2.9, 2.9, 5.8))
    env = ReachAlphaEnv(wide)
    targets = np.array([env.reset(seed=s)[1]["target"] for s in range(300)])
    assert targets[:, 3].max() > 4.0  # B now reaches the paper's scenario angles
    assert np.all(targets >= WORKSPACE_LOW) and np.all(targets <= np.array(wide.workspace_high))
    assert env.bounds_high[3] == pytest.approx(6.1)  # the bounds follow the range
    assert ReachAlphaEnv(EnvConfig()).bounds_high[3] == pytest.approx(3.1)
    assert EnvConfig.from_dict(wide.to_dict()) == wide
    with pytest.raises(ValueError, match="low < high"):
        ReachAlphaEnv(EnvConfig(workspace_high=(5.8, 2.9, 2.9, 0.1)))


def _first_motion(config: EnvConfig, start: np.ndarray) -> int:
    """Physics steps after the first non-zero action until E moves (0 at once)."""
    env = ReachAlphaEnv(config)
    env.reset(seed=0, options={"start": start, "target": start, "torque_scale": np.ones(4)})
    env.step(np.zeros(4))  # settle the zero command in flight
    q0 = env.arm.q.copy()
    for k in range(1, 10):
        env.step(np.array([1.0, 0.0, 0.0, 0.0]))
        if abs(env.arm.q[0] - q0[0]) > 1e-4:
            return k
    raise AssertionError("E never moved")


def test_commands_in_flight_switch_at_the_physics_step_they_land_on() -> None:
    """A delay of 1.2 periods of 25 steps: each command is held from 30 steps after it was
    sent until the next one lands, in spans that split a period at the switch; before the
    first lands, zero current. A negative delay is refused."""
    from policy.tasks.arm import CommandsInFlight

    class Recorder:
        def __init__(self) -> None:
            self.spans: list[tuple[float, int]] = []

        def step(self, currents_mA: np.ndarray, n: int = 1, work: object = None) -> None:
            self.spans.append((float(currents_mA[0]), n))

    arm = Recorder()
    line = CommandsInFlight(30, 4)
    for k in range(3):
        line.advance(arm, np.full(4, k + 1.0), 25 * k, 25)  # type: ignore[arg-type]
    assert arm.spans == [(0.0, 25), (0.0, 5), (1.0, 20), (1.0, 5), (2.0, 20)]
    assert line.applied[0] == 2.0
    with pytest.raises(ValueError, match="delay"):
        CommandsInFlight(-1, 4)


def test_latency_delays_each_action_as_the_direct_backend_does() -> None:
    start = np.array([3.0, 1.7, 1.7, 1.65])
    frictionless = dataclasses.replace(
        mujoco_arm(ReachAlphaEnv(EnvConfig())).params, frictionloss=(0,) * 4
    )

    def arm_factory(config: EnvConfig) -> Alpha5Arm:
        from reach_sim_bridge.model.arm import Alpha5Arm

        return Alpha5Arm(dt=config.physics_dt, params=frictionless)

    # the step that first moves E: at once without latency, one period later with 1 period
    env0 = ReachAlphaEnv(EnvConfig(), arm_factory=arm_factory)
    env2 = ReachAlphaEnv(EnvConfig(latency_periods=2.0), arm_factory=arm_factory)
    assert env2.latency_substeps == 2 * env2.n_substeps
    for env in (env0, env2):
        env.reset(seed=0, options={"start": start, "target": start})
    q0 = env0.arm.q.copy()
    moved = {}
    for name, env in (("0", env0), ("2", env2)):
        for k in range(1, 6):
            env.step(np.array([1.0, 0.0, 0.0, 0.0]))
            if env.arm.q[0] - q0[0] > 1e-4 and name not in moved:
                moved[name] = k
    assert moved == {"0": 1, "2": 3}
    # a half-period latency: the command switches mid-period, same trace as policy.campaigns.direct
    from policy.campaigns.direct import DirectArm
    from policy.tasks.episodes import Episode, RunConfig

    class Replay:
        def __init__(self, actions: np.ndarray, limits: np.ndarray) -> None:
            self.actions, self.limits, self.k = actions, limits, 0

        def reset(self) -> None:
            self.k = 0

        def act(self, state: object, target: np.ndarray) -> np.ndarray:
            a = self.actions[self.k] * self.limits
            self.k += 1
            return a

    rng = np.random.default_rng(3)
    actions = rng.uniform(-1, 1, size=(12, 4))
    env = ReachAlphaEnv(EnvConfig(latency_periods=0.52, episode_s=0.6))
    env.measure_power = True
    env.reset(seed=0, options={"start": start, "target": start + 0.1})
    for a in actions:
        env.step(a)
    backend = DirectArm(lambda seed: mujoco_arm(env).__class__(dt=0.002))
    result = backend.run(
        Replay(actions, env.current_limits_mA),
        Episode(start, start + 0.1),
        RunConfig(seconds=0.6, latency_periods=0.52),
        0,
    )
    np.testing.assert_allclose(result.trace.q[-1], env.arm.q, atol=1e-12)


def test_envelope_arms_per_episode() -> None:
    env = ReachAlphaEnv(EnvConfig(envelope_fraction=1.0, sensor_noise=True))
    nominal = mujoco_arm(env).params
    seen = []
    for seed in range(4):
        _, info = env.reset(seed=seed)
        v = env.variant
        assert v is not None and info["variant"] == v.name
        for name in ("frictionloss", "damping", "armature", "link_mass_kg", "link_volume_l"):
            assert getattr(mujoco_arm(env).params, name) == getattr(v.params, name)
        assert v.params.frictionloss != nominal.frictionloss
        np.testing.assert_array_equal(env.arm.torque_scale, v.torque_scale)
        assert env.latency_substeps == round(v.latency_periods * env.n_substeps)
        assert env.noise.position_std == pytest.approx(0.002 * v.noise_scale)
        seen.append(v.name)
    assert len(set(seen)) == 4
    # deterministic per seed; a share of 0 leaves the configured arm, nominal again
    assert ReachAlphaEnv(EnvConfig(envelope_fraction=1.0)).reset(seed=2)[1]["variant"] == seen[2]
    env.config = EnvConfig()
    _, info = env.reset(seed=0)
    assert info["variant"] is None and env.latency_substeps == 0
    assert mujoco_arm(env).params.frictionloss == nominal.frictionloss
    half = ReachAlphaEnv(EnvConfig(envelope_fraction=0.5))
    share = np.mean([half.reset(seed=s)[1]["variant"] is not None for s in range(40)])
    assert 0.2 < share < 0.8
    cfg = EnvConfig(envelope_fraction=0.5, latency_periods=1.0, noise_scale=2.0)
    assert EnvConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="envelope_fraction"):
        EnvConfig(envelope_fraction=1.5)


def test_sign_flip_penalty_is_paid_near_the_goal_only() -> None:
    cfg = dataclasses.replace(SHAPED, sign_flip_weight=1.0)
    q_req = np.array([3.0, 1.7, 1.7, 1.65])
    flip = np.array([0.5, 0.0, 0.0, 0.0]), np.array([-0.5, 0.0, 0.0, 0.0])
    z = np.zeros(4)

    def term(q: np.ndarray, a: np.ndarray, a_prev: np.ndarray) -> float:
        return reward_terms(q, z, q_req, a, a_prev, True, cfg)["sign_flip"]

    near = term(q_req + 0.005, *flip)
    assert near == pytest.approx(-0.25 * np.exp(-0.5 * (0.005 / 0.05) ** 2))  # mean over 4
    assert term(q_req + np.array([0.5, 0, 0, 0]), *flip) > -1e-5  # far from the goal: ~0
    assert term(q_req, flip[0], flip[0]) == 0.0  # same sign
    assert term(q_req, np.array([0.05, 0, 0, 0]), flip[1]) == 0.0  # below 10 % of the limit
    assert reward_terms(q_req, z, q_req, *flip, True, SHAPED)["sign_flip"] == 0.0  # weight 0
    # in the env: a bang-bang at the goal pays it every step
    env = ReachAlphaEnv(EnvConfig(reward=cfg))
    env.reset(seed=0, options={"start": q_req, "target": q_req})
    paid = [
        env.step(np.array([s, 0, 0, 0]))[4]["reward_terms"]["sign_flip"] for s in (0.3, -0.3, 0.3)
    ]
    assert paid[0] == 0.0 and paid[1] < -0.2 and paid[2] < -0.2, paid


# -- the arm is a parameter ------------------------------------------------------------------

REFERENCE = Path(__file__).resolve().parent / "data" / "alpha_env_reference.json"


def _rollout(config: EnvConfig, seed: int, steps: int = 30) -> dict[str, object]:
    """What `alpha_env_reference.json` holds: 30 steps of uniform random actions (seeded)."""
    env = ReachAlphaEnv(config)
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out: dict[str, Any] = {"obs": [obs.tolist()], "reward": [], "variant": None}
    out["variant"] = None if env.variant is None else env.variant.name
    for _ in range(steps):
        o, r, *_ = env.step(rng.uniform(-1, 1, 4))
        out["obs"].append(o.tolist())
        out["reward"].append(r)
    return out


@pytest.mark.parametrize(
    ("case", "config", "seed"),
    [
        ("paper", EnvConfig(), 3),
        ("scratch-envelope-arm", DDPGConfig.scratch().env, 11),
        ("scratch-perturbed", DDPGConfig.scratch().env, 1),  # +-20 % around the nominal arm
    ],
)
def test_the_alpha_env_observes_and_rewards_exactly_as_before(
    case: str, config: EnvConfig, seed: int
) -> None:
    """Recorded before the arm was a parameter (tests/data/README.md): every observation
    and reward bit for bit, the observation's normalisation and the reward's scales included."""
    reference = json.loads(REFERENCE.read_text())[case]
    assert config.arm is ArmModelName.ALPHA5 and config.on(ALPHA5) is config
    assert _rollout(config, seed) == reference


def test_the_bravo_env_has_six_joint_spaces_from_its_model() -> None:
    paper = ReachAlphaEnv(EnvConfig().on(BRAVO7))
    check_env(paper, skip_render_check=True)
    assert paper.action_space.shape == (6,)
    assert paper.observation_space.shape == (18,)
    scratch = DDPGConfig.scratch().on(BRAVO7)
    env = ReachAlphaEnv(scratch.env)
    assert env.observation_space.shape == (scratch.env.observation.size_for(6),) == (42,)
    # each fact from the model: limits and motors from protocol.bravo7, through its twin
    np.testing.assert_array_equal(env.current_limits_mA, BRAVO7.current_limits_mA)
    lows = [BRAVO7.position_limits[d][0] + WORKSPACE_INSET_RAD for d in BRAVO7.joints]
    np.testing.assert_allclose(env.workspace_low, lows)
    assert np.all(
        env.bounds_high <= np.array([BRAVO7.position_limits[d][1] for d in BRAVO7.joints])
    )
    speed = model_no_load_speed(BRAVO7)
    np.testing.assert_array_equal(env.scales.no_load_speed, speed)
    assert 1.0 < speed.min() < speed.max() < 1.2  # bravo7.md "Motors": 1.10 to 1.17 rad/s
    obs, info = env.reset(seed=0)
    assert obs.shape == (42,) and info["q"].shape == (6,) and info["target"].shape == (6,)
    assert np.all((info["target"] >= env.workspace_low) & (info["target"] <= env.workspace_high))
    obs, reward, *_, info = env.step(np.full(6, 0.5))
    assert np.isfinite(reward) and info["reward_terms"]["velocity"] <= 0.0
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        env.step(np.zeros(4))
    with pytest.raises(ValueError, match="6 finite numbers"):
        env.reset(options={"start": [1.0] * 4})


def _table(doc: str, heading: str) -> list[list[str]]:
    """The rows of the first table after `heading` in a docstring, cells stripped."""
    lines = doc.split(heading, 1)[1].splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith("|"))
    rows = []
    for line in lines[start:]:
        if not line.strip().startswith("|"):
            break
        rows.append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return rows[2:]  # past the header and its rule


def test_the_env_docstring_tables_say_what_each_arm_has() -> None:
    doc = ReachAlphaEnv.__doc__ or ""
    actions = _table(doc, "## Action space")
    for model, (joint, mA) in ((ALPHA5, (1, 2)), (BRAVO7, (3, 4))):
        env = ReachAlphaEnv(EnvConfig().on(model))
        told = [(row[joint], row[mA]) for row in actions if row[joint]]
        expected = [
            (f"joint {letter}", f"{limit:g}")
            for letter, limit in zip(model.joint_letters, env.current_limits_mA, strict=True)
        ]
        assert told == expected, model.name
    sizes = _table(doc, "## Observation space")[-1]
    assert sizes[0] == "m"
    for column, obs in ((2, ObservationConfig.paper()), (3, ObservationConfig())):
        per_arm = [
            str(EnvConfig(observation=obs).on(m).observation.size_for(m.n_joints))
            for m in (ALPHA5, BRAVO7)
        ]
        assert sizes[column] == " / ".join(per_arm)
        assert ReachAlphaEnv(EnvConfig(observation=obs).on(BRAVO7)).observation_space.shape == (
            int(per_arm[1]),
        )
    env = ReachAlphaEnv(EnvConfig().on(BRAVO7))
    low, high = env.workspace_low, env.workspace_high
    said = f"G D B [{low[0]:.1f}, {high[0]:.2f}], F E C [{low[1]:.1f}, {high[1]:.1f}] rad"
    assert said in " ".join(doc.split()), said


def test_envelope_arms_and_perturbation_are_refused_on_the_bravo() -> None:
    six = (1.0,) * 6
    for config in (
        EnvConfig(arm=ArmModelName.BRAVO7, torque_scale=six, envelope_fraction=0.5),
        EnvConfig(arm=ArmModelName.BRAVO7, torque_scale=six, param_perturbation=0.5),
    ):
        with pytest.raises(ValueError, match="draw Reach Alpha 5 arms.*not the Reach Bravo 7's"):
            ReachAlphaEnv(config)
    with pytest.raises(ValueError, match=r"torque_scale needs 6 values \(G F E D C B\)"):
        EnvConfig(arm=ArmModelName.BRAVO7)
    # the scratch recipe fitted to the Bravo: both off, the weak joint its base joint G
    env = DDPGConfig.scratch().on(BRAVO7).env
    assert env.envelope_fraction == 0.0 and env.param_perturbation == 0.0
    assert env.torque_scale_low == (0.25, 1.0, 1.0, 1.0, 1.0, 1.0)
    assert env.workspace_high is None  # the Alpha's wide B is the Alpha's
    assert EnvConfig.from_dict(env.to_dict()) == env and env.to_dict()["arm"] == "bravo7"
    assert EnvConfig.from_dict({}).arm is ArmModelName.ALPHA5  # absent: the Alpha 5
    with pytest.raises(ValueError, match="no arm model 'gamma9'"):
        EnvConfig.from_dict({"arm": "gamma9"})
