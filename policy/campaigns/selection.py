"""The rule that picks which trained actor ships (tools/select_weights.py runs it).

Fixed before looking at Table I's episodes: among the candidates that reach every scenario and
every selection episode and have no restless episode (one not at rest, docs/metrics.md "Rest",
on the stability screen), the one better than the reference
controller on the most of Table I's six metrics; ties go to the lowest mean ratio
candidate / reference over the six.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.table import Table

from policy.campaigns.evaluation import evaluate
from policy.campaigns.parallel import run_on_ray
from policy.controllers.weights import ActorWeights
from policy.rl.batched import eval_envs
from policy.rl.env import SENSOR_NOISE, EnvConfig
from policy.tasks.envelope import Variant, draws
from policy.tasks.episodes import Episode, EpisodeResult, RunConfig, random_episodes, score
from policy.tasks.scenarios import SCENARIOS, TABLE_KEYS, wins
from protocol.alpha5 import N_JOINTS
from reach_driver.controllers import ControlState, load_controller
from reach_driver.metrics import REST_KEYS, Metrics, Trace

#: screen episode i is reset with `seed * SCREEN_SEED_STRIDE + i`
SCREEN_SEED_STRIDE = 1_000
SCREENED = "ddpg-distilled"
"""The screen runs the actor with its reference integral, built by this name, and without the
settle supervisor: it screens what was learned, which the supervisor would cover."""

ControllerFactory = Callable[[Path], Any]


def weights_of(candidate: Path) -> Path:
    """A run directory's `best_actor.npz`, or the .npz itself."""
    path = candidate / "best_actor.npz" if candidate.is_dir() else candidate
    if not path.exists():
        raise FileNotFoundError(f"{candidate}: no actor at {path}")
    return path


def _shipped(path: Path) -> Any:
    return load_controller(SCREENED, weights=str(path), settle=False)


def _screen(
    path: Path, indices: Sequence[int], seed: int, perturb: float, factory: ControllerFactory
) -> list[EpisodeResult]:
    """Screen episodes ``indices`` in lock-step on the training env, each scored by the one
    scorer (`policy.tasks.episodes.score`) on the true state, commands included."""
    weights = ActorWeights.load(path)
    envs = eval_envs(
        EnvConfig.from_dict(weights.metadata["env"]), len(indices), param_perturbation=perturb
    )
    controllers = [factory(path) for _ in envs]
    for i, env, ctrl in zip(indices, envs, controllers, strict=True):
        env.reset(seed=seed * SCREEN_SEED_STRIDE + i)
        ctrl.reset()
    steps = envs[0].config.steps_per_episode
    dt = envs[0].control_dt
    shape = (steps + 1, len(envs), N_JOINTS)
    q, qdot, tau, power, command = (np.zeros(shape) for _ in range(5))
    q[0] = np.stack([env.arm.q for env in envs])
    for k in range(steps):
        for n, (env, ctrl) in enumerate(zip(envs, controllers, strict=True)):
            reading_q, reading_qdot = env.last_reading  # what the sensors said, noise included
            state = ControlState(q=reading_q, qdot=reading_qdot, t=k * dt)
            info = env.step(np.asarray(ctrl.act(state, env.target)) / weights.current_limits_mA)
            q[k + 1, n], qdot[k + 1, n], tau[k + 1, n] = env.arm.q, env.arm.qdot, env.arm.tau
            power[k + 1, n] = info[4]["power"]
            command[k + 1, n] = env.prev_action * env.current_limits_mA
    out = []
    for n, env in enumerate(envs):
        trace = Trace(dt, q[:, n], qdot[:, n], tau[:, n], env.target.copy(), power[:, n])
        episode = Episode(q[0, n], env.target, np.asarray(env.arm.torque_scale))
        out.append(score(episode, trace, command[:, n]))
    return out


@dataclass(frozen=True)
class ScreenJob:
    """One screen episode for a Ray worker (the controller is built there, by name)."""

    weights: str
    index: int
    seed: int
    perturb: float


def screen_job(job: ScreenJob) -> Metrics:
    return _screen(Path(job.weights), [job.index], job.seed, job.perturb, _shipped)[0].metrics


def screen(
    path: Path,
    episodes: int,
    seed: int,
    perturb: float,
    factory: ControllerFactory | None = None,
    workers: int | None = None,
    address: str | None = None,
) -> list[Metrics]:
    """Every screen episode's metrics, the actor run as shipped (`factory(path)`, by default
    the `ddpg-distilled` controller with these weights). With ``workers`` or ``address`` the
    episodes run on Ray (`policy.campaigns.parallel`) with the same results: each env's
    randomness comes from its own reset seed. A custom ``factory`` runs in this process only."""
    if workers is None and address is None:
        results = _screen(path, range(episodes), seed, perturb, factory or _shipped)
        return [r.metrics for r in results]
    if factory is not None:
        raise ValueError("a custom controller factory cannot be sent to Ray workers")
    jobs = [ScreenJob(str(path), i, seed, perturb) for i in range(episodes)]
    return run_on_ray(screen_job, jobs, workers, address)


def restless_episodes(
    path: Path,
    episodes: int,
    seed: int,
    perturb: float,
    factory: ControllerFactory | None = None,
    workers: int | None = None,
    address: str | None = None,
) -> list[int]:
    """Screen episodes that do not come to rest (`Metrics.at_rest`, docs/metrics.md "Rest")."""
    metrics = screen(path, episodes, seed, perturb, factory, workers, address)
    return [i for i, m in enumerate(metrics) if not m.at_rest]


#: envelope evaluation: arm i runs episode i of `random_episodes(n, episode_seed)` with sensor
#: noise seed ENVELOPE_NOISE_SEED + i (times its noise multiple)
ENVELOPE_NOISE_SEED = 16_000


def envelope_results(
    controller: Any, n: int, seed: int, episode_seed: int
) -> list[tuple[Variant, EpisodeResult]]:
    """`controller` on `n` arms drawn from the envelope (`policy.tasks.envelope.draws(n, seed)`),
    each with one episode, noise on, through `policy.campaigns.evaluation.evaluate` (the direct
    backend, which emulates the arm's latency)."""
    variants = draws(n, seed).variants
    episodes = random_episodes(n, episode_seed)
    out = []
    for i, (variant, episode) in enumerate(zip(variants, episodes, strict=True)):
        base = RunConfig(noise=SENSOR_NOISE, seed=ENVELOPE_NOISE_SEED + i)
        result = evaluate(controller, [variant.episode(episode)], variant.run_config(base))
        out.append((variant, result.results[0]))
    return out


def envelope_summary(results: Sequence[tuple[Variant, EpisodeResult]]) -> dict[str, Any]:
    """Counts and worst cases over `envelope_results` (the arms that failed, by name)."""
    metrics = [r.metrics for _, r in results]
    overshoot = np.array([m.overshoot_pct for m in metrics])
    return {
        "arms": len(metrics),
        "reached": int(sum(m.reached for m in metrics)),
        "at_rest": int(sum(m.at_rest for m in metrics)),
        "overshoot_mean_pct": float(overshoot.mean()),
        "overshoot_max_pct": float(overshoot.max()),
        "overshoot_over_2pct": int(np.sum(overshoot > 2.0)),
        "settling_mean_s": float(np.mean([m.settling_time_s for m in metrics])),
        "energy_mean_j": float(np.mean([m.energy_j for m in metrics])),
        "failed": [
            {"arm": i, **v.to_dict(), "at_rest": r.metrics.at_rest}
            for i, (v, r) in enumerate(results)
            if not r.metrics.reached
        ],
    }


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


def score_candidate(
    candidate: Path,
    path: Path,
    episodes: Sequence[Episode],
    config: RunConfig,
    reference: dict[str, float],
    screened: Sequence[Metrics],
) -> dict[str, Any]:
    """One candidate's row for `choose`: the scenarios it reaches (nominal arm, no noise),
    its selection-set summary and where it beats the reference, and its restless episodes
    among `screened` (its stability screen, `screen`)."""
    sc = evaluate(
        load_controller(SCREENED, weights=path, settle=False),
        [s.episode() for s in SCENARIOS],
        RunConfig(),
        name=SCREENED,
    )
    summary = evaluate(
        load_controller(SCREENED, weights=path, settle=False), episodes, config, name=SCREENED
    ).summary()
    restless = [i for i, m in enumerate(screened) if not m.at_rest]
    return {
        "candidate": str(candidate),
        "weights": str(path),
        "scenarios_reached": sum(r.metrics.reached for r in sc.results),
        "scenario_final_error": [float(np.abs(r.final_error).max()) for r in sc.results],
        "summary": summary,
        "better_than_reference": wins(summary, reference),
        "restless": restless,
        "restless_rest": {i: {k: screened[i].as_dict()[k] for k in REST_KEYS} for i in restless},
    }


def selection_table(
    title: str,
    reference_name: str,
    reference: dict[str, float],
    rows: Sequence[dict[str, Any]],
    best: dict[str, Any] | None,
    screen_episodes: int,
) -> Table:
    """The reference and every candidate's figures, the chosen one starred."""
    table = Table(title=title)
    for col in (
        "candidate",
        "scenarios",
        "worst scenario |e|",
        "restless",
        "E [J]",
        "RMSE",
        "MIE",
        "MSSE",
        "OS [%]",
        "ST [s]",
        "reached",
        "better",
    ):
        table.add_column(col)

    def add(
        name: str, s: dict[str, float], scen: str, worst: str, restless: str, better: str
    ) -> None:
        table.add_row(
            name,
            scen,
            worst,
            restless,
            f"{s['energy_j']:.3f}",
            f"{s['rmse']:.4f}",
            f"{s['mie']:.4f}",
            f"{s['msse']:.5f}",
            f"{s['overshoot_pct']:.2f}",
            f"{s['settling_time_s']:.3f}",
            f"{s['reached']:.2f}",
            better,
        )

    add(reference_name, reference, "-", "-", "-", "-")
    for r in rows:
        add(
            r["candidate"] + ("*" if r is best else ""),
            r["summary"],
            f"{r['scenarios_reached']}/{len(SCENARIOS)}",
            f"{max(r['scenario_final_error']):.4f}",
            f"{len(r['restless'])}/{screen_episodes}",
            f"{sum(r['better_than_reference'].values())}/{len(TABLE_KEYS)}",
        )
    return table
