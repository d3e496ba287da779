"""Does the reward an actor was trained on prefer what we want of it?

A learned policy that falls short can fall short for two different reasons: its reward pays
more for the wrong behaviour (fix the reward), or a better policy earns more and the learner
did not find it (fix the inputs, the algorithm, the budget). This audit tells them apart by
running the actor and reference controllers that arrive without overshoot on the same
episodes, in the env the actor was trained in, and paying each trajectory the actor's own
reward, term by term.

References: `pid` (the shipped per-joint PID on the noisy readings, as the driver runs it:
not privileged) and `pd-expert` (`policy.rl.expert.PDExpert`: the true state, the episode's
masses and torque scale: privileged, so it bounds what a policy that knew its arm could
earn). Neither is a teacher here: nothing is learned from them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from policy.campaigns.stats import PairedDifference, paired_difference_ci
from policy.controllers.pid import make_controller
from policy.controllers.weights import ActorWeights
from policy.rl.batched import eval_envs
from policy.rl.env import REWARD_TERMS, EnvConfig, ReachAlphaEnv
from policy.rl.expert import PDExpert
from policy.tasks.envelope import has_envelope
from protocol.models import ArmModel
from reach_driver.controllers import ControlState

#: joints whose step is shorter than this (rad) have no overshoot ratio (docs/metrics.md)
MIN_STEP_RAD = 0.05

#: the last seconds of an episode, where every controller here has arrived: what holding the
#: goal earns (a limit cycle's precision against its command changes), apart from the arrival
HOLD_S = 2.0

#: a batch of envs to the actions (fractions of the current limit) each takes this period
Acting = Callable[[Sequence[ReachAlphaEnv], np.ndarray], np.ndarray]


@dataclass(frozen=True)
class EpisodeReturns:
    """Per episode of one controller: the reward's sum, its discounted sum from the start
    (what the actor maximises from its first state), its sum over the last `HOLD_S` (holding
    the goal), each term's sum, and the overshoot."""

    total: np.ndarray
    discounted: np.ndarray
    hold: np.ndarray
    terms: dict[str, np.ndarray]
    overshoot_pct: np.ndarray


@dataclass(frozen=True)
class Audit:
    gamma: float
    episodes: int
    returns: dict[str, EpisodeReturns]
    #: reference name -> paired difference (actor - reference) of the discounted return
    actor_minus: dict[str, PairedDifference]
    #: the same for the return over the last `HOLD_S`
    hold_minus: dict[str, PairedDifference]


def _actor(weights: ActorWeights) -> Acting:
    return lambda envs, obs: np.asarray(weights.forward(obs), dtype=np.float64)


def _pd_expert() -> Acting:
    expert = PDExpert()
    return lambda envs, obs: np.stack([expert(env) for env in envs])


def _pid(n: int, model: ArmModel) -> Acting:
    controllers = [make_controller(model) for _ in range(n)]

    def act(envs: Sequence[ReachAlphaEnv], obs: np.ndarray) -> np.ndarray:
        out = []
        for env, ctrl in zip(envs, controllers, strict=True):
            q, qdot = env.last_reading  # the readings the observation was built from
            state = ControlState(q=q, qdot=qdot, t=env.steps * env.control_dt)
            out.append(ctrl.act(state, env.target) / env.current_limits_mA)
        return np.clip(np.stack(out), -1.0, 1.0)

    return act


def run_returns(
    acting: Acting, config: EnvConfig, episodes: int, seed: int, gamma: float
) -> EpisodeReturns:
    """`episodes` Table I-like episodes (sensor noise, arms within +-20 % on an arm whose
    parameters can be drawn so, the nominal arm otherwise), env i reset with `seed + i`,
    under `acting`; the reward is `config.reward`, from the true state."""
    spread = 0.2 if has_envelope(config.model) else 0.0
    envs = eval_envs(config, episodes, param_perturbation=spread)
    obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(envs)])
    start = np.stack([env.arm.q for env in envs])
    target = np.stack([env.target for env in envs])
    total = np.zeros(episodes)
    discounted = np.zeros(episodes)
    hold = np.zeros(episodes)
    hold_from = config.steps_per_episode - int(round(HOLD_S * config.control_hz))
    terms = {name: np.zeros(episodes) for name in REWARD_TERMS}
    furthest_past = np.zeros_like(start)
    sign = np.sign(target - start)
    for k in range(config.steps_per_episode):
        actions = acting(envs, obs)
        stepped = [env.step(a) for env, a in zip(envs, actions, strict=True)]
        obs = np.stack([s[0] for s in stepped])
        reward = np.array([s[1] for s in stepped])
        total += reward
        discounted += gamma**k * reward
        if k >= hold_from:
            hold += reward
        for i, s in enumerate(stepped):
            for name, value in s[4]["reward_terms"].items():
                terms[name][i] += value
        q = np.stack([env.arm.q for env in envs])
        furthest_past = np.maximum(furthest_past, (q - target) * sign)
    step = np.abs(target - start)
    ratio = np.where(step >= MIN_STEP_RAD, furthest_past / np.maximum(step, 1e-9), 0.0)
    return EpisodeReturns(total, discounted, hold, terms, 100.0 * ratio.max(axis=1))


def audit(path: Path, episodes: int = 40, seed: int = 40_000) -> Audit:
    """The actor at `path` against `pid` and `pd-expert` on the same `episodes`, each paid
    the actor's own reward and discount (the held-out standard set's seeds by default). On
    another arm than the Alpha 5 the PD expert (the Alpha 5's) sits out."""
    weights = ActorWeights.load(path)
    config = dataclasses.replace(
        EnvConfig.from_dict(weights.metadata["env"]), observation=weights.observation
    )
    gamma = float(weights.metadata.get("config", {}).get("gamma", 0.99))
    plans: dict[str, Acting] = {"actor": _actor(weights), "pid": _pid(episodes, config.model)}
    if has_envelope(config.model):
        plans["pd-expert"] = _pd_expert()
    returns = {name: run_returns(act, config, episodes, seed, gamma) for name, act in plans.items()}
    diffs = {
        name: paired_difference_ci(returns["actor"].discounted, returns[name].discounted)
        for name in plans
        if name != "actor"
    }
    holds = {
        name: paired_difference_ci(returns["actor"].hold, returns[name].hold)
        for name in plans
        if name != "actor"
    }
    return Audit(gamma, episodes, returns, diffs, holds)


def render(result: Audit) -> list[list[str]]:
    """Rows for a table: per controller, the mean discounted and total return, each active
    term's mean sum, the mean overshoot and the share of episodes under 2 %."""
    active = [
        name
        for name in REWARD_TERMS
        if any(np.any(r.terms[name] != 0) for r in result.returns.values())
    ]
    header = ["controller", f"discounted return (gamma {result.gamma:g})", "return"]
    header += [f"last {HOLD_S:g} s"]
    header += [f"{name}" for name in active] + ["overshoot %", "overshoot < 2 %"]
    rows = [header]
    for name, r in result.returns.items():
        cell = f"{r.discounted.mean():.1f}"
        if name in result.actor_minus:
            d = result.actor_minus[name]
            cell += f" (actor {d.estimate:+.1f} [{d.low:+.1f}, {d.high:+.1f}])"
        hold = f"{r.hold.mean():.2f}"
        if name in result.hold_minus:
            d = result.hold_minus[name]
            hold += f" (actor {d.estimate:+.2f} [{d.low:+.2f}, {d.high:+.2f}])"
        rows.append(
            [name, cell, f"{r.total.mean():.1f}", hold]
            + [f"{r.terms[t].mean():.1f}" for t in active]
            + [f"{r.overshoot_pct.mean():.1f}", f"{100 * np.mean(r.overshoot_pct < 2):.0f} %"]
        )
    return rows
