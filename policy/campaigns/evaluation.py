"""Closed-loop evaluation of a controller on the simulated arm, scored by `reach_driver.metrics`.

One `run_episode` and one `evaluate` for every backend: `DirectArm` (the controller steps the
physics, `policy.campaigns.direct`) or `ViaDriver` (through `reach_driver` and the virtual arm on a
pty, `policy.campaigns.via_driver`). Both return the same `EpisodeResult`, scored by the same code
on the simulator's true angles, so the numbers in docs/results.md compare like with like.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from policy.campaigns.direct import ArmFactory, DirectArm
from policy.tasks.episodes import (
    DEFAULT_RATE_HZ,
    DEFAULT_RUN,
    DEFAULT_SECONDS,
    Episode,
    EpisodeResult,
    Evaluation,
    NoisyReadings,
    RunConfig,
    load_episodes,
    random_episodes,
)
from protocol.models import ALPHA5
from reach_driver.controllers import Controller, ControlState, load_controller
from reach_driver.metrics import METRIC_KEYS
from reach_sim_bridge.model.sensors import SensorNoise


class Backend(Protocol):
    """Where an episode runs; `stats()` is what it adds to `Evaluation.controller_stats`."""

    def run(
        self, controller: Controller, episode: Episode, config: RunConfig, episode_seed: int
    ) -> EpisodeResult: ...

    def stats(self) -> dict[str, Any]: ...


def run_episode(
    controller: Controller,
    episode: Episode,
    config: RunConfig = DEFAULT_RUN,
    backend: Backend | None = None,
    episode_seed: int = 0,
) -> EpisodeResult:
    """One episode: reset arm and controller, hold each action for one control period (on
    the twin of the episode's arm unless `backend` says otherwise)."""
    return (backend or DirectArm(model=episode.model)).run(
        controller, episode, config, episode_seed
    )


def evaluate(
    controller: Controller,
    episodes: Sequence[Episode],
    config: RunConfig = DEFAULT_RUN,
    name: str = "controller",
    backend: Backend | None = None,
    on_episode: Callable[[int, EpisodeResult], None] | None = None,
) -> Evaluation:
    """Every episode in turn; episode i uses seed `config.seed + i`. Without a `backend`, the
    direct one on the episodes' arm."""
    backend = backend or DirectArm(model=episodes[0].model if episodes else ALPHA5)
    results = []
    for i, episode in enumerate(episodes):
        result = backend.run(controller, episode, config, config.seed + i)
        results.append(result)
        if on_episode is not None:
            on_episode(i, result)
    stats: dict[str, Any] = dict(backend.stats())
    solve_stats = getattr(controller, "solve_time_stats", None)
    if callable(solve_stats):
        stats["solve_time_s"] = solve_stats()
    return Evaluation(name, config, results, stats)


def add_param_option(parser: argparse.ArgumentParser, example: str) -> None:
    """The tools' repeatable `--param KEY=VALUE` (read with `parse_controller_params`)."""
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="keyword argument for the controller factory, JSON value (repeatable), e.g. "
        + example,
    )


def parse_controller_params(items: Sequence[str]) -> dict[str, Any]:
    """`--param KEY=VALUE` options of the tools: each value JSON if it parses, else a string
    (`weights=runs/x/best_actor.npz`, `horizon=15`)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--param expects KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(raw)
        except json.JSONDecodeError:
            out[key] = raw
    return out


__all__ = [
    "DEFAULT_RATE_HZ",
    "DEFAULT_SECONDS",
    "METRIC_KEYS",
    "ArmFactory",
    "Backend",
    "ControlState",
    "DirectArm",
    "Episode",
    "EpisodeResult",
    "Evaluation",
    "NoisyReadings",
    "RunConfig",
    "SensorNoise",
    "add_param_option",
    "evaluate",
    "load_controller",
    "load_episodes",
    "parse_controller_params",
    "random_episodes",
    "run_episode",
]
