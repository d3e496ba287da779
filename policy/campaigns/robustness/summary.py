"""A robustness campaign's rows summarised: metrics with 95 % bootstrap intervals
(policy/campaigns/stats.py), the worst arms by overshoot, failures by factor level, how the
overshoots came about and where they live."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
from typing import Any

import numpy as np

from policy.campaigns.robustness.arms import ENVELOPE, SETS
from policy.campaigns.stats import bootstrap_ci
from policy.tasks.envelope import Envelope
from protocol.alpha5 import JOINT_LETTERS
from reach_driver.metrics import ARRIVAL_SPEED_RAD_S, REACHED_TOL_RAD
from reach_sim_bridge.model.sensors import SensorNoise

OVERSHOOT_TARGET_PCT = 2.0
WORST = 8

METRICS: tuple[tuple[str, str, str], ...] = (
    ("reached", "reached", "frac"),
    ("at_rest", "at rest", "frac"),
    ("overshoot_pct", "overshoot [%]", "mean"),
    ("settling_time_s", "settling [s]", "mean"),
    ("energy_j", "energy [J]", "mean"),
)


def ci_summary(values: Sequence[float], seed: int = 0) -> dict[str, float]:
    arr = np.asarray(values, dtype=float)
    low, high = bootstrap_ci(arr, seed=seed)
    return {"mean": float(arr.mean()), "low": low, "high": high, "max": float(arr.max())}


def _spans(envelope: Envelope) -> dict[str, tuple[float, float]]:
    return {
        f.name: getattr(envelope, f.name)
        for f in fields(envelope)
        if isinstance(getattr(envelope, f.name), tuple)
    }


def factor_level(name: str, value: float, factors: dict[str, float], envelope: Envelope) -> str:
    """A factor's level for the failure table: low / high half of its range; the weak joint
    by letter; torque scale only where a joint is weak."""
    if name == "weak_joint":
        return "none" if value < 0 else JOINT_LETTERS[int(value)]
    if name == "torque_scale" and factors.get("weak_joint", -1.0) < 0:
        return "no weak joint"
    span = _spans(envelope)[name]
    mid = 0.5 * (span[0] + span[1])
    return "low" if value <= mid else "high"


FACTOR_ORDER = (
    "coulomb_edc",
    "coulomb_b",
    "viscous",
    "armature",
    "link_mass",
    "buoyancy",
    "weak_joint",
    "torque_scale",
    "noise",
    "latency_periods",
)


def failed(row: dict[str, Any]) -> bool:
    return not row["metrics"]["reached"]


def summarize_rows(rows: Sequence[dict[str, Any]], envelope: Envelope = ENVELOPE) -> dict:
    """Metrics with CIs, the worst arms by overshoot and failures by factor level."""
    if not rows:
        raise ValueError("no episodes to summarise")
    m = [r["metrics"] for r in rows]
    out: dict[str, Any] = {"n": len(rows)}
    for key, _, _ in METRICS:
        out[key] = ci_summary([float(x[key]) for x in m])
    out["overshoot_over_target"] = int(
        sum(float(x["overshoot_pct"]) >= OVERSHOOT_TARGET_PCT for x in m)
    )
    out["missed"] = int(sum(not x["reached"] for x in m))
    out["not_at_rest"] = int(sum(not x["at_rest"] for x in m))
    order = sorted(range(len(rows)), key=lambda i: -float(m[i]["overshoot_pct"]))[:WORST]
    out["worst"] = [
        {
            "name": rows[i]["name"],
            "overshoot_pct": float(m[i]["overshoot_pct"]),
            "reached": bool(m[i]["reached"]),
            "at_rest": bool(m[i]["at_rest"]),
            "settling_time_s": float(m[i]["settling_time_s"]),
            "factors": rows[i]["factors"],
        }
        for i in order
    ]
    levels: dict[tuple[str, str], dict[str, int]] = {}
    for r in rows:
        for name in FACTOR_ORDER:
            lv = factor_level(name, r["factors"][name], r["factors"], envelope)
            cell = levels.setdefault(
                (name, lv), {"arms": 0, "missed": 0, "not_at_rest": 0, "over": 0}
            )
            cell["arms"] += 1
            cell["missed"] += int(failed(r))
            cell["not_at_rest"] += int(not r["metrics"]["at_rest"])
            cell["over"] += int(float(r["metrics"]["overshoot_pct"]) >= OVERSHOOT_TARGET_PCT)
    out["by_factor"] = [
        {"factor": name, "level": lv, **cell}
        for (name, lv), cell in sorted(
            levels.items(), key=lambda kv: (FACTOR_ORDER.index(kv[0][0]), kv[0][1])
        )
    ]
    out["overshoot_anatomy"] = overshoot_summary(rows)
    out["shared"] = shared_by_failures(out["by_factor"], out["missed"])
    out["worst_pair"] = worst_pair(rows, envelope)
    return out


def overshoot_summary(rows: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The arms overshooting OVERSHOOT_TARGET_PCT or more, by how their worst joint did it:
    carried through by its approach (crossing its goal at ARRIVAL_SPEED_RAD_S or faster) or
    across slowly near the goal, with the median distance past the goal, and how many went
    no further past than 3 standard deviations of the arm's position noise. None for results
    written before rows carried it."""
    if not rows or any("overshoot" not in r for r in rows):
        return None
    over = [
        r
        for r in rows
        if float(r["metrics"]["overshoot_pct"]) >= OVERSHOOT_TARGET_PCT and r["overshoot"]
    ]
    sigma = SensorNoise().position_std
    out: dict[str, Any] = {"over": len(over)}
    for name, keep in (("arrival", True), ("near_goal", False)):
        sel = [r for r in over if (r["overshoot"]["crossing_speed"] >= ARRIVAL_SPEED_RAD_S) == keep]
        past = [1000.0 * float(r["overshoot"]["past_rad"]) for r in sel]
        out[name] = {
            "arms": len(sel),
            "median_past_mrad": float(np.median(past)) if past else 0.0,
            "by_joint": {
                letter: sum(r["overshoot"]["joint"] == letter for r in sel)
                for letter in JOINT_LETTERS
            },
            "within_noise": sum(
                float(r["overshoot"]["past_rad"]) < 3.0 * sigma * float(r["factors"]["noise"])
                for r in sel
            ),
        }
    return out


def check_factors(factors: Sequence[str]) -> None:
    """A clear error for an `--overshoot-by` list that names no factor or one not in
    `FACTOR_ORDER`."""
    if not factors or any(f not in FACTOR_ORDER for f in factors):
        raise ValueError(
            f"--overshoot-by takes factors of {', '.join(FACTOR_ORDER)}; got {list(factors)}"
        )


def overshoot_by(
    rows: Sequence[dict[str, Any]], factors: Sequence[str], envelope: Envelope = ENVELOPE
) -> list[dict[str, Any]]:
    """The overshoot of the arms grouped by the levels of `factors` (`factor_level`): per
    group, the arms, those at `OVERSHOOT_TARGET_PCT` or more, those of them whose worst joint
    also went further past its goal than the reach tolerance (an absolute floor: 2 % of a 0.1
    rad step is 2 mrad, the noise's size), the median overshoot and distance past, and how
    many of the arms over 2 % were carried through by their approach. Says where the
    overshoot lives, which the failure table by one factor at a time does not."""
    check_factors(factors)
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for r in rows:
        key = tuple(factor_level(f, r["factors"][f], r["factors"], envelope) for f in factors)
        groups.setdefault(key, []).append(r)
    out = []
    for key in sorted(groups):
        sel = groups[key]
        pct = np.array([float(r["metrics"]["overshoot_pct"]) for r in sel])
        anat = [r.get("overshoot") or {} for r in sel]
        past = np.array([float(a.get("past_rad", 0.0)) for a in anat])
        speed = np.array([float(a.get("crossing_speed", 0.0)) for a in anat])
        over = pct >= OVERSHOOT_TARGET_PCT
        out.append(
            {
                "levels": dict(zip(factors, key, strict=True)),
                "arms": len(sel),
                "over": int(over.sum()),
                "over_past_tolerance": int((over & (past > REACHED_TOL_RAD)).sum()),
                "arrivals": int((over & (speed >= ARRIVAL_SPEED_RAD_S)).sum()),
                "median_pct": float(np.median(pct)),
                "median_past_mrad": 1000.0 * float(np.median(past)),
            }
        )
    return out


def shared_by_failures(by_factor: list[dict[str, Any]], missed: int) -> list[str]:
    """What the misses have in common: each factor whose miss rate differs by at least 15
    points between its levels, largest difference first, as "factor level: rate (misses/arms)
    vs other levels' rates"."""
    if missed == 0:
        return []
    spread = []
    for name in FACTOR_ORDER:
        cells = [c for c in by_factor if c["factor"] == name and c["level"] != "no weak joint"]
        if len(cells) < 2:
            continue
        rates = sorted(cells, key=lambda c: -c["missed"] / c["arms"])
        hi, lo = rates[0], rates[-1]
        diff = hi["missed"] / hi["arms"] - lo["missed"] / lo["arms"]
        if diff >= 0.15:
            others = ", ".join(
                f"{c['level']} {100 * c['missed'] / c['arms']:.0f} %" for c in rates[1:]
            )
            spread.append(
                (
                    diff,
                    f"{name} {hi['level']}: {100 * hi['missed'] / hi['arms']:.0f} % missed "
                    f"({hi['missed']}/{hi['arms']}) vs {others}",
                )
            )
    return [text for _, text in sorted(spread, key=lambda x: -x[0])]


def worst_pair(rows: Sequence[dict[str, Any]], envelope: Envelope = ENVELOPE) -> list[dict]:
    """Miss rates over the levels of the two factors whose levels differ most (the first two
    of `shared_by_failures`' order), cell by cell: where the misses concentrate."""
    rates = []
    for name in FACTOR_ORDER:
        if name == "torque_scale":
            continue
        count: dict[str, list[int]] = {}
        for r in rows:
            lv = factor_level(name, r["factors"][name], r["factors"], envelope)
            cell = count.setdefault(lv, [0, 0])
            cell[0] += 1
            cell[1] += int(failed(r))
        if len(count) < 2:
            continue
        values = [m / n for n, m in count.values()]
        rates.append((max(values) - min(values), name))
    rates.sort(reverse=True)
    if len(rates) < 2 or rates[0][0] < 0.15:
        return []
    a, b = rates[0][1], rates[1][1]
    cells: dict[tuple[str, str], list[int]] = {}
    for r in rows:
        f = r["factors"]
        key = (factor_level(a, f[a], f, envelope), factor_level(b, f[b], f, envelope))
        cell = cells.setdefault(key, [0, 0])
        cell[0] += 1
        cell[1] += int(failed(r))
    return [{a: ka, b: kb, "arms": n, "missed": m} for (ka, kb), (n, m) in sorted(cells.items())]


def summaries(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """`summarize_rows` per set present in ``rows``."""
    return {
        s: summarize_rows([r for r in rows if r["set"] == s])
        for s in SETS
        if any(r["set"] == s for r in rows)
    }
