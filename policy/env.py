"""Gymnasium environment `ReachAlpha-v0`: the four joints E D C B of the MuJoCo Alpha 5.

The env steps `reach_sim_bridge.arm.Alpha5Arm` directly (the same arm and motor model the
virtual arm serves on the wire), so a policy trained here meets the same physics in the loop.
Actions in [-1, 1]^4 are currents as a fraction of each joint's current limit.

Gymnasium 1.x has no plugin entry points any more, so importing this module registers the env;
`gym.make("policy.env:ReachAlpha-v0")` imports and registers in one go.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import gymnasium as gym
import numpy as np

from policy.arm import ArmLike
from policy.observation import (
    WORKSPACE_HALF_RANGE,
    WORKSPACE_HIGH,
    WORKSPACE_LOW,
    ObservationConfig,
    build_observation,
    observation_bounds,
)
from protocol.alpha5 import N_JOINTS
from reach_sim_bridge.faults import SensorNoise
from reach_sim_bridge.motor import no_load_speed

ENV_ID = "ReachAlpha-v0"
#: rad/s per joint at 24 V (reach_sim_bridge/model/README.md): scales the shaped reward's speed
NO_LOAD_SPEEDS = np.asarray(no_load_speed(), dtype=np.float64)
#: what `EnvConfig.sensor_noise` switches on (the sim's one noise, Table I's sigmas)
SENSOR_NOISE = SensorNoise()


class RewardMode(str, Enum):
    PAPER = "paper"  # -1 + exp(-0.5 (|q - q_req| / sigma)^2), -10 per step out of bounds
    SHAPED = "shaped"  # per-joint paper terms + distance, and calm-arrival penalties


@dataclass(frozen=True)
class RewardConfig:
    """Reward terms. `PAPER` uses only `sigma` and `out_of_bounds`.

    The paper's -10 is paid for EVERY step spent outside the bounds and the episode goes on:
    a one-off terminal -10 would make crashing out cheaper than ~-100 for staying inside
    (Carlucho et al., OCEANS 2020, read with care).
    """

    mode: RewardMode = RewardMode.PAPER
    sigma: float = 0.018  # rad
    out_of_bounds: float = -10.0
    distance_weight: float = 1.0  # x mean |e| / half-range: a gradient far from the target
    near_scale: float = 0.05  # rad: width of the gate that switches on the penalties below
    velocity_weight: float = 0.0  # x mean gate * |qdot| / no-load speed
    action_change_weight: float = 0.0  # x mean gate * |a - a_prev|


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines an episode; serialisable so it can ship beside the weights.

    control_hz: 20 Hz by default: the paper does not state its rate, but its mean integral
    error (58.27 over 20 random 20 s episodes) is the size of |e| summed per step at ~20 Hz.
    """

    control_hz: float = 20.0
    episode_s: float = 20.0
    physics_dt: float = 0.002
    observation: ObservationConfig = field(default_factory=ObservationConfig.paper)
    reward: RewardConfig = field(default_factory=RewardConfig)
    bounds_margin: float = 0.3  # rad outside the workspace before a step counts as out of bounds
    sensor_noise: bool = False  # sigma 0.002 rad on q, 0.02 rad/s on qdot
    torque_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    #: if set, each episode draws each joint's torque scale uniformly in [low, torque_scale]
    torque_scale_low: tuple[float, float, float, float] | None = None
    #: relative perturbation of the model parameters per episode (0.1 = +-10 %), 0 disables
    param_perturbation: float = 0.0
    #: starts and goals at most this far apart per joint (rad); None = whole workspace
    max_step: float | None = None
    #: draw starts and goals (and put the bounds around) this range instead of the evaluation
    #: workspace, e.g. B over most of its turn for the paper's scenarios (B up to 5.65 rad)
    workspace_low: tuple[float, float, float, float] | None = None
    workspace_high: tuple[float, float, float, float] | None = None

    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of the episodes' starts and goals, rad, E D C B."""
        low = WORKSPACE_LOW if self.workspace_low is None else np.asarray(self.workspace_low)
        high = WORKSPACE_HIGH if self.workspace_high is None else np.asarray(self.workspace_high)
        if low.shape != (N_JOINTS,) or high.shape != (N_JOINTS,) or np.any(low >= high):
            raise ValueError(f"workspace must be 4 ranges low < high, got {low} .. {high}")
        return low.astype(np.float64), high.astype(np.float64)

    @property
    def steps_per_episode(self) -> int:
        return int(round(self.episode_s * self.control_hz))

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["reward"]["mode"] = self.reward.mode.value
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EnvConfig:
        data = dict(data)
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown env config keys: {sorted(unknown)}")
        if "observation" in data:
            data["observation"] = ObservationConfig.from_dict(data["observation"])
        if "reward" in data:
            reward = dict(data["reward"])
            reward["mode"] = RewardMode(reward.get("mode", "paper"))
            data["reward"] = RewardConfig(**reward)
        for key in ("torque_scale", "torque_scale_low", "workspace_low", "workspace_high"):
            if data.get(key) is not None:
                data[key] = tuple(float(x) for x in data[key])
        return cls(**data)


def compute_reward(
    q: np.ndarray,
    qdot: np.ndarray,
    q_req: np.ndarray,
    action: np.ndarray,
    prev_action: np.ndarray,
    in_bounds: bool,
    config: RewardConfig,
) -> float:
    """One step's reward from the TRUE state (never the noisy readings)."""
    if not in_bounds:
        return float(config.out_of_bounds)
    error = q_req - q
    if config.mode is RewardMode.PAPER:
        return float(-1.0 + np.exp(-0.5 * (np.linalg.norm(error) / config.sigma) ** 2))
    gate = np.exp(-0.5 * (error / config.near_scale) ** 2)
    reward = -1.0 + np.mean(np.exp(-0.5 * (error / config.sigma) ** 2))
    reward -= config.distance_weight * np.mean(np.abs(error) / WORKSPACE_HALF_RANGE)
    reward -= config.velocity_weight * np.mean(gate * np.abs(qdot) / NO_LOAD_SPEEDS)
    reward -= config.action_change_weight * np.mean(gate * np.abs(action - prev_action))
    return float(reward)


def default_arm_factory(config: EnvConfig) -> ArmLike:
    """The MuJoCo arm at its nominal parameters."""
    from reach_sim_bridge.arm import Alpha5Arm

    arm: ArmLike = Alpha5Arm(dt=config.physics_dt)
    return arm


class ReachAlphaEnv(gym.Env[np.ndarray, np.ndarray]):
    """Reach random goals from random starts in 20 s; no termination, only truncation."""

    metadata = {"render_modes": []}

    def __init__(
        self,
        config: EnvConfig | None = None,
        arm_factory: Callable[[EnvConfig], ArmLike] | None = None,
        **overrides: Any,
    ) -> None:
        config = config or EnvConfig()
        if overrides:
            config = dataclasses.replace(config, **overrides)
        if config.control_hz <= 0 or config.episode_s <= 0:
            raise ValueError("control_hz and episode_s must be positive")
        self.config = config
        #: put each step's mean |tau qdot| over the period in info["power"] (W, per joint);
        #: evaluation switches it on, training leaves the faster whole-period step
        self.measure_power = False
        self._arm_factory = arm_factory or default_arm_factory
        self.n_substeps = max(1, int(round(1.0 / (config.control_hz * config.physics_dt))))
        self.control_dt = self.n_substeps * config.physics_dt
        low, high = observation_bounds(config.observation)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)
        self._obs_low, self._obs_high = low, high
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(N_JOINTS,), dtype=np.float32)
        self.arm: ArmLike = self._arm_factory(config)
        self._nominal_params = getattr(self.arm, "params", None)
        limits = np.asarray(self.arm.position_limits, dtype=np.float64)
        self.workspace_low, self.workspace_high = config.workspace()
        self.bounds_low = np.maximum(self.workspace_low - config.bounds_margin, limits[:, 0])
        self.bounds_high = np.minimum(self.workspace_high + config.bounds_margin, limits[:, 1])
        self.current_limits_mA = np.asarray(self.arm.current_limits_mA, dtype=np.float64).copy()
        self.target = self.workspace_low.copy()
        self.start = self.workspace_low.copy()
        self.prev_action = np.zeros(N_JOINTS)
        self.steps = 0
        self.last_reading = (self.start.copy(), np.zeros(N_JOINTS))

    # -- gymnasium API -------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Random start and goal; `options` may fix them: {"start": q0, "target": q_req}."""
        super().reset(seed=seed)
        options = options or {}
        cfg = self.config
        if cfg.param_perturbation > 0:
            if self._nominal_params is None:
                raise ValueError("param_perturbation needs an arm with params / set_params")
            perturbed = self._nominal_params.randomized(self.np_random, cfg.param_perturbation)
            self.arm.set_params(perturbed)  # type: ignore[attr-defined]
        low, high = self.workspace_low, self.workspace_high
        start = self.np_random.uniform(low, high)
        target = self.np_random.uniform(low, high)
        if cfg.max_step is not None:
            step = self.np_random.uniform(-cfg.max_step, cfg.max_step, size=N_JOINTS)
            target = np.clip(start + step, low, high)
        scale = np.asarray(cfg.torque_scale, dtype=np.float64)
        if cfg.torque_scale_low is not None:
            scale = self.np_random.uniform(np.asarray(cfg.torque_scale_low), scale)
        if "start" in options:
            start = self._joint_vector(options["start"], "start")
        if "target" in options:
            target = self._joint_vector(options["target"], "target")
        if "torque_scale" in options:
            scale = self._joint_vector(options["torque_scale"], "torque_scale")
        self.start, self.target = start, target
        self.arm.torque_scale = scale.copy()
        self.arm.reset(q=start.copy())
        self.prev_action = np.zeros(N_JOINTS)
        self.steps = 0
        return self._observe(), self._info(in_bounds=True)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (N_JOINTS,):
            raise ValueError(f"action must have shape (4,), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action}")
        action = np.clip(action, -1.0, 1.0)
        currents = action * self.current_limits_mA
        power = None
        if self.measure_power:
            # one physics step at a time, |tau qdot| at the physics rate (as the direct backend)
            work = np.zeros(N_JOINTS)
            for _ in range(self.n_substeps):
                self.arm.step(currents, n=1)
                work += np.abs(self.arm.tau * self.arm.qdot)
            power = work / self.n_substeps
        else:
            self.arm.step(currents, n=self.n_substeps)
        self.steps += 1
        q, qdot = np.asarray(self.arm.q), np.asarray(self.arm.qdot)
        in_bounds = bool(np.all((q > self.bounds_low) & (q < self.bounds_high)))
        reward = compute_reward(
            q, qdot, self.target, action, self.prev_action, in_bounds, self.config.reward
        )
        self.prev_action = action
        truncated = self.steps >= self.config.steps_per_episode
        info = self._info(in_bounds)
        if power is not None:
            info["power"] = power
        return self._observe(), reward, False, truncated, info

    # -- helpers -------------------------------------------------------------------------
    def readings(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles and speeds as a sensor reports them (with noise if configured)."""
        q = np.array(self.arm.q, dtype=np.float64)
        qdot = np.array(self.arm.qdot, dtype=np.float64)
        if self.config.sensor_noise:
            q, qdot = SENSOR_NOISE.apply(q, qdot, self.np_random)
        return q, qdot

    def _observe(self) -> np.ndarray:
        q, qdot = self.readings()
        self.last_reading = (q, qdot)
        obs = build_observation(q, qdot, self.target, self.config.observation)
        return np.clip(obs, self._obs_low, self._obs_high)

    def _info(self, in_bounds: bool) -> dict[str, Any]:
        return {
            "q": np.array(self.arm.q, dtype=np.float64),
            "qdot": np.array(self.arm.qdot, dtype=np.float64),
            "target": self.target.copy(),
            "time": self.steps * self.control_dt,
            "in_bounds": in_bounds,
        }

    @staticmethod
    def _joint_vector(value: Any, name: str) -> np.ndarray:
        arr = np.asarray(value, dtype=np.float64)
        if arr.shape != (N_JOINTS,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"option {name!r} must be 4 finite numbers (E D C B), got {value!r}")
        return arr


def register_envs() -> None:
    """Register `ReachAlpha-v0` (idempotent)."""
    if ENV_ID not in gym.registry:
        gym.register(
            id=ENV_ID,
            entry_point="policy.env:ReachAlphaEnv",
            max_episode_steps=None,
        )


register_envs()
