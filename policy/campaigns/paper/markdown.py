"""The generated block of docs/results.md: Table I with the paper's rows, confidence
intervals (policy/campaigns/stats.py), paired differences, other seeds and the scenarios."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from typing import Any

import numpy as np

from policy.campaigns.evaluation import EpisodeResult, RunConfig
from policy.campaigns.paper.figures import FIGURE_CONTROLLERS
from policy.campaigns.paper.settings import BEGIN, END, Settings
from policy.campaigns.paper.table import summary, values
from policy.campaigns.stats import bootstrap_ci, paired_difference_ci
from policy.tasks.scenarios import SCENARIOS, TABLE_HEADS, TABLE_KEYS, wins
from reach_driver.metrics import METRIC_LABELS, metric_label

PAPER_TABLE = {
    "RL (DDPG), paper": (19.86, 0.23, 58.27, 0.0033, 1.43, 6.26),
    "MPC, paper": (13.8, 0.27, 97.64, 0.033, 18.21, 7.96),
}


#: paired comparisons (a - b) reported with bootstrap intervals, when both were run
PAIRS = (
    ("ddpg", "mpc"),
    ("ddpg", "pid"),
    ("ddpg", "ddpg-distilled"),
    ("ddpg-distilled", "mpc"),
    ("ddpg-distilled-pure", "mpc"),
    ("ddpg-distilled", "ddpg-distilled-pure"),
)
#: the learned controller whose wins over the MPC are counted per seed
LEARNED = "ddpg"
SHORT = {k: METRIC_LABELS[k][0] for k in TABLE_KEYS}


def _fmt_row(name: str, s: dict[str, float]) -> str:
    return (
        f"| {name} | {s['energy_j']:.2f} | {s['rmse']:.3f} | {s['mie']:.3f} | "
        f"{s['msse']:.4f} | {s['overshoot_pct']:.2f} | {s['settling_time_s']:.2f} | "
        f"{s['reached']:.2f} | {s['rmse'] / s['rmse_floor']:.3f} |"
    )


# the scenario table's columns after "max final abs(e)", in order
SCENARIO_KEYS = ("overshoot_pct", "settling_time_s", "rmse", "energy_j")

# per metric: the number format in the CI tables (names and units: METRIC_LABELS)
CI_FORMAT = {
    "energy_j": ".2f",
    "rmse": ".4f",
    "mie": ".4f",
    "msse": ".6f",
    "overshoot_pct": ".2f",
    "settling_time_s": ".3f",
}


def ci_cell(mean: float, low: float, high: float, key: str, signed: bool = False) -> str:
    """mean [low, high] in the metric's unit (`CI_FORMAT`); a difference (signed) gets enough
    decimals for two significant digits of its interval's half-width."""
    fmt = CI_FORMAT[key]
    if signed:
        half = 0.5 * (high - low)
        digits = int(fmt[1:-1])
        if half > 0:
            digits = max(digits, int(-math.floor(math.log10(half))) + 1)
        fmt = f"+.{digits}f"
    return f"{mean:{fmt}} [{low:{fmt}}, {high:{fmt}}]"


def ci_lines(table: dict[str, dict[str, Any]], n: int, resamples: int, ci_seed: int) -> list[str]:
    heads = [metric_label(k) for k in TABLE_KEYS]
    lines = [
        "",
        f"95 % confidence intervals of the means above, across the {n} episodes (percentile "
        f"bootstrap, {resamples} resamples, seed {ci_seed}): mean [low, high]. They describe "
        "the spread over random targets and arms, which all controllers share; for whether "
        "one controller beats another, see the paired differences below.",
        "",
        "| controller | " + " | ".join(heads) + " |",
        "|---|" + "---|" * len(heads),
    ]
    for name, run in table.items():
        cells = []
        for k in TABLE_KEYS:
            v = values(run, k)
            low, high = bootstrap_ci(v, resamples=resamples, seed=ci_seed)
            cells.append(ci_cell(float(np.mean(v)), low, high, k))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def paired_lines(
    every: dict[int, dict[str, dict[str, Any]]], main_seed: int, resamples: int, ci_seed: int
) -> tuple[list[str], dict[str, Any]]:
    """ddpg - MPC (and the other PAIRS) per metric, paired by episode: on Table I's
    seed and pooled over every seed run. Returns the lines and the numbers (for runs/paper JSON)."""
    pairs = [(a, b) for a, b in PAIRS if all(a in every[sd] and b in every[sd] for sd in every)]
    if not pairs:
        return [], {}
    seeds = list(every)
    pooled_n = sum(len(every[sd][pairs[0][0]]["episodes"]) for sd in seeds)
    multi = len(seeds) > 1
    lines = [
        "",
        "### Paired differences, per episode (a - b; negative = a better, every metric is "
        "lower-is-better)",
        "",
        f"Each pair ran the same episodes (targets, sensor noise and degraded arm), so the "
        f"per-episode difference removes the spread they share. Mean difference and its 95 % "
        f"confidence interval (percentile bootstrap over episodes, {resamples} resamples, seed "
        f"{ci_seed}); 'rel.' is the difference relative to b's mean. "
        + (
            f"Pooled: the {pooled_n} episodes of seeds {', '.join(map(str, seeds))} together "
            "(each seed draws its episodes independently from the same distribution)."
            if multi
            else ""
        ),
        "",
        f"| a - b | metric | seed {main_seed}: diff [95 % CI] | rel. [%] | "
        + (
            f"pooled ({pooled_n}): diff [95 % CI] | rel. [%] | a better / tied in |"
            if multi
            else ""
        )
        + ("" if multi else "a better / tied in |"),
        "|---|---|---|---|" + ("---|---|---|" if multi else "---|"),
    ]
    unresolved: dict[str, list[str]] = {}
    numbers: dict[str, Any] = {}
    for a, b in pairs:
        label = f"{a} - {b}"
        numbers[label] = {}
        for k in TABLE_KEYS:
            cells = []
            for which, sds in (("seed", [main_seed]), ("pooled", seeds)):
                if which == "pooled" and not multi:
                    continue
                va = np.concatenate([values(every[sd][a], k) for sd in sds])
                vb = np.concatenate([values(every[sd][b], k) for sd in sds])
                d = paired_difference_ci(va, vb, resamples=resamples, seed=ci_seed)
                ref = float(np.mean(vb))
                rel = f"{100 * d.estimate / ref:+.1f}" if ref != 0 else "-"
                cells += [ci_cell(d.estimate, d.low, d.high, k, signed=True), rel]
                numbers[label].setdefault(which, {})[k] = {
                    **dataclasses.asdict(d),
                    "b_mean": ref,
                }
                if not d.excludes_zero:
                    tag = f"seed {main_seed}" if which == "seed" else "pooled"
                    unresolved.setdefault(f"{label}, {tag}", []).append(SHORT[k])
            last = d  # the pooled one when there is one
            lines.append(
                f"| {label} | {metric_label(k)} | "
                + " | ".join(cells)
                + f" | {last.a_better} / {last.ties} of {last.n} |"
            )
    lines += [
        "",
        "Intervals that contain 0 (the sign of the difference is not resolved at 95 %): "
        + (
            "; ".join(f"{where}: {', '.join(ks)}" for where, ks in unresolved.items())
            if unresolved
            else "none"
        )
        + ".",
    ]
    return lines, numbers


def _summary(run: Any) -> dict[str, float]:
    """The means of a table run dict, or of anything with a `summary()` (an `Evaluation`)."""
    return run.summary() if callable(getattr(run, "summary", None)) else summary(run)


def seed_lines(
    more: dict[int, dict[str, Any]], table: dict[str, Any], seed: int, n: int
) -> list[str]:
    """The comparison repeated on other seeds, and how often `LEARNED` beats MPC per metric."""
    every = {seed: table, **more}
    lines = [
        "",
        f"### The same comparison on other seeds ({n} random targets each, same "
        "conditions; episode set, noise and parameter draws all from the seed)",
        "",
        "| seed | controller | " + " | ".join(TABLE_HEADS) + " | reached |",
        "|---|---|" + "---|" * (len(TABLE_HEADS) + 1),
    ]
    for sd, runs in every.items():
        for name, run in runs.items():
            s = _summary(run)
            lines.append(
                f"| {sd} | {name} | {s['energy_j']:.2f} | {s['rmse']:.4f} | "
                f"{s['mie']:.4f} | {s['msse']:.5f} | {s['overshoot_pct']:.2f} | "
                f"{s['settling_time_s']:.3f} | {s['reached']:.2f} |"
            )
    pairs = [runs for runs in every.values() if LEARNED in runs and "mpc" in runs]
    if pairs:
        counts = {k: 0 for k in TABLE_KEYS}
        for runs in pairs:
            for k, better in wins(_summary(runs[LEARNED]), _summary(runs["mpc"])).items():
                counts[k] += better
        lines += [
            "",
            f"{LEARNED} better than MPC on {len(pairs)} seeds: "
            + ", ".join(f"{SHORT[k]} {counts[k]}/{len(pairs)}" for k in TABLE_KEYS)
            + ". (Per-seed means; a tie is not a win.)",
        ]
    return lines


def conditions(config: RunConfig) -> str:
    cond = []
    if config.noise is not None:
        cond.append(
            f"sensor noise sigma {config.noise.position_std} rad / "
            f"{config.noise.velocity_std} rad/s"
        )
    if config.param_spread > 0:
        cond.append(f"arm parameters degraded by U(1 +- {config.param_spread:g})")
    return ", ".join(cond) if cond else "nominal arm, no noise"


def markdown(
    settings: Settings,
    scenarios: dict[str, list[EpisodeResult]],
    table: dict[str, dict[str, Any]],
    more: dict[int, dict[str, dict[str, Any]]],
    table_config: RunConfig,
    scenario_config: RunConfig,
    figure_links: dict[int, str],
    skipped: dict[str, str],
    resamples: int,
    ci_seed: int,
    reused: list[str],
) -> tuple[str, dict[str, Any]]:
    lines = [BEGIN, f"<!-- settings: {json.dumps(settings.to_dict(), sort_keys=True)} -->", ""]
    numbers: dict[str, Any] = {}
    if table:
        n = settings.n
        lines += [
            f"### Table I: {n} random targets (seed {settings.seed}, "
            f"{conditions(table_config)}, "
            f"{table_config.seconds:g} s at {table_config.rate_hz:g} Hz)",
            "",
            "| controller | " + " | ".join(TABLE_HEADS) + " | reached | RMSE / floor |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        floor = None
        for name, run in table.items():
            s = summary(run)
            floor = s["rmse_floor"]
            lines.append(_fmt_row(name, s))
        for name, row in PAPER_TABLE.items():
            lines.append(f"| {name} | " + " | ".join(f"{v:g}" for v in row) + " | - | - |")
        if floor is not None:
            lines += ["", f"RMSE floor (no-load speed, same episodes): {floor:.3f} rad."]
        for name, run in table.items():
            st = run.get("controller_stats", {}).get("solve_time_s")
            if st:
                lines.append(
                    f"{name} solve time over the table's {st['n']} solves: "
                    f"p50 {st['p50'] * 1e3:.1f} ms, p99 {st['p99'] * 1e3:.1f} ms, "
                    f"max {st['max'] * 1e3:.1f} ms; {st['over_period']} over the "
                    f"{1e3 / table_config.rate_hz:.0f} ms control period, "
                    f"{st['unconverged']} stopped unconverged (iterate used)."
                )
        loads = [run["machine"]["load1"] for run in table.values() if "machine" in run]
        lines.append(
            f"Machine: {os.cpu_count()} cores, 1-minute load average "
            + (
                (
                    f"{min(loads):.1f}"
                    if f"{min(loads):.1f}" == f"{max(loads):.1f}"
                    else f"{min(loads):.1f}-{max(loads):.1f}"
                )
                + " while the table ran"
                if len(loads) == len(table)
                else f"not recorded while the table ran, {os.getloadavg()[0]:.1f} when it "
                "was written"
            )
            + " (other jobs share the cores; solve times depend on it)."
        )
        lines += ci_lines(table, n, resamples, ci_seed)
    for name, why in skipped.items():
        lines.append(f"{name}: not run ({why}).")
    if more:
        every = {settings.seed: table, **more}
        lines += seed_lines(more, table, settings.seed, settings.n)
    else:
        every = {settings.seed: table} if table else {}
    if every:
        extra, numbers = paired_lines(every, settings.seed, resamples, ci_seed)
        lines += extra
    if scenarios:
        lines += [
            "",
            f"### Scenarios ({conditions(scenario_config)}, {scenario_config.seconds:g} s at "
            f"{scenario_config.rate_hz:g} Hz)",
            "",
            "| scenario | controller | reached | max final abs(e) [rad] | "
            + " | ".join(metric_label(k) for k in SCENARIO_KEYS)
            + " |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for sc in SCENARIOS:
            for name, results in scenarios.items():
                r = results[sc.number - 1]
                m = r.metrics
                lines.append(
                    f"| {sc.number}. {sc.title} | {name} | {'yes' if m.reached else 'no'} | "
                    f"{np.abs(r.final_error).max():.4f} | {m.overshoot_pct:.2f} | "
                    f"{m.settling_time_s:.2f} | {m.rmse:.3f} | {m.energy_j:.2f} |"
                )
        lines.append("")
        for sc in SCENARIOS:
            if sc.number in figure_links:
                shown = ", ".join(n for n in FIGURE_CONTROLLERS if n in scenarios) or ", ".join(
                    scenarios
                )
                lines += [
                    f"![scenario {sc.number} ({sc.title}): {shown}]({figure_links[sc.number]})",
                    "",
                ]
    if reused:
        lines += [
            f"Table runs reloaded from their JSON (same controller, episodes and settings): "
            f"{', '.join(reused)}.",
            "",
        ]
    lines.append(END)
    return "\n".join(lines), numbers
