"""Gymnasium environment `ReachAlpha-v0`: the rotary joints of a MuJoCo Reach arm, the four
E D C B of the Alpha 5 by default, or the six G F E D C B of the Bravo 7 (`EnvConfig.arm`).

The env steps the arm's twin (`reach_sim_bridge.model.arms.arm_twin`: the same arm and motor
model the virtual arm serves on the wire) directly, so a policy trained here meets the same
physics in the loop. `ReachAlphaEnv`'s docstring describes the spaces, rewards and episodes.

Gymnasium 1.x has no plugin entry points any more, so importing this module registers the env;
`gym.make("policy.rl.env:ReachAlpha-v0")` imports and registers in one go. As for Gymnasium's own
envs, the time limit is the `TimeLimit` wrapper that `gym.make` adds (`max_episode_steps`), not
the env: `time_limited(env)` wraps an env built directly the same way.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import TimeLimit

from policy.controllers.observation import (
    WORKSPACE_HALF_RANGE,
    InputMemory,
    ObservationConfig,
    Workspace,
    observation_bounds,
)
from policy.tasks.arm import ArmLike, CommandsInFlight
from policy.tasks.envelope import Envelope, Variant, draws, has_envelope
from protocol.models import ALPHA5, ArmModel, ArmModelName, model_named
from reach_driver.metrics import OVERSHOOT_MIN_STEP_RAD
from reach_sim_bridge.model.motor import model_no_load_speed, no_load_speed
from reach_sim_bridge.model.sensors import SensorNoise

ENV_ID = "ReachAlpha-v0"
#: rad/s per joint at 24 V (reach_sim_bridge/model/README.md): scales the shaped reward's speed
NO_LOAD_SPEEDS = np.asarray(no_load_speed(), dtype=np.float64)
#: what `EnvConfig.sensor_noise` switches on (the sim's one noise, Table I's sigmas)
SENSOR_NOISE = SensorNoise()


@dataclass(frozen=True)
class ArmScales:
    """An arm's per-joint scales in the shaped reward: the half-range of its evaluation
    workspace (distance, potential) and its motors' no-load speed (velocity, away)."""

    half_range: np.ndarray
    no_load_speed: np.ndarray

    @classmethod
    def of(cls, model: ArmModel) -> ArmScales:
        """From the model: `Workspace.of(model)`, and the no-load speed of its motors at its
        nominal supply."""
        speed = np.asarray(model_no_load_speed(model), dtype=np.float64)
        return cls(Workspace.of(model).half_range, speed)


#: the Alpha 5's (`reward_terms` uses them unless given an arm's)
ALPHA5_SCALES = ArmScales(WORKSPACE_HALF_RANGE, NO_LOAD_SPEEDS)


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
    #: x mean gate * [the command reversed its sign, both it and the previous one above
    #: `sign_flip_threshold`]: the bang-bang of a limit cycle at the goal (docs/chatter.md),
    #: counted as the rest metric counts `command_reversals` (docs/metrics.md)
    sign_flip_weight: float = 0.0
    #: fraction of the current limit both commands must exceed for a reversal to count
    #: (the rest metric's 10 %)
    sign_flip_threshold: float = 0.1
    #: x (-1 + mean_j exp(-0.5 (e_j / fine_sigma)^2)): a second, narrow precision term that
    #: still tells 1 mrad from 5 (sigma 0.018 barely does), so holding the goal to the
    #: milliradian pays (shaped mode). 0 disables
    fine_weight: float = 0.0
    fine_sigma: float = 0.004  # rad
    #: x mean_j max(0, -sign(e_j) qdot_j) / no-load speed: moving AWAY from the goal, which
    #: no shortest path does; it is what an overshoot is once the goal is crossed, and what
    #: a sag under gravity is before it (shaped mode)
    away_weight: float = 0.0
    #: potential-based shaping (Ng et al. 1999), either mode: + gamma Phi(s') - Phi(s) with
    #: Phi = -potential_weight mean_j |e_j| / half-range_j. It rewards progress towards the
    #: goal without changing which policy is optimal, provided `potential_gamma` is the
    #: agent's discount (DDPGConfig checks). 0 disables
    potential_weight: float = 0.0
    potential_gamma: float = 0.99
    #: x mean_j clip(past_j / max(|step_j|, overshoot_floor), 0, 1) for the joints whose
    #: step is at least OVERSHOOT_MIN_STEP_RAD, with past_j how far beyond its goal joint j
    #: is, signed by its step from the episode's start: the overshoot metric's own ratio
    #: (docs/metrics.md), paid each step it lasts. The floor keeps a short step from making
    #: a milliradian past its goal cost more than stopping short (shaped mode). 0 disables
    overshoot_weight: float = 0.0
    overshoot_floor: float = 0.1  # rad
    #: x mean_j (the growth this step of joint j's running maximum of that same ratio): the
    #: overshoot metric paid once, when it is made. Over an episode the term sums to
    #: -overshoot_peak_weight x mean_j (joint j's largest ratio), the metric's own figure
    #: (averaged over joints where the metric takes the worst), so a joint that crossed its
    #: goal and came back, or hovers a milliradian past it, pays no more; `overshoot_weight`
    #: pays for every step past it (shaped mode). 0 disables
    overshoot_peak_weight: float = 0.0


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines an episode; serialisable so it can ship beside the weights.

    control_hz: 20 Hz by default: the paper does not state its rate, but its mean integral
    error (58.27 over 20 random 20 s episodes) is the size of |e| summed per step at ~20 Hz.

    Per-joint tuples are in `arm`'s joint order, one value per joint; `on(model)` gives this
    config for another arm.
    """

    control_hz: float = 20.0
    episode_s: float = 20.0
    physics_dt: float = 0.002
    observation: ObservationConfig = field(default_factory=ObservationConfig.paper)
    reward: RewardConfig = field(default_factory=RewardConfig)
    bounds_margin: float = 0.3  # rad outside the workspace before a step counts as out of bounds
    sensor_noise: bool = False  # sigma 0.002 rad on q, 0.02 rad/s on qdot
    torque_scale: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)
    #: if set, each episode draws each joint's torque scale uniformly in [low, torque_scale]
    torque_scale_low: tuple[float, ...] | None = None
    #: relative perturbation of the model parameters per episode (0.1 = +-10 %), 0 disables;
    #: an arm the envelope is defined for only (`has_envelope`: the Alpha 5)
    param_perturbation: float = 0.0
    #: starts and goals at most this far apart per joint (rad); None = whole workspace
    max_step: float | None = None
    #: per joint, the share of goals drawn within `small_step` rad of the start (the others
    #: as `max_step` says). Why: the overshoot metric divides by the step, so a small step
    #: beside a long move is where an arrival's few milliradians weigh most, and goals drawn
    #: uniformly make it rare: in `scratch`, whose B spans 5.3 rad for the paper's scenarios,
    #: a B step under 0.2 rad is one goal in 14, on Table I's 2.3 rad one in 6. 0 leaves the
    #: draw and its random stream as they were. Training only: evaluation draws uniformly
    small_step_fraction: float = 0.0
    small_step: float = 0.3
    #: draw starts and goals (and put the bounds around) this range instead of the evaluation
    #: workspace, e.g. B over most of its turn for the paper's scenarios (B up to 5.65 rad)
    workspace_low: tuple[float, ...] | None = None
    workspace_high: tuple[float, ...] | None = None
    #: control latency in control periods: the action computed from the state at t takes
    #: effect at t + latency, rounded to physics steps (the previous one stays in force until
    #: then), as `policy.campaigns.direct` emulates `RunConfig.latency_periods`
    latency_periods: float = 0.0
    #: multiple of the sensor noise's sigmas (with `sensor_noise`)
    noise_scale: float = 1.0
    #: share of episodes whose arm is drawn from the uncertainty envelope
    #: (`policy.tasks.envelope.draws`, its default ranges around the nominal arm): parameters, weak
    #: joint's torque scale, noise multiple and latency all come from the draw and replace
    #: `param_perturbation`, `torque_scale(_low)`, `noise_scale` and `latency_periods` for
    #: that episode; 0 disables, 1 trains on envelope arms only. The Alpha 5 only: the
    #: envelope is drawn around its `ArmParams`
    envelope_fraction: float = 0.0
    #: draw a new goal every this many seconds within the episode (from where the arm is,
    #: as the first goal is drawn from the start; the memory channels run on, as they do at
    #: run time when a target sequence moves on), so an episode holds several arrivals
    #: instead of one; None: one goal per episode (evaluation always uses one)
    goal_every_s: float | None = None
    #: the arm (`protocol.models`): its twin, joints, workspace, limits and motors
    arm: ArmModelName = ArmModelName.ALPHA5

    def __post_init__(self) -> None:
        object.__setattr__(self, "arm", ArmModelName(model_named(self.arm).name))
        n, letters = self.model.n_joints, " ".join(self.model.joint_letters)
        for key in ("torque_scale", "torque_scale_low", "workspace_low", "workspace_high"):
            value = getattr(self, key)
            if value is not None and len(value) != n:
                raise ValueError(
                    f"{key} needs {n} values ({letters}) for the {self.model.title}, got "
                    f"{value} (EnvConfig.on(model) fits a config to an arm)"
                )
        if not 0.0 <= self.small_step_fraction <= 1.0:
            raise ValueError(
                f"small_step_fraction must be in [0, 1], got {self.small_step_fraction}"
            )
        if not self.small_step > 0:
            raise ValueError(f"small_step must be > 0 rad, got {self.small_step}")
        if self.goal_every_s is not None and not self.goal_every_s > 0:
            raise ValueError(f"goal_every_s must be > 0 or None, got {self.goal_every_s}")
        if not 0.0 <= self.envelope_fraction <= 1.0:
            raise ValueError(f"envelope_fraction must be in [0, 1], got {self.envelope_fraction}")
        if not 0.0 <= self.latency_periods <= 10.0:
            raise ValueError(f"latency_periods must be in [0, 10], got {self.latency_periods}")
        if not self.noise_scale >= 0.0:
            raise ValueError(f"noise_scale must be >= 0, got {self.noise_scale}")

    @property
    def model(self) -> ArmModel:
        """The arm's model (`arm`)."""
        return model_named(self.arm)

    def on(self, model: ArmModel) -> EnvConfig:
        """This config for an arm of `model` (itself if it is that arm's already): the
        per-joint fields written for another arm's joints become `model`'s: full torque
        (`torque_scale_low`: the base joint's range kept, the others at full torque), the
        arm's own workspace. Envelope arms and parameter perturbation are switched off for an
        arm the envelope is not defined for (`policy.tasks.envelope.has_envelope`)."""
        if model.name == self.arm.value:
            return self
        n = model.n_joints
        low = self.torque_scale_low
        fields: dict[str, Any] = {
            "arm": ArmModelName(model.name),
            "torque_scale": (1.0,) * n,
            "torque_scale_low": None if low is None else (low[0],) + (1.0,) * (n - 1),
            "workspace_low": None,
            "workspace_high": None,
        }
        if not has_envelope(model):
            fields.update(param_perturbation=0.0, envelope_fraction=0.0)
        return dataclasses.replace(self, **fields)

    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of the episodes' starts and goals, rad, in the arm's joint order: its
        evaluation workspace (`Workspace.of`) unless `workspace_low` / `workspace_high`."""
        arm = Workspace.of(self.model)
        low = np.asarray(arm.low if self.workspace_low is None else self.workspace_low)
        high = np.asarray(arm.high if self.workspace_high is None else self.workspace_high)
        n = arm.n_joints
        if low.shape != (n,) or high.shape != (n,) or np.any(low >= high):
            raise ValueError(f"workspace must be {n} ranges low < high, got {low} .. {high}")
        return low.astype(np.float64), high.astype(np.float64)

    @property
    def steps_per_episode(self) -> int:
        return int(round(self.episode_s * self.control_hz))

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["arm"] = self.arm.value
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


#: the terms of `reward_terms`, in the order they are summed
REWARD_TERMS = (
    "precision",
    "precision_fine",
    "potential",
    "distance",
    "velocity",
    "away",
    "overshoot",
    "overshoot_peak",
    "action_change",
    "sign_flip",
    "out_of_bounds",
)


def sign_flips(action: np.ndarray, prev_action: np.ndarray, threshold: float) -> np.ndarray:
    """Per joint 1.0 where the command reversed its sign with both it and the previous one
    above `threshold` (fraction of the current limit), else 0.0."""
    big = (np.abs(action) > threshold) & (np.abs(prev_action) > threshold)
    out: np.ndarray = (big & (np.sign(action) != np.sign(prev_action))).astype(np.float64)
    return out


def reward_terms(
    q: np.ndarray,
    qdot: np.ndarray,
    q_req: np.ndarray,
    action: np.ndarray,
    prev_action: np.ndarray,
    in_bounds: bool,
    config: RewardConfig,
    prev_q: np.ndarray | None = None,
    start: np.ndarray | None = None,
    scales: ArmScales = ALPHA5_SCALES,
    overshoot_peak: np.ndarray | None = None,
) -> dict[str, float]:
    """One step's reward, term by term (signed; inactive terms 0), from the TRUE state (never
    the noisy readings). Their sum in `REWARD_TERMS` order is the reward, exactly. `prev_q`
    (the true angles before the step) is needed by the potential term only, `start` (the
    episode's first angles) by the overshoot terms only, `overshoot_peak` (each joint's largest
    `overshoot_ratio` before this step) by the overshoot-peak term only; `scales` are the
    arm's."""
    terms = dict.fromkeys(REWARD_TERMS, 0.0)
    if config.potential_weight and prev_q is not None:
        terms["potential"] = config.potential_gamma * _potential(
            q, q_req, config, scales
        ) - _potential(prev_q, q_req, config, scales)
    if not in_bounds:
        terms["out_of_bounds"] = float(config.out_of_bounds)
        return terms
    error = q_req - q
    if config.mode is RewardMode.PAPER:
        terms["precision"] = float(
            -1.0 + np.exp(-0.5 * (np.linalg.norm(error) / config.sigma) ** 2)
        )
        return terms
    gate = np.exp(-0.5 * (error / config.near_scale) ** 2)
    terms["precision"] = float(-1.0 + np.mean(np.exp(-0.5 * (error / config.sigma) ** 2)))
    if config.fine_weight:
        fine = np.mean(np.exp(-0.5 * (error / config.fine_sigma) ** 2))
        terms["precision_fine"] = float(config.fine_weight * (-1.0 + fine))
    terms["distance"] = -float(config.distance_weight * np.mean(np.abs(error) / scales.half_range))
    terms["velocity"] = -float(
        config.velocity_weight * np.mean(gate * np.abs(qdot) / scales.no_load_speed)
    )
    if config.away_weight:
        away = np.maximum(0.0, -np.sign(error) * qdot) / scales.no_load_speed
        terms["away"] = -float(config.away_weight * np.mean(away))
    if config.overshoot_weight and start is not None:
        share = overshoot_ratio(q, q_req, start, config.overshoot_floor)
        terms["overshoot"] = -float(config.overshoot_weight * np.mean(share))
    if config.overshoot_peak_weight and start is not None and overshoot_peak is not None:
        ratio = overshoot_ratio(q, q_req, start, config.overshoot_floor)
        growth = np.maximum(ratio - overshoot_peak, 0.0)
        terms["overshoot_peak"] = -float(config.overshoot_peak_weight * np.mean(growth))
    terms["action_change"] = -float(
        config.action_change_weight * np.mean(gate * np.abs(action - prev_action))
    )
    if config.sign_flip_weight:
        flips = sign_flips(action, prev_action, config.sign_flip_threshold)
        terms["sign_flip"] = -float(config.sign_flip_weight * np.mean(gate * flips))
    return terms


def overshoot_ratio(
    q: np.ndarray, q_req: np.ndarray, start: np.ndarray, floor: float
) -> np.ndarray:
    """Per joint, how far past its goal it is over its step from `start` (at least `floor`),
    in [0, 1]; 0 for a joint whose step is under OVERSHOOT_MIN_STEP_RAD: the overshoot
    metric's ratio (docs/metrics.md) at one instant."""
    step = q_req - start
    moving = np.abs(step) >= OVERSHOOT_MIN_STEP_RAD
    past = (q - q_req) * np.sign(step) / np.maximum(np.abs(step), floor)
    out: np.ndarray = np.where(moving, np.clip(past, 0.0, 1.0), 0.0)
    return out


def _potential(q: np.ndarray, q_req: np.ndarray, config: RewardConfig, scales: ArmScales) -> float:
    return -float(config.potential_weight * np.mean(np.abs(q_req - q) / scales.half_range))


def compute_reward(
    q: np.ndarray,
    qdot: np.ndarray,
    q_req: np.ndarray,
    action: np.ndarray,
    prev_action: np.ndarray,
    in_bounds: bool,
    config: RewardConfig,
) -> float:
    """One step's reward: the sum of `reward_terms`."""
    terms = reward_terms(q, qdot, q_req, action, prev_action, in_bounds, config)
    return float(sum(terms.values()))


def default_arm_factory(config: EnvConfig) -> ArmLike:
    """The MuJoCo twin of the config's arm, at its nominal parameters."""
    from reach_sim_bridge.model.arms import arm_twin

    arm: ArmLike = arm_twin(config.model, dt=config.physics_dt)  # type: ignore[assignment]
    return arm


def _no_envelope(model: ArmModel, what: str) -> str:
    return (
        f"{what} draw {ALPHA5.title} arms (policy.tasks.envelope), not the {model.title}'s: "
        "set env.envelope_fraction and env.param_perturbation to 0"
    )


class ReachAlphaEnv(gym.Env[np.ndarray, np.ndarray]):
    """Reach a random goal from a random start with the arm's rotary joints (`EnvConfig.arm`):
    E D C B on the Alpha 5 (the default), G F E D C B on the Bravo 7; the jaw is not moved.

    ## Action space

    `Box(-1, 1, (n,), float32)`, n the arm's joints: each joint's current as a fraction of its
    current limit (the twin's, the model's defaults), clipped to [-1, 1] and held for the
    control period (`n_substeps` physics steps of 2 ms).

    | Num | Alpha 5: current of | x mA | Bravo 7: current of | x mA |
    |-----|---------------------|------|---------------------|------|
    | 0   | joint E             | 600  | joint G             | 2000 |
    | 1   | joint D             | 600  | joint F             | 2000 |
    | 2   | joint C             | 600  | joint E             | 1500 |
    | 3   | joint B             | 300  | joint D             | 1500 |
    | 4   |                     |      | joint C             | 1500 |
    | 5   |                     |      | joint B             | 1000 |

    ## Observation space

    `Box(low, high, (m,), float32)` with finite bounds (`observation_bounds`), built by
    `policy.controllers.observation.build_observation`, the function the deployed controller calls.
    Each group is n entries, in the arm's joint order. Readings are clipped to
    [-0.5, 2 pi + 0.5] rad and +-5 rad/s first; with `sensor_noise`, q and qdot are as a sensor
    reports them (sigma 0.002 rad, 0.02 rad/s), q_req exact.

    | Group | Observation          | `ObservationConfig.paper()` | default                   |
    |-------|----------------------|-----------------------------|---------------------------|
    | 0     | joint angles q       | rad                         | (q - centre) / half-range |
    | 1     | joint speeds qdot    | rad/s                       | qdot / 1.2 rad/s          |
    | 2     | goal q_req           | rad                         | (q_req - centre) / h.-r.  |
    | 3     | error e = q_req - q  | -                           | e / half-range            |
    | 4     | fine error           | -                           | tanh(e / 0.05 rad)        |
    | m     | Alpha 5 / Bravo 7    | 12 / 18                     | 20 / 30                   |

    centre and half-range are the arm's evaluation workspace's (`Workspace.of`). The memory
    channels (`previous_action`, `integral_tau`, `history`, `target_step`) add n entries per
    group.

    ## Rewards

    From the TRUE state (never the noisy readings), `RewardConfig`. `info["reward_terms"]`
    holds each term, signed (inactive ones 0); they sum to the reward.

    | Term            | `paper` mode                         | `shaped` mode                       |
    |-----------------|--------------------------------------|-------------------------------------|
    | `precision`     | -1 + exp(-0.5 (norm(e) / sigma)^2)   | -1 + mean_j exp(-0.5 (e_j/sigma)^2) |
    | `distance`      | 0                                    | -w_d mean_j abs(e_j) / half-range_j |
    | `velocity`      | 0                                    | -w_v mean_j g_j abs(qdot_j) / v0_j  |
    | `action_change` | 0                                    | -w_a mean_j g_j abs(a_j - a_prev_j) |
    | `sign_flip`     | 0                                    | -w_f mean_j g_j flip_j              |
    | `out_of_bounds` | -10, alone, on a step ending with a joint outside the bounds (both)       |

    sigma 0.018 rad; gate g_j = exp(-0.5 (e_j / near_scale)^2) (calm arrival is asked for
    near the goal only); v0_j the joint's no-load speed; flip_j 1 when the command a_j
    reversed the sign of a_prev_j with both above `sign_flip_threshold` (10 % of the limit,
    as the rest metric counts reversals), else 0; bounds: the workspace widened by
    `bounds_margin` (0.3 rad), within the joint limits.

    ## Latency

    With `latency_periods` L (or an envelope arm's), the action computed from the
    observation at t is applied from t + L (rounded to physics steps of 2 ms) and the
    previous one stays in force until then, exactly as `policy.campaigns.direct` runs
    `RunConfig.latency_periods`: the observation is the state the action was computed from.

    ## Starting state

    At rest at a start q0 drawn uniformly in the workspace (`Workspace.of`; the Alpha 5's
    E [0.4, 5.8], D [0.5, 2.9], C [0.5, 2.9], B [0.5, 2.8] rad; the Bravo 7's its factory
    envelope 0.4 rad in from each end: G D B [0.4, 5.88], F E C [0.4, 2.8] rad; or
    `workspace_low` / `workspace_high`), the goal drawn in the same range (or within
    `max_step` of q0). Per episode, if configured: each joint's
    torque scale uniform in [`torque_scale_low`, `torque_scale`], the arm's parameters scaled
    by U(1 +- `param_perturbation`). With `envelope_fraction` > 0, that share of episodes
    runs on an arm drawn from `policy.tasks.envelope` instead (`draws(1, seed)` with a seed from
    the env's generator: friction, armature, masses, buoyancy, one weak joint, noise multiple,
    latency; infeasible arms are redrawn); `info["variant"]` names it. Both perturb the Alpha
    5's `ArmParams`: on another arm either is refused (ValueError). `reset(options=...)` may
    fix "start", "target", "torque_scale", and "variant" (a `policy.tasks.envelope.Variant`).

    ## Episode end

    | Ends by     | When                                                                     |
    |-------------|--------------------------------------------------------------------------|
    | termination | never: leaving the bounds costs -10 per step and the episode goes on     |
    | truncation  | `EnvConfig.steps_per_episode` steps (400: 20 s at 20 Hz), by `TimeLimit` |

    The env itself never truncates: `gym.make("ReachAlpha-v0")` wraps it in `TimeLimit` with
    the default 400 steps (pass `max_episode_steps=config.steps_per_episode` with a config of
    another length), `time_limited(env)` wraps an env built directly.

    ## Info

    `q`, `qdot` (true, rad, rad/s), `target` (rad), `time` (s since reset), `in_bounds`,
    `variant` (the envelope arm's name, or None);
    from `step` also `reward_terms`, and `power` (W per joint) when `measure_power` is set.
    """

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
        steps = 1.0 / (config.control_hz * config.physics_dt)
        if abs(steps - round(steps)) > 1e-6 * steps:
            # rounded silently, a control period would not be 1 / control_hz: the episode's
            # steps and a controller run at the weights' control_hz would be off by as much
            near = sorted({max(1, math.floor(steps)), math.ceil(steps)})
            rates = " or ".join(f"{1.0 / (n * config.physics_dt):.6g} Hz ({n} steps)" for n in near)
            raise ValueError(
                f"control_hz {config.control_hz:g} is not a whole number of physics steps of "
                f"{config.physics_dt:g} s ({steps:.4g}); use {rates}"
            )
        self.config = config
        #: put each step's mean |tau qdot| over the period in info["power"] (W, per joint);
        #: evaluation switches it on, training leaves the faster whole-period step
        self.measure_power = False
        self._arm_factory = arm_factory or default_arm_factory
        self.n_substeps = max(1, int(round(1.0 / (config.control_hz * config.physics_dt))))
        self.control_dt = self.n_substeps * config.physics_dt
        #: the arm's model, and what the inputs and the reward are normalised by
        self.model = config.model
        self.n_joints = n = self.model.n_joints
        self.arm_workspace = Workspace.of(self.model)
        self.scales = ArmScales.of(self.model)
        low, high = observation_bounds(config.observation, self.arm_workspace)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)
        self._obs_low, self._obs_high = low, high
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(n,), dtype=np.float32)
        self.arm: ArmLike = self._arm_factory(config)
        self._nominal_params = getattr(self.arm, "params", None)
        if not has_envelope(self.model) and (config.envelope_fraction or config.param_perturbation):
            raise ValueError(_no_envelope(self.model, "envelope arms and param_perturbation"))
        limits = np.asarray(self.arm.position_limits, dtype=np.float64)
        if limits.shape != (n, 2):
            raise ValueError(
                f"the arm has {limits.shape[0]} joints, the {self.model.title} {n}: "
                "an arm_factory for another arm than env.arm"
            )
        self.workspace_low, self.workspace_high = config.workspace()
        self.bounds_low = np.maximum(self.workspace_low - config.bounds_margin, limits[:, 0])
        self.bounds_high = np.minimum(self.workspace_high + config.bounds_margin, limits[:, 1])
        self.current_limits_mA = np.asarray(self.arm.current_limits_mA, dtype=np.float64).copy()
        self.target = self.workspace_low.copy()
        self.start = self.workspace_low.copy()
        self.prev_action = np.zeros(n)
        self.steps = 0
        self.last_reading = (self.start.copy(), np.zeros(n))
        #: this episode's envelope arm (None: the configured arm) and what it sets
        self.variant: Variant | None = None
        self.latency_substeps = self._latency(config.latency_periods)
        self.noise = SENSOR_NOISE.scaled(config.noise_scale)
        self._in_flight = CommandsInFlight(self.latency_substeps, n)
        #: the observation's memory channels (previous action, error integral), if any
        self.memory = InputMemory(config.observation, self.control_dt, self.arm_workspace)

    # -- gymnasium API -------------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Random start and goal; `options` may fix them: {"start": q0, "target": q_req}."""
        super().reset(seed=seed)
        options = options or {}
        cfg = self.config
        variant: Variant | None = options.get("variant")
        if variant is None and cfg.envelope_fraction > 0:
            if self.np_random.uniform() < cfg.envelope_fraction:
                variant = self.draw_variant()
        if variant is not None:
            if self._nominal_params is None:
                raise ValueError("envelope arms need an arm with params / set_params")
            self.arm.set_params(variant.params)  # type: ignore[attr-defined]
        elif cfg.param_perturbation > 0:
            if self._nominal_params is None:
                raise ValueError("param_perturbation needs an arm with params / set_params")
            perturbed = self._nominal_params.randomized(self.np_random, cfg.param_perturbation)
            self.arm.set_params(perturbed)  # type: ignore[attr-defined]
        elif self.variant is not None:  # back to the nominal arm after an envelope one
            self.arm.set_params(self._nominal_params)  # type: ignore[attr-defined]
        start = self.np_random.uniform(self.workspace_low, self.workspace_high)
        target = self._draw_goal(start)
        scale = np.asarray(cfg.torque_scale, dtype=np.float64)
        if cfg.torque_scale_low is not None:
            scale = self.np_random.uniform(np.asarray(cfg.torque_scale_low), scale)
        if "start" in options:
            start = self._joint_vector(options["start"], "start")
        if "target" in options:
            target = self._joint_vector(options["target"], "target")
        if variant is not None:
            scale = np.asarray(variant.torque_scale, dtype=np.float64)
        if "torque_scale" in options:
            scale = self._joint_vector(options["torque_scale"], "torque_scale")
        self.variant = variant
        latency = cfg.latency_periods if variant is None else variant.latency_periods
        noise_scale = cfg.noise_scale if variant is None else variant.noise_scale
        self.latency_substeps = self._latency(latency)
        self.noise = SENSOR_NOISE.scaled(noise_scale)
        self.start, self.target = start, target
        self.arm.torque_scale = scale.copy()
        self.arm.reset(q=start.copy())
        self.prev_action = np.zeros(self.n_joints)
        #: each joint's largest overshoot ratio so far this episode (`overshoot_peak_weight`)
        self.overshoot_peak = np.zeros(self.n_joints)
        self._in_flight = CommandsInFlight(self.latency_substeps, self.n_joints)
        self.steps = 0
        self.memory.reset()
        return self._observe(), self._info(in_bounds=True)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.n_joints,):
            raise ValueError(f"action must have shape ({self.n_joints},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action}")
        action = np.clip(action, -1.0, 1.0)
        currents = action * self.current_limits_mA
        prev_q = np.array(self.arm.q, dtype=np.float64)
        power = self._advance(currents)
        self.steps += 1
        q, qdot = np.asarray(self.arm.q), np.asarray(self.arm.qdot)
        in_bounds = bool(np.all((q > self.bounds_low) & (q < self.bounds_high)))
        terms = reward_terms(
            q,
            qdot,
            self.target,
            action,
            self.prev_action,
            in_bounds,
            self.config.reward,
            prev_q,
            self.start,
            self.scales,
            self.overshoot_peak,
        )
        self.overshoot_peak = np.maximum(
            self.overshoot_peak,
            overshoot_ratio(q, self.target, self.start, self.config.reward.overshoot_floor),
        )
        self.prev_action = action
        self.memory.acted(action)
        every = self.config.goal_every_s
        if every is not None and self.steps % max(1, round(every * self.config.control_hz)) == 0:
            self.start = q.copy()
            self.target = self._draw_goal(self.start)
            self.overshoot_peak = np.zeros(self.n_joints)
        info = self._info(in_bounds)
        info["reward_terms"] = terms
        if power is not None:
            info["power"] = power
        # never terminated, never truncated: the time limit is TimeLimit's (`time_limited`)
        return self._observe(), float(sum(terms.values())), False, False, info

    # -- helpers -------------------------------------------------------------------------
    def _draw_goal(self, start: np.ndarray) -> np.ndarray:
        """A goal in the workspace (within `max_step` of `start` per joint, if set; each
        joint within `small_step` of it with probability `small_step_fraction`)."""
        cfg = self.config
        low, high = self.workspace_low, self.workspace_high
        if cfg.max_step is None:
            goal = self.np_random.uniform(low, high)
        else:
            step = self.np_random.uniform(-cfg.max_step, cfg.max_step, size=self.n_joints)
            goal = np.clip(start + step, low, high)
        if cfg.small_step_fraction > 0:
            near = self.np_random.uniform(-cfg.small_step, cfg.small_step, size=self.n_joints)
            small = self.np_random.uniform(size=self.n_joints) < cfg.small_step_fraction
            goal = np.where(small, np.clip(start + near, low, high), goal)
        return goal

    def draw_variant(self) -> Variant:
        """A feasible arm of the envelope around the nominal one, from the env's generator."""
        if self._nominal_params is None or not has_envelope(self.model):
            raise ValueError(_no_envelope(self.model, "envelope arms"))
        seed = int(self.np_random.integers(0, 2**31 - 1))
        return draws(1, seed, Envelope(), self._nominal_params).variants[0]

    def _latency(self, periods: float) -> int:
        return int(round(periods * self.n_substeps))

    def _advance(self, currents: np.ndarray) -> np.ndarray | None:
        """One control period of physics: `currents` join the commands in flight and each
        takes effect `latency_substeps` physics steps after the state it was computed from
        (as `policy.campaigns.direct`). Returns the period's mean |tau qdot| with
        `measure_power`."""
        n = self.n_substeps
        # with `work`, |tau qdot| summed at the physics rate (as `direct`)
        work = np.zeros(self.n_joints) if self.measure_power else None
        self._in_flight.advance(self.arm, currents, self.steps * n, n, work=work)
        return None if work is None else work / n

    def readings(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles and speeds as a sensor reports them (with noise if configured, times
        the episode's noise multiple)."""
        q = np.array(self.arm.q, dtype=np.float64)
        qdot = np.array(self.arm.qdot, dtype=np.float64)
        if self.config.sensor_noise:
            q, qdot = self.noise.apply(q, qdot, self.np_random)
        return q, qdot

    def _observe(self) -> np.ndarray:
        q, qdot = self.readings()
        self.last_reading = (q, qdot)
        obs = self.memory.observe(q, qdot, self.target)
        return np.clip(obs, self._obs_low, self._obs_high)

    def _info(self, in_bounds: bool) -> dict[str, Any]:
        return {
            "q": np.array(self.arm.q, dtype=np.float64),
            "qdot": np.array(self.arm.qdot, dtype=np.float64),
            "target": self.target.copy(),
            "time": self.steps * self.control_dt,
            "in_bounds": in_bounds,
            "variant": None if self.variant is None else self.variant.name,
        }

    def _joint_vector(self, value: Any, name: str) -> np.ndarray:
        arr = np.asarray(value, dtype=np.float64)
        n, letters = self.n_joints, " ".join(self.model.joint_letters)
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"option {name!r} must be {n} finite numbers ({letters}), got {value!r}"
            )
        return arr


def time_limited(env: ReachAlphaEnv) -> TimeLimit[np.ndarray, np.ndarray]:
    """`env` behind gymnasium's TimeLimit at its own episode length, as `gym.make` wraps it."""
    return TimeLimit(env, max_episode_steps=max(1, env.config.steps_per_episode))


def register_envs() -> None:
    """Register `ReachAlpha-v0` (idempotent), time-limited at the default episode length."""
    if ENV_ID not in gym.registry:
        gym.register(
            id=ENV_ID,
            entry_point="policy.rl.env:ReachAlphaEnv",
            max_episode_steps=EnvConfig().steps_per_episode,
        )


register_envs()
