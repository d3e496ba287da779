"""The learned `ddpg` policy's inputs and controller: what training saw is what the arm gets.

The memory channels (previous action, leaky error integral) are state kept outside the
network; the env (training) and `LearnedController` (run time) must keep it identically, or
the deployed network sees inputs it never trained on.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import policy.rl.env as policy_env
from policy.controllers.ddpg import LearnedController, make_controller
from policy.controllers.observation import InputMemory, ObservationConfig, build_observation
from policy.controllers.weights import FORMAT, LAYERS, LEARNED_WEIGHTS, ActorWeights
from policy.rl.config import DDPGConfig
from policy.rl.env import EnvConfig, ReachAlphaEnv, RewardConfig, RewardMode, reward_terms
from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver.controllers import ControllerModelError, ControlState, load_controller

MEMORY_OBS = ObservationConfig(previous_action=True, integral_tau=1.0)


def random_weights(config: ObservationConfig, seed: int = 0, hz: float = 20.0) -> ActorWeights:
    rng = np.random.default_rng(seed)
    sizes = [config.size, 32, 32, 4]
    weights = tuple(rng.normal(0, 0.5, (o, i)) for i, o in zip(sizes, sizes[1:], strict=False))
    biases = tuple(rng.normal(0, 0.1, o) for o in sizes[1:])
    meta = {"format": FORMAT, "layers": LAYERS, "env": {"control_hz": hz}}
    return ActorWeights(weights, biases, 0.01, config, np.array([600.0, 600, 600, 300]), meta)


def test_memory_channels_size_and_bounds() -> None:
    assert MEMORY_OBS.size == 28
    assert ObservationConfig().size == 20
    with pytest.raises(ValueError, match="memory channels"):
        ObservationConfig(include_error=False, previous_action=True)
    with pytest.raises(ValueError, match="integral_tau"):
        ObservationConfig(integral_tau=-1.0)


def test_integral_is_a_leaky_mean_of_the_squashed_error() -> None:
    dt = 0.05
    memory = InputMemory(MEMORY_OBS, dt)
    q, q_req = np.full(4, 1.0), np.array([1.003, 0.997, 1.0, 1.5])
    squashed = np.tanh((q_req - q) / MEMORY_OBS.integral_error_scale)
    for k in range(1, 41):
        obs = memory.observe(q, np.zeros(4), q_req)
        expected = (1 - np.exp(-k * dt / MEMORY_OBS.integral_tau)) * squashed
        np.testing.assert_allclose(obs[24:28], expected, rtol=1e-5, atol=1e-7)
    # after two time constants a steady 3 mrad error reads 0.86 of tanh(0.3)
    assert obs[24] == pytest.approx(0.8647 * np.tanh(0.3), rel=1e-3)
    memory.acted(np.array([2.0, -0.5, 0.0, 0.25]))
    obs = memory.observe(q, np.zeros(4), q_req)
    np.testing.assert_allclose(obs[20:24], [1.0, -0.5, 0.0, 0.25])  # clipped as applied
    memory.reset()
    assert not memory.integral.any() and not memory.prev_action.any()


def test_memory_observation_needs_its_memory() -> None:
    with pytest.raises(ValueError, match="InputMemory"):
        build_observation(np.ones(4), np.zeros(4), np.ones(4), MEMORY_OBS)


WINDOW_OBS = ObservationConfig(previous_action=True, integral_tau=1.0, history=3)


def test_the_window_holds_the_last_speeds_read_and_actions_taken_newest_first() -> None:
    assert WINDOW_OBS.size == 28 + 3 * 8
    memory = InputMemory(WINDOW_OBS, 0.05)
    q, q_req = np.ones(4), np.full(4, 2.0)
    speeds = [np.array([0.12, -0.24, 0.6, 9.0]) * (k + 1) for k in range(4)]
    actions = [np.array([0.1, -0.2, 0.3, 1.5]) * (k + 1) for k in range(4)]
    obs = memory.observe(q, speeds[0], q_req)
    assert not obs[28:].any()  # nothing read before the first period
    for k in range(4):
        memory.acted(actions[k])
        obs = memory.observe(q, speeds[(k + 1) % 4], q_req)
    window = obs[28:].reshape(3, 8)
    # newest first: the speed read at period 3 and the action taken on it, then 2, then 1
    for row, k in enumerate((3, 2, 1)):
        np.testing.assert_allclose(window[row, :4], np.clip(speeds[k] / 1.2, -2, 2), rtol=1e-6)
        np.testing.assert_allclose(window[row, 4:], np.clip(actions[k], -1, 1), rtol=1e-6)
    low, high = policy_env.observation_bounds(WINDOW_OBS)
    assert np.all(obs >= low) and np.all(obs <= high)
    memory.reset()
    assert not memory.window.any()
    with pytest.raises(ValueError, match="history"):
        ObservationConfig(previous_action=True, history=-1)
    with pytest.raises(ValueError, match="history"):
        ObservationConfig(previous_action=True, history=2.5)  # type: ignore[arg-type]


STEP_OBS = ObservationConfig(previous_action=True, integral_tau=1.0, target_step=True)


def test_the_target_step_is_the_error_read_when_the_target_changed() -> None:
    """Held from the first reading with a target until the target changes, whatever the arm
    does meanwhile: past the goal the error changes sign, the step does not."""
    assert STEP_OBS.size == 28 + 4
    memory = InputMemory(STEP_OBS, 0.05)
    half = memory.workspace.half_range
    goal = np.array([1.5, 1.4, 2.0, 3.0])
    obs = memory.observe(np.ones(4), np.zeros(4), goal)
    np.testing.assert_allclose(obs[28:], (goal - 1.0) / half, rtol=1e-6)
    past = goal + 0.01  # an overshoot on every joint
    obs = memory.observe(past, np.zeros(4), goal.copy())  # equal values: the same target
    np.testing.assert_allclose(obs[28:], (goal - 1.0) / half, rtol=1e-6)
    assert np.all(obs[12:16] < 0) and np.all(obs[28:] > 0)  # the error says back, the step ahead
    new = goal - 0.2
    obs = memory.observe(past, np.zeros(4), new)
    np.testing.assert_allclose(obs[28:], (new - past) / half, rtol=1e-6)
    low, high = policy_env.observation_bounds(STEP_OBS)
    assert np.all(obs >= low) and np.all(obs <= high)
    assert low.size == STEP_OBS.size
    memory.reset()
    assert not memory.step.any()
    obs = memory.observe(new, np.zeros(4), new)  # after a reset the same target is new again
    assert not obs[28:].any()
    with pytest.raises(ValueError, match="target_step"):
        ObservationConfig(previous_action=True, target_step=1)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "obs_config", [MEMORY_OBS, WINDOW_OBS, STEP_OBS], ids=["memory", "window", "step"]
)
def test_controller_feeds_the_network_what_the_env_fed_it(obs_config: ObservationConfig) -> None:
    """Step the env with the actor's own actions (a new goal every second); the controller,
    given the readings the env observed, sends exactly those actions (times the limits) at
    every step."""
    weights = random_weights(obs_config)
    env = ReachAlphaEnv(EnvConfig(observation=obs_config, sensor_noise=True, goal_every_s=1.0))
    controller = LearnedController(weights)
    obs, _ = env.reset(seed=3)
    controller.reset()
    targets = set()
    for k in range(60):
        targets.add(env.target.tobytes())
        q, qdot = env.last_reading
        sent = controller.act(ControlState(q, qdot, k * env.control_dt), env.target)
        action = weights.forward(obs)
        np.testing.assert_allclose(sent, action * weights.current_limits_mA, rtol=1e-5)
        obs, *_ = env.step(action)
    assert controller.control_hz == 20.0
    assert len(targets) == 3


def test_controller_rejects_bad_input() -> None:
    controller = LearnedController(random_weights(MEMORY_OBS))
    state = ControlState(np.full(4, np.nan), np.zeros(4), 0.0)
    with pytest.raises(ValueError, match="finite"):
        controller.act(state, np.ones(4))
    with pytest.raises(ValueError, match="target"):
        controller.act(ControlState(np.ones(4), np.zeros(4), 0.0), np.ones(3))


def test_weights_file_round_trip_keeps_memory_config(tmp_path: Path) -> None:
    weights = random_weights(MEMORY_OBS, hz=10.0)
    path = tmp_path / "actor.npz"
    arrays: dict[str, Any] = {f"W{i}": w for i, w in enumerate(weights.weights)}
    arrays.update({f"b{i}": b for i, b in enumerate(weights.biases)})
    np.savez(path, **arrays)
    meta = dict(weights.metadata, observation=MEMORY_OBS.to_dict())
    path.with_suffix(".json").write_text(json.dumps(meta))
    loaded = ActorWeights.load(path)
    assert loaded.observation == MEMORY_OBS
    assert LearnedController(loaded).control_hz == 10.0


def test_potential_shaping_telescopes() -> None:
    """With gamma 1 the shaping terms of a trajectory sum to Phi(end) - Phi(start): progress
    is rewarded, but no path to the same end earns more than another."""
    config = RewardConfig(mode=RewardMode.SHAPED, potential_weight=3.0, potential_gamma=1.0)
    rng = np.random.default_rng(1)
    q_req = np.array([3.0, 1.5, 1.5, 1.5])
    path = [q_req + rng.normal(0, 0.5, 4) for _ in range(30)]
    z = np.zeros(4)
    total = sum(
        reward_terms(b, z, q_req, z, z, True, config, prev_q=a)["potential"]
        for a, b in zip(path, path[1:], strict=False)
    )
    half_range = np.array([2.7, 1.2, 1.2, 1.15])

    def phi(q: np.ndarray) -> float:
        return -3.0 * float(np.mean(np.abs(q_req - q) / half_range))

    assert total == pytest.approx(phi(path[-1]) - phi(path[0]), abs=1e-9)


def test_potential_gamma_must_be_the_agents() -> None:
    env = EnvConfig(reward=RewardConfig(potential_weight=1.0, potential_gamma=0.9))
    with pytest.raises(ValueError, match="potential_gamma"):
        DDPGConfig(env=env, gamma=0.99)
    DDPGConfig(env=dataclasses.replace(env, reward=RewardConfig(potential_weight=1.0)))


def test_away_term_charges_moving_away_from_the_goal_only() -> None:
    config = RewardConfig(mode=RewardMode.SHAPED, away_weight=2.0, distance_weight=0.0)
    q_req = np.full(4, 1.5)
    q = np.array([1.4, 1.6, 1.4, 1.6])  # E and C below the goal, D and B above
    towards = np.array([0.5, -0.5, 0.5, -0.5])
    z = np.zeros(4)
    assert reward_terms(q, towards, q_req, z, z, True, config)["away"] == 0.0
    away = reward_terms(q, -towards, q_req, z, z, True, config)["away"]
    speeds = np.asarray(policy_env.NO_LOAD_SPEEDS)
    assert away == pytest.approx(-2.0 * float(np.mean(0.5 / speeds)))


def test_fine_precision_term_tells_one_milliradian_from_five() -> None:
    config = RewardConfig(mode=RewardMode.SHAPED, fine_weight=1.0, distance_weight=0.0)
    q_req, z = np.full(4, 1.5), np.zeros(4)

    def fine(error: float) -> float:
        return reward_terms(q_req - error, z, q_req, z, z, True, config)["precision_fine"]

    assert fine(0.0) == 0.0
    assert fine(0.001) == pytest.approx(-1 + np.exp(-0.5 * (1 / 4) ** 2))
    assert fine(0.005) - fine(0.001) < -0.5  # the coarse term moves by 0.04 over the same
    assert fine(0.1) == pytest.approx(-1.0)


def test_the_shipped_ddpg_is_learned_from_scratch_and_says_how() -> None:
    weights = ActorWeights.load(LEARNED_WEIGHTS)
    provenance = weights.provenance
    assert provenance is not None and provenance.from_scratch
    assert provenance.demonstrations == "none" and provenance.teacher == "none"
    assert provenance.algorithm in ("DDPG", "TD3")  # no behaviour cloning suffix
    assert "tools/train.py" in provenance.command and provenance.env_steps > 0
    config = DDPGConfig.from_dict(weights.metadata["config"])
    assert config.demo_episodes == 0 and config.bc_weight == 0 and config.init_actor is None
    assert weights.observation.has_memory  # its memory channels travel with it
    controller = make_controller()
    assert isinstance(controller, LearnedController) and controller.control_hz == 20.0


# -- another arm -----------------------------------------------------------------------------


def bravo_actor_file(tmp_path: Path, seed: int = 0) -> Path:
    """A (random) actor saved by training's own writer for the scratch recipe on the Bravo."""
    import torch

    from policy.rl.checkpoint import save_actor_npz
    from policy.rl.networks import Actor

    config = DDPGConfig.scratch(hidden=(16, 16)).on(BRAVO7)
    torch.manual_seed(seed)
    actor = Actor(config.env.observation.size_for(6), 6, config.hidden)
    path = tmp_path / "bravo_actor.npz"
    save_actor_npz(path, actor, config)
    return path


def test_a_bravo_actor_round_trips_with_its_arm(tmp_path: Path) -> None:
    path = bravo_actor_file(tmp_path)
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["arm"] == "bravo7"
    assert meta["current_limits_mA"] == [2000.0, 2000.0, 1500.0, 1500.0, 1500.0, 1000.0]
    weights = ActorWeights.load(path)
    assert weights.model is BRAVO7 and weights.weights[0].shape == (16, 42)
    np.testing.assert_array_equal(weights.current_limits_mA, BRAVO7.current_limits_mA)
    # the controller builds the inputs the Bravo env built, step by step
    env = ReachAlphaEnv(DDPGConfig.scratch().on(BRAVO7).env)
    controller = LearnedController(weights, model=BRAVO7)
    obs, _ = env.reset(seed=4)
    for k in range(40):
        q, qdot = env.last_reading
        sent = controller.act(ControlState(q, qdot, k * env.control_dt), env.target)
        action = weights.forward(obs)
        np.testing.assert_allclose(sent, action * weights.current_limits_mA, rtol=1e-5)
        obs, *_ = env.step(action)
    with pytest.raises(ValueError, match=r"6 finite angles \(rad, G F E D C B\)"):
        controller.act(ControlState(np.ones(6), np.zeros(6), 0.0), np.ones(4))
    # a file written before the arm was recorded (the shipped ones) is an Alpha 5's
    del meta["arm"]
    path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"needs 4 finite values >= 0 \(Reach Alpha 5\)"):
        ActorWeights.load(path)
    assert "arm" not in json.loads(LEARNED_WEIGHTS.with_suffix(".json").read_text())
    assert ActorWeights.load(LEARNED_WEIGHTS).model is ALPHA5


@pytest.mark.parametrize("arm", [ALPHA5, BRAVO7])
def test_ddpg_refuses_an_actor_for_another_arm_in_one_line(tmp_path: Path, arm: ArmModel) -> None:
    bravo = {"weights": str(bravo_actor_file(tmp_path))}
    shipped: dict[str, str] = {}  # the shipped actor: the Alpha 5's
    mine, other = (shipped, bravo) if arm is ALPHA5 else (bravo, shipped)
    other_model = BRAVO7 if arm is ALPHA5 else ALPHA5
    with pytest.raises(ControllerModelError) as caught:
        load_controller("ddpg", arm=arm, **other)
    message = str(caught.value)
    assert "\n" not in message
    assert (
        f"the weights hold an actor for the {other_model.title} ({other_model.n_joints} "
        f"joints), not the {arm.title}: drive a {other_model.title} with it (reach-driver "
        f"--arm {other_model.name}) or train one for the {arm.title} (tools/train.py --arm "
        f"{arm.name})"
    ) in message
    own = load_controller("ddpg", arm=arm, **mine)
    assert isinstance(own, LearnedController) and own.model is arm
