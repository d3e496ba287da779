"""Whether a trained actor meets the Table I line of the learned controller's target.

The line (docs/training.md, "Targets"): on Table I's standard set (the 80 episodes of seeds
2020, 2120, 2220 and 2320: random targets, sensor noise, arms within +-20 %), the actor alone
reaches its goal and rests there in at least 79; its mean overshoot is below the paper's RL row
(1.43 %) and the MPC's; its steady-state error is below the MPC's; energy, RMSE, MIE and
settling time are no more than 1 % above the MPC's; and it beats the PID (the
non-privileged PD with gravity feed-forward on the same noisy readings) on reaching,
overshoot and steady-state error. Verdicts use the means over the 80 episodes; every
comparison also gives the paired 95 % bootstrap interval of the difference, so a pass that
rests on noise shows as one.

Another arm has its own Table I set (`ARM_TABLE_SEEDS`: the Bravo 7's is the 20 random
episodes of seed 7020 in its workspace, under the same noise and +-20 % arms); the line is
the Alpha's, so there `metrics_table` gives each controller's figures with their intervals.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from policy.campaigns.evaluation import evaluate
from policy.campaigns.paper.markdown import CI_FORMAT, ci_cell
from policy.campaigns.paper.table import values
from policy.campaigns.stats import DEFAULT_RESAMPLES, bootstrap_ci, paired_difference_ci
from policy.tasks.episodes import RunConfig, random_episodes
from policy.tasks.scenarios import TABLE_KEYS
from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver.controllers import load_controller
from reach_driver.metrics import metric_label
from reach_sim_bridge.model.sensors import SensorNoise

#: Table I's seeds: 20 random episodes each (docs/results.md)
TABLE_SEEDS = (2020, 2120, 2220, 2320)
EPISODES_PER_SEED = 20
#: each arm's Table I set: the seeds of its random episodes (`random_episodes` in the arm's
#: workspace, `EPISODES_PER_SEED` per seed)
ARM_TABLE_SEEDS: Mapping[str, tuple[int, ...]] = MappingProxyType(
    {ALPHA5.name: TABLE_SEEDS, BRAVO7.name: (7020,)}
)
#: the paper's RL row's overshoot (Carlucho et al., Table I), in %
PAPER_RL_OVERSHOOT_PCT = 1.43
#: reached and at rest in at least this share of the episodes (79 of 80)
MIN_REACHED_SHARE = 79 / 80
#: energy, RMSE, MIE and settling may exceed the MPC's by this fraction
MPC_TOLERANCE = 0.01
#: lower-is-better metrics held to the MPC within the tolerance
WITHIN_TOLERANCE = ("energy_j", "rmse", "mie", "settling_time_s")


@dataclass(frozen=True)
class Check:
    """One item of the line: what was compared, the figures, and the verdict."""

    item: str
    figure: str
    passed: bool

    def __post_init__(self) -> None:
        object.__setattr__(self, "passed", bool(self.passed))  # numpy's bools print oddly


def table_config(seed: int) -> RunConfig:
    """Table I's conditions on one seed: sensor noise and arms degraded by +-20 %."""
    return RunConfig(noise=SensorNoise(0.002, 0.02), seed=seed, param_spread=0.2)


def _cache_name(
    controller: str, params: dict[str, Any], seed: int, model: ArmModel = ALPHA5
) -> str:
    named: dict[str, Any] = {"controller": controller, "params": params}
    if model.name != ALPHA5.name:  # the Alpha's names stay those of runs kept before arms
        named["arm"] = model.name
    key = json.dumps(named, sort_keys=True)
    for value in params.values():  # a weights file: its bytes, so a retrained file reruns
        if isinstance(value, str) and Path(value).is_file():
            key += hashlib.sha256(Path(value).read_bytes()).hexdigest()
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    return f"{controller}-{digest}-seed{seed}.json"


def table_runs(
    controller: str,
    params: dict[str, Any],
    runs: Path,
    seeds: Sequence[int] = TABLE_SEEDS,
    progress: Callable[[str], None] | None = None,
    model: ArmModel = ALPHA5,
) -> list[dict[str, Any]]:
    """The controller on every seed's episodes of `model`, as `Evaluation.to_dict()`; each
    seed's run is kept in `runs` and reused while the arm, the controller, its parameters (a
    weights file by its bytes) and the settings are unchanged."""
    runs.mkdir(parents=True, exist_ok=True)
    out = []
    for seed in seeds:
        config = table_config(seed)
        path = runs / _cache_name(controller, params, seed, model)
        episodes = random_episodes(EPISODES_PER_SEED, seed, model=model)
        run = None
        if path.is_file():
            kept = json.loads(path.read_text(encoding="utf-8"))
            if kept.get("config") == config.to_dict():
                run = kept
        if run is None:
            if progress is not None:
                named = " ".join([controller, *(f"{k}={v}" for k, v in params.items())])
                progress(f"{named} on the {model.title}, seed {seed}")
            run = evaluate(
                load_controller(controller, arm=model, **params), episodes, config, name=controller
            ).to_dict()
            path.write_text(json.dumps(run), encoding="utf-8")
        out.append(run)
    return out


def pooled(runs: Sequence[dict[str, Any]], key: str) -> np.ndarray:
    """One metric over every episode of every seed, in seed order (MSSE in mrad)."""
    scale = 1000.0 if key == "msse" else 1.0
    return scale * np.concatenate([values(run, key).astype(float) for run in runs])


def _label(key: str) -> str:
    return "MSSE [mrad]" if key == "msse" else metric_label(key)


def reached_at_rest(runs: Sequence[dict[str, Any]]) -> np.ndarray:
    return pooled(runs, "reached") * pooled(runs, "at_rest")


def _diff(a: np.ndarray, b: np.ndarray) -> str:
    d = paired_difference_ci(a, b)
    return f"{d.estimate:+.3g} [{d.low:+.3g}, {d.high:+.3g}]"


def line_checks(
    actor: Sequence[dict[str, Any]],
    mpc: Sequence[dict[str, Any]],
    pid: Sequence[dict[str, Any]],
) -> list[Check]:
    """Every item of the Table I line for the actor's runs against the MPC's and the PID's
    on the same episodes (same seeds, in the same order)."""
    checks = []
    ok = reached_at_rest(actor)
    n = ok.size
    need = int(np.ceil(MIN_REACHED_SHARE * n - 1e-9))
    checks.append(
        Check("reached and at rest", f"{int(ok.sum())}/{n} (need {need})", ok.sum() >= need)
    )
    os_a = pooled(actor, "overshoot_pct")
    checks.append(
        Check(
            f"overshoot below the paper's RL row ({PAPER_RL_OVERSHOOT_PCT} %)",
            f"{os_a.mean():.2f} %",
            os_a.mean() < PAPER_RL_OVERSHOOT_PCT,
        )
    )
    for key, tol in [("overshoot_pct", 0.0), ("msse", 0.0)] + [
        (k, MPC_TOLERANCE) for k in WITHIN_TOLERANCE
    ]:
        a, m = pooled(actor, key), pooled(mpc, key)
        limit = m.mean() * (1.0 + tol)
        word = "below the MPC's" if tol == 0.0 else f"within {tol:.0%} of the MPC's"
        checks.append(
            Check(
                f"{_label(key)} {word}",
                f"{a.mean():.4g} vs {m.mean():.4g}; paired diff {_diff(a, m)}",
                bool(a.mean() < limit) if tol == 0.0 else bool(a.mean() <= limit),
            )
        )
    ok_pid = reached_at_rest(pid)
    checks.append(
        Check(
            "reaches at least as often as the PID",
            f"{int(ok.sum())} vs {int(ok_pid.sum())}",
            ok.sum() >= ok_pid.sum(),
        )
    )
    for key in ("overshoot_pct", "msse"):
        a, p = pooled(actor, key), pooled(pid, key)
        checks.append(
            Check(
                f"{_label(key)} below the PID's",
                f"{a.mean():.4g} vs {p.mean():.4g}; paired diff {_diff(a, p)}",
                bool(a.mean() < p.mean()),
            )
        )
    return checks


def metrics_table(
    table: Mapping[str, Sequence[dict[str, Any]]],
    resamples: int = DEFAULT_RESAMPLES,
    ci_seed: int = 0,
) -> list[str]:
    """Table I's metrics per controller (its runs, every seed pooled) as markdown: the mean
    and its 95 % percentile-bootstrap interval over the episodes."""
    keys = ("reached", "at_rest", *TABLE_KEYS)
    heads = [metric_label(k) for k in keys]
    lines = ["| controller | " + " | ".join(heads) + " |", "|---|" + "---|" * len(heads)]
    for name, runs in table.items():
        cells = []
        for key in keys:
            v = np.concatenate([values(run, key).astype(float) for run in runs])
            low, high = bootstrap_ci(v, resamples=resamples, seed=ci_seed)
            mean = float(np.mean(v))
            if key in CI_FORMAT:
                cells.append(ci_cell(mean, low, high, key))
            else:  # a share of the episodes
                cells.append(f"{mean:.2f} [{low:.2f}, {high:.2f}]")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines
