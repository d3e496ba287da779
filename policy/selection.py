"""The rule that picks which trained actor ships (tools/select_weights.py runs it).

Fixed before looking at Table I's episodes: among the candidates that reach every scenario and
every selection episode and have no restless episode, the one better than the reference
controller on the most of Table I's six metrics; ties go to the lowest mean ratio
candidate / reference over the six.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from policy.batched import eval_envs
from policy.ddpg_controller import make_controller
from policy.env import EnvConfig
from policy.scenarios import SCENARIOS, TABLE_KEYS, wins
from policy.weights import ActorWeights
from protocol.alpha5 import N_JOINTS
from reach_driver.controllers import ControlState

#: mean |qdot| over an episode's last REST_WINDOW_S above which a joint is not at rest (rad/s)
RESTLESS_SPEED = 0.05
REST_WINDOW_S = 5.0
#: screen episode i is reset with `seed * SCREEN_SEED_STRIDE + i`
SCREEN_SEED_STRIDE = 1_000


def weights_of(candidate: Path) -> Path:
    """A run directory's `best_actor.npz`, or the .npz itself."""
    path = candidate / "best_actor.npz" if candidate.is_dir() else candidate
    if not path.exists():
        raise FileNotFoundError(f"{candidate}: no actor at {path}")
    return path


def restless_episodes(
    path: Path,
    episodes: int,
    seed: int,
    perturb: float,
    factory: Callable[[Path], Any] = make_controller,
) -> list[int]:
    """Screen episodes whose arm is still moving at the end, each run by the controller as
    shipped (`factory(path)`: the actor with its reference integral) on the training env."""
    weights = ActorWeights.load(path)
    envs = eval_envs(
        EnvConfig.from_dict(weights.metadata["env"]), episodes, param_perturbation=perturb
    )
    for env in envs:
        env.measure_power = False  # only speeds are screened
    controllers = [factory(path) for _ in envs]
    for i, (env, ctrl) in enumerate(zip(envs, controllers, strict=True)):
        env.reset(seed=seed * SCREEN_SEED_STRIDE + i)
        ctrl.reset()
    steps = envs[0].config.steps_per_episode
    dt = envs[0].control_dt
    window = int(round(REST_WINDOW_S / dt))
    speed = np.zeros((episodes, N_JOINTS))
    for k in range(steps):
        for env, ctrl in zip(envs, controllers, strict=True):
            q, qdot = env.last_reading  # what the sensors said, noise included
            state = ControlState(q=q, qdot=qdot, t=k * dt)
            env.step(np.asarray(ctrl.act(state, env.target)) / weights.current_limits_mA)
        if k >= steps - window:
            speed += np.abs(np.stack([env.arm.qdot for env in envs])) / window
    return [i for i in range(episodes) if np.any(speed[i] > RESTLESS_SPEED)]


def choose(rows: list[dict[str, Any]], reference: dict[str, float]) -> dict[str, Any] | None:
    """The rule: every scenario and episode reached, none restless; most metrics better;
    lowest mean ratio."""
    ok = [
        r
        for r in rows
        if r["scenarios_reached"] == len(SCENARIOS)
        and r["summary"]["reached"] >= 1.0
        and not r.get("restless")
    ]
    if not ok:
        return None

    def key(r: dict[str, Any]) -> tuple[int, float]:
        s = r["summary"]
        ratio = float(np.mean([s[k] / max(reference[k], 1e-12) for k in TABLE_KEYS]))
        return (-sum(wins(s, reference).values()), ratio)

    return min(ok, key=key)
