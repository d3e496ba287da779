"""Evaluation campaigns on Ray: the episodes of `policy.evaluation.evaluate`, in parallel.

Ray (the optional extra ``.[scale]``) schedules one task per episode on this machine
(``ray.init(num_cpus=workers)``) or on a running cluster (``address``). The results are the
serial run's: episode i runs with seed ``config.seed + i`` exactly as `evaluate` runs it (its
arm, parameter draw and sensor noise depend on that seed alone, and the controller is reset
before every episode), whichever worker runs it and in whatever order. Controllers are built
inside the workers by name (`load_controller`), never pickled, once per worker process.
A cluster's nodes need this repository installed (``pip install -e '.[scale]'``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from policy.direct import DirectArm
from policy.rollout import Episode, EpisodeResult, Evaluation, RunConfig
from reach_driver.controllers import Controller, load_controller

INSTALL_HINT = "pip install -e '.[scale]'"


class RayUnavailable(RuntimeError):
    """Ray is not installed; the message says how to install it."""


def import_ray() -> ModuleType:
    """Ray, or `RayUnavailable` naming the extra that installs it."""
    try:
        import ray
    except ImportError as exc:
        raise RayUnavailable(
            f"parallel evaluation (--workers, --address) needs Ray: {INSTALL_HINT}"
        ) from exc
    return ray


@dataclass(frozen=True)
class Job:
    """One episode, as every worker needs it (small and picklable)."""

    controller: str
    params_json: str
    episode: Episode
    config: RunConfig
    index: int


_CONTROLLERS: dict[tuple[str, str], Controller] = {}
"""Per worker process: one controller per (name, parameters), reused as `evaluate` reuses one."""


def run_job(job: Job) -> tuple[int, EpisodeResult]:
    """Episode ``job.index`` with seed ``config.seed + index``, on this process's controller."""
    key = (job.controller, job.params_json)
    controller = _CONTROLLERS.get(key)
    if controller is None:
        controller = load_controller(job.controller, **json.loads(job.params_json))
        _CONTROLLERS[key] = controller
    result = DirectArm().run(controller, job.episode, job.config, job.config.seed + job.index)
    return job.index, result


def evaluate_parallel(
    controller_name: str,
    params: dict[str, Any],
    episodes: Sequence[Episode],
    config: RunConfig,
    workers: int | None = None,
    address: str | None = None,
    on_episode: Callable[[int, EpisodeResult], None] | None = None,
) -> Evaluation:
    """`evaluate(load_controller(controller_name, **params), episodes, config)` on Ray.

    Starts a local Ray with ``workers`` CPUs (or joins the cluster at ``address``) unless Ray
    is already initialised, and shuts down only what it started. ``on_episode`` is called as
    episodes finish (in completion order); the results come back in episode order."""
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        if address is not None:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    try:
        remote = ray.remote(num_cpus=1)(run_job)
        params_json = json.dumps(params, sort_keys=True)
        pending = [
            remote.remote(Job(controller_name, params_json, episode, config, i))
            for i, episode in enumerate(episodes)
        ]
        results: dict[int, EpisodeResult] = {}
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            index, result = ray.get(done[0])
            results[index] = result
            if on_episode is not None:
                on_episode(index, result)
        cpus = int(ray.cluster_resources().get("CPU", 0))
    finally:
        if started:
            ray.shutdown()
    stats = {"engine": "ray", "cluster_cpus": cpus, "address": address or "local"}
    ordered = [results[i] for i in range(len(episodes))]
    return Evaluation(controller_name, config, ordered, stats)
