"""What each ingredient of a training recipe brings: the recipe trained for several seeds with
one ingredient switched off at a time, every run's selected actor scored on held-out episodes,
and the spread across seeds and episodes.

An ingredient is a named set of ``--set`` overrides (`INGREDIENTS`); training one is a seed
sweep (tools/sweep.py ``--ablate NAME``, or tools/train.py per seed) into ``ROOT/NAME/seed-N``.
`score_root` then runs each ``ROOT/NAME/seed-N/best_actor.npz`` on the same held-out test
episodes (`HeldOutSets`: never used in training or checkpoint selection) and `summarize` gives
per ingredient the means with seed-then-episode bootstrap intervals and the difference to
the recipe itself. tools/ablation.py prints it and writes the tables docs/ablation.md holds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policy.campaigns.stats import DEFAULT_RESAMPLES, interval, seed_episode_bootstrap
from policy.controllers.weights import ActorWeights
from policy.rl.batched import eval_envs, run_batch
from policy.rl.env import EnvConfig
from policy.tasks.envelope import has_envelope

#: the recipe itself: every ablation is read against it
BASELINE = "baseline"


@dataclass(frozen=True)
class Ingredient:
    """One ingredient of the `scratch` recipe and the overrides that switch it off (or, for
    one that the recipe leaves off, on)."""

    name: str
    summary: str
    overrides: tuple[str, ...]


INGREDIENTS: tuple[Ingredient, ...] = (
    Ingredient(BASELINE, "the recipe as it is", ()),
    Ingredient(
        "no-memory",
        "no previous action and no error integral in the input",
        ("env.observation.previous_action=false", "env.observation.integral_tau=0"),
    ),
    Ingredient(
        "no-envelope",
        "no arms from the uncertainty envelope (+-20 % arms, noise and the weak E only)",
        ("env.envelope_fraction=0",),
    ),
    Ingredient("no-away", "no cost for moving away from the goal", ("env.reward.away_weight=0",)),
    Ingredient("no-fine", "no narrow (4 mrad) precision term", ("env.reward.fine_weight=0",)),
    Ingredient(
        "td3-updates",
        "TD3's twin critics, smoothed targets and delayed actor instead of DDPG's updates",
        ("twin_critics=true", "target_noise=0.1", "policy_delay=2"),
    ),
    Ingredient(
        "wide-gate",
        "the calm-arrival terms gated from 0.15 rad out (the recipe: 0.05), where braking starts",
        ("env.reward.near_scale=0.15",),
    ),
    Ingredient(
        "away-x5",
        "five times the cost of moving away from the goal (away_weight 10, the recipe 2)",
        ("env.reward.away_weight=10",),
    ),
    Ingredient(
        "window",
        "a window of the last 4 periods' speed readings and actions in the input (off in the "
        "recipe): in-episode adaptation to the arm",
        ("env.observation.history=4",),
    ),
    Ingredient(
        "goals-5s",
        "a new goal every 5 s within each training episode (the recipe: one per 20 s episode): "
        "four arrivals per episode instead of one",
        ("env.goal_every_s=5.0",),
    ),
    Ingredient(
        "small-steps",
        "a quarter of each joint's training goals within 0.3 rad of its start (the recipe: all "
        "uniform over the workspace): the small steps the overshoot metric weighs most",
        ("env.small_step_fraction=0.25",),
    ),
    Ingredient(
        "target-step",
        "the error read when the target last changed in the input (off in the recipe): which "
        "side of the goal the arm came from and how far, so a crossing (an overshoot) is "
        "observable; the error alone reads the same before the goal and past it",
        ("env.observation.target_step=true",),
    ),
    Ingredient(
        "smooth-spatial",
        "CAPS's spatial smoothness in the actor's loss (off in the recipe): || pi(s) - pi(s~) ||, "
        "s~ read with fresh sensor noise, weight 1: the actor learns not to answer the noise",
        ("smooth_spatial_weight=1",),
    ),
    Ingredient(
        "gamma-0.99",
        "discount 0.99 (a 5 s horizon at 20 Hz; the recipe 0.95, 1 s): the paper's, its values "
        "five times the size, an arrival's overshoot a smaller share of them",
        ("gamma=0.99",),
    ),
    Ingredient(
        "gamma-0.9",
        "discount 0.9 (a 0.5 s horizon at 20 Hz)",
        ("gamma=0.9",),
    ),
    Ingredient(
        "updates-x2",
        "four updates per round of 16 env steps (the recipe two): twice the critic's fitting "
        "per transition, at about half the env steps per second",
        ("updates_per_round=4",),
    ),
    Ingredient(
        "n-step-3",
        "three rewards per transition before the bootstrap (the recipe one): an arrival's cost "
        "reaches the states that caused it sooner",
        ("n_step=3",),
    ),
    Ingredient(
        "rate-40hz",
        "control at 41.7 Hz (12 physics steps of 2 ms) with discount 0.975, the same 1 s "
        "horizon: twice the decisions per arrival",
        ("env.control_hz=41.666666666666664", "gamma=0.975", "env.reward.potential_gamma=0.975"),
    ),
    Ingredient(
        "actor-average",
        "a Polyak average of the actor's weights (rate 0.0005 per update, ~16k env steps) is "
        "what checkpoints score and the run keeps; the online actor learns as before",
        ("actor_average_tau=0.0005",),
    ),
    Ingredient(
        "goal-relabel",
        "goal relabelling (hindsight replay, off in the recipe): each ended episode stored 4 "
        "more times for goals the arm passed through, 80 % of the buffer replays",
        ("her_goals=4",),
    ),
    Ingredient(
        "critic-ln",
        "LayerNorm in the critic's hidden layers (off in the recipe): a steadier value fit",
        ("critic_layer_norm=true",),
    ),
    Ingredient(
        "overshoot-peak",
        "the overshoot metric paid once, as each joint's largest excursion past its goal grows "
        "(weight 100: a 10 % overshoot of one joint costs 2.5); off in the recipe",
        ("env.reward.overshoot_peak_weight=100",),
    ),
    Ingredient(
        "crossq",
        "CrossQ's critic under DDPG's actor (off in the recipe): batch renormalisation in the "
        "critic, no target networks, (s, a) and (s', pi(s')) in one batch, Adam's beta1 0.5, "
        "the actor updated every third critic update, as CrossQ does",
        ("crossq_critic=true", "adam_beta1=0.5", "policy_delay=3"),
    ),
    Ingredient(
        "sac",
        "soft actor-critic instead of DDPG: a Gaussian actor explored by its own samples, an "
        "entropy bonus with a learned temperature, twin critics; the mean action ships",
        ("algorithm=sac", "twin_critics=true"),
    ),
    Ingredient(
        "potential",
        "potential-based shaping switched on (off in the recipe)",
        ("env.reward.potential_weight=2.0",),
    ),
    Ingredient(
        "overshoot",
        "the overshoot metric's ratio paid as a cost each step past the goal (off in the recipe)",
        ("env.reward.overshoot_weight=10",),
    ),
)


def ingredient(name: str) -> Ingredient:
    for item in INGREDIENTS:
        if item.name == name:
            return item
    raise ValueError(f"unknown ingredient {name!r}; choose from {[i.name for i in INGREDIENTS]}")


@dataclass(frozen=True)
class HeldOutSets:
    """The held-out episodes every actor is scored on. Their seeds (from `seed`) lie apart
    from training's (`seed * ENV_SEED_STRIDE + ...`, far below) and from checkpoint
    selection's (`eval_seed` 10 000 plus offsets under 10 000)."""

    #: Table I's conditions: sensor noise, each arm's parameters within +-20 %
    standard: int = 40
    #: arms drawn from the uncertainty envelope (docs/robustness.md), one episode each
    envelope: int = 100
    seed: int = 40_000

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    def add_arguments(self, parser: argparse.ArgumentParser, what: str, seed_flag: str) -> None:
        """A tool's --standard, --envelope and `seed_flag` for sets like these (the
        defaults); `what` names the episodes ("test", "validation"). `from_args` reads them."""
        parser.add_argument(
            "--standard",
            type=int,
            default=self.standard,
            help=f"{what} episodes under Table I's conditions per actor ({self.standard})",
        )
        parser.add_argument(
            "--envelope",
            type=int,
            default=self.envelope,
            help=f"{what} episodes on envelope arms per actor ({self.envelope})",
        )
        parser.add_argument(
            seed_flag,
            dest="sets_seed",
            type=int,
            default=self.seed,
            metavar="SEED",
            help=f"the {what} episodes' first seed ({self.seed}; the envelope's add 10000)",
        )

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> HeldOutSets:
        return cls(args.standard, args.envelope, args.sets_seed)


#: per-episode figures kept for each test episode
EPISODE_KEYS = ("reached", "at_rest", "overshoot_pct", "msse", "energy_j")
#: a test episode's overshoot counts as small below this (the issue's and the paper's 2 %)
SMALL_OVERSHOOT_PCT = 2.0


def evaluate_actor(path: Path, sets: HeldOutSets) -> dict[str, list[dict[str, float]]]:
    """The actor at `path` alone (its memory channels kept by the env, as the `ddpg`
    controller keeps them) on both test sets: per set, one dict of `EPISODE_KEYS` per
    episode. Alpha 5 actors only: the sets' arms are drawn around the Alpha's."""
    weights = ActorWeights.load(path)
    env_config = dataclasses.replace(
        EnvConfig.from_dict(weights.metadata["env"]), observation=weights.observation
    )
    if not has_envelope(env_config.model):
        raise ValueError(
            f"{path}: an actor for the {env_config.model.title}; the held-out sets draw arms "
            "around the Reach Alpha 5's (+-20 % and its uncertainty envelope) only"
        )
    out: dict[str, list[dict[str, float]]] = {}
    plans = (
        ("standard", eval_envs(env_config, sets.standard, param_perturbation=0.2), 0),
        ("envelope", eval_envs(env_config, sets.envelope, envelope=True), 10_000),
    )
    for name, envs, offset in plans:
        results = run_batch(weights.forward, envs, sets.seed + offset) if envs else []
        out[name] = [{key: float(getattr(r.metrics, key)) for key in EPISODE_KEYS} for r in results]
    return out


#: the file beside each actor that keeps its test figures (recomputed when the sets change)
SCORES = "test_scores.json"


def score_root(
    root: Path, sets: HeldOutSets, progress: Callable[[str], None] | None = None
) -> dict[str, dict[int, dict[str, list[dict[str, float]]]]]:
    """Every ``root/NAME/seed-N/best_actor.npz`` on the test sets, by ingredient and seed;
    each actor's figures are kept beside it and reused while its weights and the sets are
    unchanged."""
    found: dict[str, dict[int, dict[str, list[dict[str, float]]]]] = {}
    for actor in sorted(root.glob("*/seed-*/best_actor.npz")):
        name, seed_dir = actor.parent.parent.name, actor.parent.name
        try:
            seed = int(seed_dir.removeprefix("seed-"))
        except ValueError:
            continue
        found.setdefault(name, {})[seed] = cached_episodes(
            actor, sets, actor.parent / SCORES, progress, f"{name} seed {seed}"
        )
    return found


def cached_episodes(
    actor: Path,
    sets: HeldOutSets,
    cache: Path,
    progress: Callable[[str], None] | None = None,
    label: str = "",
) -> dict[str, list[dict[str, float]]]:
    """`evaluate_actor` of `actor` on `sets`, kept in `cache` and reused while the actor's
    weights and the sets are unchanged; `progress(label)` is told before an evaluation runs."""
    stamp = {"sets": sets.to_dict(), "weights_mtime_ns": actor.stat().st_mtime_ns}
    if cache.is_file():
        kept = json.loads(cache.read_text(encoding="utf-8"))
        if kept.get("stamp") == stamp:
            episodes: dict[str, list[dict[str, float]]] = kept["episodes"]
            return episodes
    if progress is not None:
        progress(label)
    episodes = evaluate_actor(actor, sets)
    cache.write_text(json.dumps({"stamp": stamp, "episodes": episodes}), "utf-8")
    return episodes


@dataclass(frozen=True)
class Figure:
    """A mean over seeds and episodes with its bootstrap interval, and (for an ingredient
    other than the recipe) the difference to the recipe's, with its interval."""

    mean: float
    low: float
    high: float
    diff: float | None = None
    diff_low: float | None = None
    diff_high: float | None = None

    @property
    def resolved(self) -> bool:
        """The difference's interval excludes 0."""
        if self.diff_low is None or self.diff_high is None:
            return False
        return self.diff_low > 0.0 or self.diff_high < 0.0


#: the table's columns: (set, label, per-episode value)
COLUMNS: tuple[tuple[str, str, Callable[[dict[str, float]], float]], ...] = (
    ("standard", "reached %", lambda e: 100.0 * e["reached"]),
    ("standard", "overshoot %", lambda e: e["overshoot_pct"]),
    ("standard", "overshoot < 2 %", lambda e: 100.0 * (e["overshoot_pct"] < SMALL_OVERSHOOT_PCT)),
    ("standard", "MSSE mrad", lambda e: 1000.0 * e["msse"]),
    ("envelope", "reached %", lambda e: 100.0 * e["reached"]),
    ("envelope", "overshoot < 2 %", lambda e: 100.0 * (e["overshoot_pct"] < SMALL_OVERSHOOT_PCT)),
)


def _matrix(runs: dict[int, dict[str, list[dict[str, float]]]], test: str, fn: Any) -> np.ndarray:
    return np.array([[fn(e) for e in runs[s][test]] for s in sorted(runs)], dtype=float)


def summarize(
    scores: dict[str, dict[int, dict[str, list[dict[str, float]]]]],
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """Per ingredient (in `INGREDIENTS` order, then any others): its seeds and a `Figure`
    per column. The recipe's and an ingredient's draws share the episodes, so a difference
    is read episode by episode; the seeds are drawn independently for each."""
    rng = np.random.default_rng(seed)
    order = [i.name for i in INGREDIENTS if i.name in scores] + sorted(
        set(scores) - {i.name for i in INGREDIENTS}
    )
    draws: dict[tuple[str, str], np.ndarray] = {}
    out: dict[str, dict[str, Any]] = {}
    for name in order:
        runs = scores[name]
        row: dict[str, Any] = {"seeds": sorted(runs), "figures": {}}
        for test, label, fn in COLUMNS:
            values = _matrix(runs, test, fn)
            key = (test, label)
            if key not in draws:
                draws[key] = rng.integers(0, values.shape[1], size=(resamples, values.shape[1]))
            dist = seed_episode_bootstrap(values, resamples, seed, episodes=draws[key])
            low, high = interval(dist)
            figure = Figure(float(values.mean()), low, high)
            base = scores.get(BASELINE)
            if name != BASELINE and base is not None:
                base_values = _matrix(base, test, fn)
                if base_values.shape[1] == values.shape[1]:
                    base_dist = seed_episode_bootstrap(
                        base_values, resamples, seed + 1, episodes=draws[key]
                    )
                    d_low, d_high = interval(dist - base_dist)
                    figure = dataclasses.replace(
                        figure,
                        diff=float(values.mean() - base_values.mean()),
                        diff_low=d_low,
                        diff_high=d_high,
                    )
            row["figures"][f"{test} {label}"] = figure
        out[name] = row
    return out


def markdown(summary: dict[str, dict[str, Any]]) -> str:
    """The table docs/ablation.md holds: mean [95 % interval], and the change against the
    recipe with its interval (bold where the interval excludes 0)."""
    heads = [f"{test} {label}" for test, label, _ in COLUMNS]
    lines = [
        "| ingredient | seeds | " + " | ".join(heads) + " |",
        "|---|---|" + "---|" * len(heads),
    ]
    for name, row in summary.items():
        cells = []
        for head in heads:
            f: Figure = row["figures"][head]
            cell = f"{f.mean:.1f} [{f.low:.1f}, {f.high:.1f}]"
            if f.diff is not None:
                change = f"{f.diff:+.1f} [{f.diff_low:+.1f}, {f.diff_high:+.1f}]"
                cell += "<br>" + (f"**{change}**" if f.resolved else change)
            cells.append(cell)
        seeds = ", ".join(str(s) for s in row["seeds"])
        lines.append(f"| {name} | {seeds} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
