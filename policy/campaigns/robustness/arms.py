"""The arms of a robustness campaign: the envelope's feasible corners and random draws
(policy/tasks/envelope.py), each with its own episode, noise, exported file and twin.

Arm i of a set (corners or draws) starts and aims at two points drawn uniformly in the
evaluation workspace from ``default_rng([seed, set, i])`` (set 0: corners, 1: draws), and its
sensor noise uses episode seed ``seed + 100000 * set + i``. A corner's episode therefore does
not depend on ``--max-corners``, and the first N draws of ``--draws 1000`` are ``--draws N``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.observation import WORKSPACE_HIGH, WORKSPACE_LOW
from policy.tasks.envelope import Envelope, Selection, Variant, corners, draws
from policy.tasks.episodes import Episode, RunConfig
from reach_sim_bridge.model.params import ArmParams, load_arm_params, save_arm_params
from reach_sim_bridge.model.sensors import SensorNoise

SETS = ("corners", "draws")
SET_SEED_STRIDE = 100_000

ENVELOPE = Envelope()


@dataclass(frozen=True)
class Arm:
    """One arm of a set, as a campaign runs it."""

    set: str
    index: int  # in the set before any subsampling: the episode and the noise depend on it
    variant: Variant


def arm_episode(seed: int, set_name: str, index: int) -> Episode:
    """Start and target of arm ``index`` of ``set_name``, from that arm's seed alone."""
    rng = np.random.default_rng([seed, SETS.index(set_name), index])
    return Episode(
        start=rng.uniform(WORKSPACE_LOW, WORKSPACE_HIGH),
        target=rng.uniform(WORKSPACE_LOW, WORKSPACE_HIGH),
    )


def subsample(n: int, k: int | None, seed: int) -> list[int]:
    """The first ``k`` of a permutation of ``range(n)`` seeded by ``seed`` (all of them when k
    is None or >= n), in increasing order: a smaller k picks a subset of a larger one's."""
    if k is None or k >= n:
        return list(range(n))
    if k < 1:
        raise ValueError(f"--max-corners must be at least 1, got {k}")
    rng = np.random.default_rng([seed, 2])
    return sorted(int(i) for i in rng.permutation(n)[:k])


@dataclass(frozen=True)
class Plan:
    """The arms to run and the infeasible ones left out, per set."""

    arms: list[Arm]
    infeasible: dict[str, list[tuple[Variant, str]]]
    available: dict[str, int]  # feasible arms in each set before subsampling


def plan(
    seed: int,
    use_corners: bool,
    n_draws: int | None,
    max_corners: int | None = None,
    envelope: Envelope = ENVELOPE,
    corner_selection: Selection | None = None,
    base: ArmParams | None = None,
) -> Plan:
    if not use_corners and not n_draws:
        raise ValueError("nothing to run: give --corners and/or --draws N")
    arms: list[Arm] = []
    infeasible: dict[str, list[tuple[Variant, str]]] = {}
    available: dict[str, int] = {}
    if use_corners:
        sel = corner_selection or corners(envelope, base)
        infeasible["corners"] = sel.infeasible
        available["corners"] = len(sel.variants)
        for i in subsample(len(sel.variants), max_corners, seed):
            arms.append(Arm("corners", i, sel.variants[i]))
    if n_draws:
        sel = draws(n_draws, seed, envelope, base)
        infeasible["draws"] = sel.infeasible
        available["draws"] = len(sel.variants)
        arms.extend(Arm("draws", i, v) for i, v in enumerate(sel.variants))
    return Plan(arms, infeasible, available)


def base_config(seed: int, set_name: str, seconds: float, rate_hz: float) -> RunConfig:
    return RunConfig(
        seconds=seconds,
        rate_hz=rate_hz,
        noise=SensorNoise(),
        seed=seed + SET_SEED_STRIDE * SETS.index(set_name),
    )


def arm_params(arm: Arm) -> ArmParams:
    """The arm's parameters with its weak joint's torque scale: the hidden arm itself."""
    return replace(arm.variant.params, torque_scale=arm.variant.torque_scale)


def arm_noise(arm: Arm) -> tuple[float, float]:
    """The arm's sensor noise (rad, rad/s): the standard noise times its multiple."""
    sensor = SensorNoise()
    return (
        sensor.position_std * arm.variant.noise_scale,
        sensor.velocity_std * arm.variant.noise_scale,
    )


def arm_file(arm: Arm) -> str:
    """The arm's file name under `--export-arms` and `--twin-from`."""
    return f"{arm.set}-{arm.index}.json"


def export_arms(arms: Sequence[Arm], out: Path, seed: int) -> list[Path]:
    """Each arm as an arm parameter file (`reach-sim --params`), its sensor noise and
    latency under ``_envelope`` (metadata the loader ignores): the hidden arms an
    identification campaign serves (docs/campaigns.md, "Campaigns on fitted twins")."""
    return [save_arm_params(arm_params(a), out / arm_file(a), envelope_meta(a, seed)) for a in arms]


def envelope_meta(arm: Arm, seed: int) -> dict[str, Any]:
    """An exported arm's metadata: where in the envelope it lies, its noise and latency."""
    return {
        "_envelope": {
            "name": arm.variant.name,
            "set": arm.set,
            "index": arm.index,
            "seed": seed,
            "factors": arm.variant.factors,
            "sensor_noise": list(arm_noise(arm)),
            "latency_periods": arm.variant.latency_periods,
        }
    }


def arm_twin(
    arm: Arm, seed: int, error: float = 0.0, fitted: ArmParams | None = None
) -> dict[str, Any]:
    """What an identification of `arm` would tell a controller: its parameters (the weak
    joint's torque scale included), its loop latency and its sensor's noise, as controller
    parameters `params`, `latency_periods`, `noise_q` and `noise_v`, and how far to trust
    them, `twin_error`. `error` > 0 scales its friction, damping, armature, masses and
    volumes by independent factors in 1 +- error (seeded by the arm), an identification's
    error. `fitted` (an identification's fit of the arm) replaces the parameters; `error`
    is then only the trust."""
    twin = arm_params(arm)
    if fitted is not None:
        twin = fitted
    elif error > 0:
        rng = np.random.default_rng([seed, SETS.index(arm.set), arm.index, 3])
        twin = replace(twin.randomized(rng, error), torque_scale=twin.torque_scale)
    noise_q, noise_v = arm_noise(arm)
    return {
        "params": twin.to_json_dict(),
        "latency_periods": arm.variant.latency_periods,
        "noise_q": noise_q,
        "noise_v": noise_v,
        "twin_error": error,
    }


def read_fitted(directory: Path, arms: Sequence[Arm]) -> dict[tuple[str, int], ArmParams]:
    """The fitted twins in ``directory`` of the planned arms (`arm_file` names; arms without
    one are left out); an error if there are none."""
    if not directory.is_dir():
        raise ValueError(f"--twin-from {directory}: no such directory")
    out = {
        (a.set, a.index): load_arm_params(p)
        for a in arms
        if (p := directory / arm_file(a)).exists()
    }
    if not out:
        raise ValueError(
            f"--twin-from {directory}: no fitted twin of a planned arm (names such as "
            f"{arm_file(arms[0]) if arms else 'corners-0.json'})"
        )
    return out
