"""Evaluation campaigns on Ray: the episodes of `policy.campaigns.evaluation.evaluate`, in parallel.

Ray (the optional extra ``.[scale]``) schedules one task per episode on this machine
(``ray.init(num_cpus=workers)``) or on a running cluster (``address``). The results are the
serial run's: episode i runs with seed ``config.seed + i`` exactly as `evaluate` runs it (its
arm, parameter draw and sensor noise depend on that seed alone, and the controller is reset
before every episode), whichever worker runs it and in whatever order. Controllers are built
inside the workers by name (`load_controller`), never pickled, once per worker process.
A cluster's nodes need this repository installed (``pip install -e '.[scale]'``).

Every task first checks that its worker imported the same code as the process that started
the campaign (`code_fingerprint`) and fails with `CodeMismatch` otherwise: Ray puts the
directory a campaign is started in first on its workers' path, so a campaign started inside
one checkout with another on ``PYTHONPATH`` would silently run the first one's code.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar

from policy.campaigns.direct import DirectArm
from policy.tasks.episodes import Episode, EpisodeResult, Evaluation, RunConfig
from reach_driver.controllers import Controller, load_controller

INSTALL_HINT = "pip install -e '.[scale]'"
J = TypeVar("J")
R = TypeVar("R")


PACKAGES = ("protocol", "reach_driver", "reach_sim_bridge", "policy")
"""The packages whose files a worker must share with the campaign's driver."""


class CampaignError(RuntimeError):
    """A campaign cannot run on the Ray it was given; the message says why."""


class RayUnavailable(CampaignError):
    """Ray is not installed; the message says how to install it."""


class CodeMismatch(CampaignError):
    """A worker imported different code (or weights) from the campaign's driver."""


def fingerprint(roots: Sequence[Path]) -> str:
    """SHA-256 over every file under ``roots`` (names and contents, caches left out)."""
    digest = hashlib.sha256()
    for root in roots:
        for path in sorted(root.rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                digest.update(f"{path.relative_to(root.parent)}\0".encode())
                digest.update(path.read_bytes())
    return digest.hexdigest()


@functools.cache
def code_fingerprint() -> tuple[str, str]:
    """This process's `PACKAGES` as imported: (their `fingerprint`, where `policy` came from)."""
    roots = [Path(importlib.import_module(name).__file__ or "").parent for name in PACKAGES]
    return fingerprint(roots), str(roots[-1])


def checked_call(fn: Callable[[J], R], code: str, job: J) -> R:
    """``fn(job)``, once this worker's `code_fingerprint` is the driver's ``code``."""
    mine, where = code_fingerprint()
    if mine != code:
        raise CodeMismatch(
            f"this Ray worker imported other code than the campaign's driver (policy from "
            f"{where}). Start the campaign from the checkout it should run (Ray puts the "
            f"starting directory first on its workers' path), and on a cluster install the "
            f"same version on every node."
        )
    return fn(job)


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


CONTROLLER_CACHE = 8
"""Controllers a worker keeps (the oldest goes first)."""

_CONTROLLERS: dict[tuple[str, str], Controller] = {}
"""Per worker process: one controller per (name, parameters), reused as `evaluate` reuses one."""


def run_job(job: Job) -> tuple[int, EpisodeResult]:
    """Episode ``job.index`` with seed ``config.seed + index``, on this process's controller."""
    key = (job.controller, job.params_json)
    controller = _CONTROLLERS.get(key)
    if controller is None:
        controller = load_controller(job.controller, **json.loads(job.params_json))
        if len(_CONTROLLERS) >= CONTROLLER_CACHE:  # one per arm when each has its own twin
            _CONTROLLERS.pop(next(iter(_CONTROLLERS)))
        _CONTROLLERS[key] = controller
    result = DirectArm().run(controller, job.episode, job.config, job.config.seed + job.index)
    return job.index, result


@contextmanager
def ray_session(workers: int | None = None, address: str | None = None) -> Iterator[ModuleType]:
    """Ray, started locally with ``workers`` CPUs or joined at ``address`` unless already
    initialised (then reused as it is); shut down on exit only if started here."""
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
        yield ray
    finally:
        if started:
            ray.shutdown()


def run_on_ray(
    fn: Callable[[J], R],
    jobs: Sequence[J],
    workers: int | None = None,
    address: str | None = None,
    on_result: Callable[[R], None] | None = None,
) -> list[R]:
    """``[fn(job) for job in jobs]``, one Ray task (one CPU) per job. ``fn`` must be a
    module-level function (workers import it by name, and check they run the driver's code:
    `checked_call`); ``on_result`` sees results as they finish, the list comes back in job
    order."""
    code, _ = code_fingerprint()
    with ray_session(workers, address) as ray:
        remote = ray.remote(num_cpus=1)(checked_call)
        index = {remote.remote(fn, code, job): i for i, job in enumerate(jobs)}
        results: dict[int, R] = {}
        pending = list(index)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            try:
                results[index[done[0]]] = ray.get(done[0])
            except CodeMismatch as exc:  # Ray's RayTaskError(CodeMismatch): its cause, plainly
                raise CodeMismatch(*getattr(exc, "cause", exc).args) from None
            if on_result is not None:
                on_result(results[index[done[0]]])
    return [results[i] for i in range(len(jobs))]


def evaluate_parallel(
    controller_name: str,
    params: dict[str, Any],
    episodes: Sequence[Episode],
    config: RunConfig,
    workers: int | None = None,
    address: str | None = None,
    on_episode: Callable[[int, EpisodeResult], None] | None = None,
) -> Evaluation:
    """`evaluate(load_controller(controller_name, **params), episodes, config)` on Ray
    (`ray_session`); ``on_episode`` is called as episodes finish, in completion order."""
    params_json = json.dumps(params, sort_keys=True)
    jobs = [Job(controller_name, params_json, e, config, i) for i, e in enumerate(episodes)]
    done = None if on_episode is None else (lambda r: on_episode(*r))
    pairs = run_on_ray(run_job, jobs, workers, address, done)
    stats = {"engine": "ray", "workers": workers, "address": address or "local"}
    return Evaluation(controller_name, config, [r for _, r in pairs], stats)


# --- training seed sweeps on Ray Tune (tools/sweep.py) ----------------------------------------


def import_tune() -> ModuleType:
    """Ray Tune, or `RayUnavailable` saying what is missing (Tune needs pandas and pyarrow
    beside Ray core: the extra ``ray[tune]``)."""
    import_ray()
    try:
        from ray import tune
    except ImportError as exc:
        raise RayUnavailable(
            f"seed sweeps need Ray Tune ({exc}): pip install 'ray[tune]' (or {INSTALL_HINT})"
        ) from exc
    return tune


def run_trial(config: dict[str, Any], report: Callable[[dict[str, Any]], None]) -> None:
    """One training run of a sweep: ``config["training"]`` (a `DDPGConfig.to_dict()`) with seed
    ``config["seed"]``, in ``config["root"]/seed-N``, for its ``total_steps``; ``report`` gets
    each checkpoint evaluation as it is made (the trainer's score, the nominal set's reached
    fraction, overshoot and energy) and the last one is the run's final evaluation."""
    from pathlib import Path

    from policy.rl.config import DDPGConfig
    from policy.rl.trainer import Trainer, make_expert

    data = dict(config["training"])
    data["seed"] = int(config["seed"])
    training = DDPGConfig.from_dict(data)
    run_dir = Path(config["root"]) / f"seed-{training.seed}"
    if (run_dir / "checkpoint.pt").exists():
        raise ValueError(f"{run_dir} already holds a run; choose another --out")
    trainer = Trainer(training, run_dir, expert=make_expert(training), log=lambda _msg: None)
    (run_dir / "config.json").write_text(json.dumps(training.to_dict(), indent=1))
    sent = [0]

    def flush() -> None:
        for record in trainer.state.history[sent[0] :]:
            nominal = record["nominal"]
            report(
                {
                    "seed": training.seed,
                    "env_steps": record["env_steps"],
                    "score": record["score"],
                    "best_score": trainer.state.best_score,
                    "reached": nominal.get("reached_fraction"),
                    "overshoot_pct": nominal.get("overshoot_pct"),
                    "energy_j": nominal.get("energy_j"),
                    "run_dir": str(run_dir),
                }
            )
        sent[0] = len(trainer.state.history)

    try:
        trainer.run(until_steps=training.total_steps, progress=lambda _s, _l: flush())
    finally:
        trainer.close()
    history = trainer.state.history
    if not history or history[-1]["env_steps"] != trainer.state.env_steps:
        trainer.evaluate_and_keep_best()
    trainer.save()
    flush()


def tune_trial(config: dict[str, Any]) -> None:
    """`run_trial` as a Ray Tune function trainable, reporting with ``ray.tune.report``
    (the function API of Ray >= 2.41; older Ray had ``ray.train.report``)."""
    tune = import_tune()
    run_trial(config, tune.report)
