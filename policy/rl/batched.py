"""The batched backend: N envs in lock-step, one batched policy call per step.

Training scores checkpoints this way (a torch forward over the batch is much cheaper than N
single ones). Each env's episode becomes the same `EpisodeResult` as the direct backend's,
scored by `policy.tasks.episodes.score`; energy integrates |tau qdot| at the physics rate as in
Table I (`ReachAlphaEnv.measure_power`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from policy.rl.env import EnvConfig, ReachAlphaEnv
from policy.tasks.episodes import Episode, EpisodeResult, score
from reach_driver.metrics import Trace, summarize

Expert = Callable[[ReachAlphaEnv], np.ndarray]
"""A privileged controller: an action in [-1, 1]^n (n joints) from the env's true state."""

#: checkpoint score: penalty per unit of RMSE / floor above 1, per % of overshoot and per rad
#: of steady-state error (reaching counts 1 per episode fraction)
SCORE_RMSE_RATIO_WEIGHT = 0.2
SCORE_OVERSHOOT_WEIGHT = 0.01
SCORE_STEADY_ERROR_WEIGHT = 5.0
FLOOR_EPS = 1e-9  # rad: a zero step has a zero floor


def eval_envs(
    env_config: EnvConfig,
    episodes: int,
    torque_scale: tuple[float, ...] | None = None,
    arm_factory: Any = None,
    param_perturbation: float = 0.0,
    training_workspace: bool = False,
    envelope: bool = False,
) -> list[ReachAlphaEnv]:
    """Envs for `evaluate_batched`: sensor noise on, the whole evaluation workspace (even when
    the run trains on a wider one, so scores stay comparable across runs; `training_workspace`
    keeps the run's own), the nominal model unless `param_perturbation` > 0 (each episode's
    arm then drawn by `ArmParams.randomized`) or `envelope` (each episode's arm drawn from the
    uncertainty envelope, fixed by the episode's seed: `EnvConfig.envelope_fraction` 1)."""
    cfg = dataclasses.replace(
        env_config,
        torque_scale_low=None,
        max_step=None,
        small_step_fraction=0.0,
        sensor_noise=True,
        workspace_low=env_config.workspace_low if training_workspace else None,
        workspace_high=env_config.workspace_high if training_workspace else None,
        param_perturbation=param_perturbation,
        torque_scale=torque_scale or (1.0,) * env_config.model.n_joints,
        envelope_fraction=1.0 if envelope else 0.0,
        goal_every_s=None,
    )
    envs = [ReachAlphaEnv(cfg, arm_factory=arm_factory) for _ in range(episodes)]
    for env in envs:
        env.measure_power = True
    return envs


@dataclass(frozen=True)
class EvalResult:
    """Means over episodes of reach_driver.metrics (docs/metrics.md), plus the floor ratio."""

    episodes: int
    reached_fraction: float
    final_error: float  # max |e| over joints at the end (rad)
    rmse: float  # rad
    rmse_floor_ratio: float  # rmse / rmse of driving straight to target at no-load speed
    overshoot_pct: float
    settling_s: float
    steady_error: float  # MSSE: mean |e| over the last 2 s (rad)
    mie: float
    energy_j: float
    at_rest_fraction: float = 1.0  # docs/metrics.md "Rest"; reached implies at rest
    overshoot_max_pct: float = 0.0  # worst episode's overshoot

    @classmethod
    def of(cls, results: Sequence[EpisodeResult]) -> EvalResult:
        summary = summarize([r.metrics for r in results])
        ratios = [r.metrics.rmse / max(r.rmse_floor, FLOOR_EPS) for r in results]
        finals = [float(np.max(np.abs(r.final_error))) for r in results]
        return cls(
            episodes=len(results),
            reached_fraction=summary["reached"],
            final_error=float(np.mean(finals)),
            rmse=summary["rmse"],
            rmse_floor_ratio=float(np.mean(ratios)),
            overshoot_pct=summary["overshoot_pct"],
            settling_s=summary["settling_time_s"],
            steady_error=summary["msse"],
            mie=summary["mie"],
            energy_j=summary["energy_j"],
            at_rest_fraction=float(np.mean([r.metrics.at_rest for r in results])),
            overshoot_max_pct=float(max(r.metrics.overshoot_pct for r in results)),
        )

    def score(self, energy_weight: float = 0.0) -> float:
        """Higher is better: reaching first, then speed, then overshoot and precision
        (and energy, per joule, when `energy_weight` > 0)."""
        return (
            self.reached_fraction
            - SCORE_RMSE_RATIO_WEIGHT * max(self.rmse_floor_ratio - 1.0, 0.0)
            - SCORE_OVERSHOOT_WEIGHT * self.overshoot_pct
            - SCORE_STEADY_ERROR_WEIGHT * self.steady_error
            - energy_weight * self.energy_j
        )

    def to_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def run_batch(
    policy: Callable[[np.ndarray], np.ndarray] | None,
    envs: Sequence[ReachAlphaEnv],
    seed: int,
    expert: Expert | None = None,
) -> list[EpisodeResult]:
    """One episode per env (env i reset with `seed + i`), scored on the true state.

    `policy` maps a batch of observations to a batch of actions; with `expert` given, the
    expert (which reads the true state) acts instead, for its baseline figures."""
    if policy is None and expert is None:
        raise ValueError("need a policy or an expert")
    n_envs = len(envs)
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)])
    steps = envs[0].config.steps_per_episode
    n_joints = envs[0].n_joints
    q = np.zeros((steps + 1, n_envs, n_joints))
    qdot = np.zeros_like(q)
    tau = np.zeros_like(q)
    power = np.zeros_like(q)
    actions_taken = np.zeros_like(q)
    q[0] = np.stack([env.arm.q for env in envs])
    for k in range(1, steps + 1):
        if expert is not None:
            actions: Any = [expert(env) for env in envs]
        else:
            assert policy is not None
            actions = policy(obs)
        stepped = [env.step(a) for env, a in zip(envs, actions, strict=True)]
        obs = np.stack([s[0] for s in stepped])
        q[k] = np.stack([env.arm.q for env in envs])
        qdot[k] = np.stack([env.arm.qdot for env in envs])
        tau[k] = np.stack([env.arm.tau for env in envs])
        power[k] = np.stack([s[4].get("power", np.zeros(n_joints)) for s in stepped])
        actions_taken[k] = np.stack([env.prev_action for env in envs])
    dt = envs[0].control_dt
    results = []
    for i, env in enumerate(envs):
        episode = Episode(q[0, i], env.target, np.asarray(env.arm.torque_scale), model=env.model)
        trace = Trace(
            dt=dt,
            q=q[:, i],
            qdot=qdot[:, i],
            tau=tau[:, i],
            target=env.target,
            power=power[:, i],
            model=env.model,
        )
        results.append(score(episode, trace, actions_taken[:, i] * env.current_limits_mA))
    return results


def evaluate_batched(
    policy: Callable[[np.ndarray], np.ndarray] | None,
    env_config: EnvConfig,
    episodes: int = 20,
    seed: int = 10_000,
    torque_scale: tuple[float, ...] | None = None,
    arm_factory: Any = None,
    expert: Expert | None = None,
    envs: list[ReachAlphaEnv] | None = None,
    param_perturbation: float = 0.0,
) -> EvalResult:
    """`episodes` fixed episodes (sensor noise on) in lock-step, as `EvalResult` means.

    Pass `envs` (from `eval_envs`) to reuse arms: a long run then scores on the very model it
    trains on."""
    if envs is None:
        envs = eval_envs(env_config, episodes, torque_scale, arm_factory, param_perturbation)
    if len(envs) != episodes:
        raise ValueError(f"{len(envs)} envs for {episodes} episodes")
    return EvalResult.of(run_batch(policy, envs, seed, expert))
