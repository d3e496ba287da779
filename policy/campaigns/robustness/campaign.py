"""One controller over a plan's arms: a `policy.campaigns.parallel.Job` per arm, run serially
or on Ray, and the report (per-episode rows and their summary)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from typing import Any

from policy.campaigns.parallel import Job, run_job, run_on_ray
from policy.campaigns.robustness.arms import (
    Arm,
    Plan,
    arm_episode,
    arm_twin,
    base_config,
)
from policy.campaigns.robustness.summary import summaries
from policy.tasks.episodes import EpisodeResult
from reach_driver.controllers import load_controller
from reach_sim_bridge.model.params import ArmParams


def make_jobs(
    controller: str,
    params: dict[str, Any],
    arms: Sequence[Arm],
    seed: int,
    seconds: float = 20.0,
    rate_hz: float = 20.0,
    twin_error: float | None = None,
    fitted: dict[tuple[str, int], ArmParams] | None = None,
) -> list[Job]:
    """One `policy.campaigns.parallel.Job` per arm: its own RunConfig and Episode; `run_job` runs it
    with episode seed ``config.seed + index``. With `twin_error` (0: exact) each arm's
    controller is also given the arm's twin (`arm_twin`), its `fitted` one where given
    (keyed by set and index)."""
    params_json = json.dumps(params, sort_keys=True)
    fitted = fitted or {}
    return [
        Job(
            controller,
            params_json
            if twin_error is None
            else json.dumps(
                {**params, **arm_twin(a, seed, twin_error, fitted.get((a.set, a.index)))},
                sort_keys=True,
            ),
            a.variant.episode(arm_episode(seed, a.set, a.index)),
            a.variant.run_config(base_config(seed, a.set, seconds, rate_hz)),
            a.index,
        )
        for a in arms
    ]


def run_jobs(
    jobs: Sequence[Job],
    workers: int | None,
    address: str | None,
    on_result: Callable[[tuple[int, EpisodeResult]], None] | None = None,
) -> list[EpisodeResult]:
    """Serially (no workers, no address) or on Ray; the same `run_job` either way."""
    if workers is None and address is None:
        out = []
        for job in jobs:
            pair = run_job(job)
            out.append(pair[1])
            if on_result is not None:
                on_result(pair)
        return out
    return [r for _, r in run_on_ray(run_job, jobs, workers, address, on_result)]


def episode_row(arm: Arm, result: EpisodeResult) -> dict[str, Any]:
    v = arm.variant.to_dict()
    return {
        "set": arm.set,
        "index": arm.index,
        "name": v["name"],
        "factors": v["factors"],
        "torque_scale": v["torque_scale"],
        "start": result.episode.start.tolist(),
        "target": result.episode.target.tolist(),
        "final_error": result.final_error.tolist(),
        "metrics": result.metrics.as_dict(),
        "rmse_floor": result.rmse_floor,
        "overshoot": None if (how := result.overshoot) is None else how.as_dict(),
    }


def campaign(
    controller: str,
    label: str,
    params: dict[str, Any],
    the_plan: Plan,
    seed: int,
    *,
    settings: dict[str, Any],
    command: str,
    workers: int | None = None,
    address: str | None = None,
    seconds: float = 20.0,
    rate_hz: float = 20.0,
    progress: Callable[[int, EpisodeResult], None] | None = None,
    twin_error: float | None = None,
    fitted: dict[tuple[str, int], ArmParams] | None = None,
) -> dict[str, Any]:
    """Run one controller over the plan's arms; the report (rows, summary) as a dict."""
    jobs = make_jobs(controller, params, the_plan.arms, seed, seconds, rate_hz, twin_error, fitted)
    if jobs:  # a bad name or parameter fails before Ray starts
        load_controller(controller, **json.loads(jobs[0].params_json))
    done = None if progress is None else (lambda pair: progress(*pair))
    t0 = time.monotonic()
    results = run_jobs(jobs, workers, address, done)
    wall = time.monotonic() - t0
    rows = [episode_row(a, r) for a, r in zip(the_plan.arms, results, strict=True)]
    return build_report(
        controller, label, params, rows, the_plan, settings=settings, command=command, wall=wall
    )


def build_report(
    controller: str,
    label: str,
    params: dict[str, Any],
    rows: list[dict[str, Any]],
    the_plan: Plan,
    *,
    settings: dict[str, Any],
    command: str,
    wall: float,
) -> dict[str, Any]:
    return {
        "label": label,
        "controller": controller,
        "params": params,
        "settings": settings,
        "command": command,
        "wall_s": wall,
        "available": the_plan.available,
        "infeasible": {k: len(v) for k, v in the_plan.infeasible.items()},
        "infeasible_arms": {
            k: [{"name": v.name, "factors": v.factors, "reason": why} for v, why in vs]
            for k, vs in the_plan.infeasible.items()
        },
        "summary": summaries(rows),
        "episodes": rows,
    }
