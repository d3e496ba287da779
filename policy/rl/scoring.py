"""Scoring an actor file (or the PD demonstrator) on the fixed evaluation episodes, nominal, with
E at 25 % torque and optionally on perturbed arms; and the arm a `--params` file describes, as an
env arm factory. tools/train.py's `--evaluate` and `--params`.

Errors are `SystemExit` naming the flag, as the command line reports them.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from policy.controllers.weights import DISTILLED_WEIGHTS, LEARNED_WEIGHTS, ActorWeights
from policy.rl.batched import evaluate_batched
from policy.rl.config import WEAK_EVAL_SEED_OFFSET, WEAK_EVAL_TORQUE_SCALE, DDPGConfig
from policy.rl.env import EnvConfig
from policy.rl.expert import PDExpert
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import load_arm_params


def params_arm_factory(path: Path | None) -> Any:
    """An env arm factory for the arm in a `--params` file (None: the env's nominal arm)."""
    if path is None:
        return None
    try:
        params = load_arm_params(path)
    except ValueError as exc:
        raise SystemExit(f"--params: {exc}") from exc

    def factory(config: EnvConfig) -> Any:
        return Alpha5Arm(params=params, dt=config.physics_dt)

    return factory


def weights_path(which: str) -> Path:
    """`--evaluate`'s WEIGHTS: 'shipped' (the `ddpg` actor), 'distilled' (`ddpg-distilled`'s)
    or a path."""
    named = {"shipped": LEARNED_WEIGHTS, "distilled": DISTILLED_WEIGHTS}
    return named.get(which, Path(which))


def evaluate_weights(
    which: str,
    episodes: int,
    seed: int,
    perturb: float = 0.0,
    expert_energy: float | None = None,
    arm_factory: Any = None,
) -> dict[str, Any]:
    """Metrics of an actor file (or the expert) on the fixed evaluation episodes."""
    env_config = DDPGConfig.ours().env
    policy: Any = None
    expert = None
    if which == "expert":
        expert = PDExpert(energy_lambda=expert_energy)
    else:
        path = weights_path(which)
        try:
            weights = ActorWeights.load(path)
        except (OSError, ValueError) as exc:
            raise SystemExit(f"--evaluate: {exc}") from exc
        env_config = dataclasses.replace(
            EnvConfig.from_dict(weights.metadata["env"]), observation=weights.observation
        )
        policy = weights.forward
    eval_seed = DDPGConfig().eval_seed + seed
    nominal = evaluate_batched(
        policy, env_config, episodes, eval_seed, expert=expert, arm_factory=arm_factory
    )
    weak = evaluate_batched(
        policy,
        env_config,
        episodes,
        eval_seed + WEAK_EVAL_SEED_OFFSET,
        torque_scale=WEAK_EVAL_TORQUE_SCALE,
        expert=expert,
        arm_factory=arm_factory,
    )
    result = {
        "weights": which,
        "episodes": episodes,
        "eval_seed": eval_seed,
        "nominal": nominal.to_dict(),
        "torque_e_25pct": weak.to_dict(),
    }
    if perturb > 0:
        if not perturb < 1:
            raise SystemExit(f"--perturb must be in (0, 1), got {perturb}")
        result[f"perturbed_{perturb:g}"] = evaluate_batched(
            policy,
            env_config,
            episodes,
            eval_seed + 10_000,
            expert=expert,
            param_perturbation=perturb,
            arm_factory=arm_factory,
        ).to_dict()
    return result
