"""The fit of an excitation's segments (`fit`: `reach_sim_bridge.fit` on every joint, then each
twin scored on the fitting and the validation motions), what it writes beside the parameters
(`fit_metadata`) and the controller gap it closes (`check_controllers`)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console

from policy.campaigns.identification.driving import Session
from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.fit.arm_fit import fit_arm, parameter_verdicts, tune_offsets
from reach_sim_bridge.fit.identifiability import ScaleVerdict
from reach_sim_bridge.fit.joint_fit import FitResult
from reach_sim_bridge.fit.replay import DEFAULT_WINDOW_S, Replay, quality, ref_name
from reach_sim_bridge.fit.segments import Segment
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.twin import Estimate, FitMetadata, Unidentified


@dataclass
class FitOutcome:
    """The fit of an excitation: the twin, each joint's fit and how both twins predict."""

    params: ArmParams
    delay_s: float
    results: dict[int, FitResult]
    nominal_quality: dict[str, Any]
    fitted_quality: dict[str, Any]
    fit_seconds: float
    quantum_s: float = 0.0
    fit_starts: bool = True
    # The segments as each twin was scored ("nominal", "fitted"): with their delay offsets.
    scored: dict[str, list[Segment]] = field(default_factory=dict)
    # Per joint, its torque scale's verdict; per parameter what is identified and what not.
    scales: dict[int, ScaleVerdict] = field(default_factory=dict)
    identified: dict[str, Estimate] = field(default_factory=dict)
    unidentifiable: dict[str, Unidentified] = field(default_factory=dict)


def fit(
    segments: Sequence[Segment],
    console: Console,
    window_s: float = DEFAULT_WINDOW_S,
    max_iter: int = 12,
    fit_starts: bool = True,
) -> tuple[FitOutcome, Replay]:
    t0 = time.monotonic()
    replay = Replay(window_s=window_s)
    nominal = ArmParams()

    def on_joint(j: int, r: FitResult) -> None:
        cells = ", ".join(
            f"{ref_name(ref)} {v:.4g} +- {s:.2g}"
            for ref, v, s in zip(r.refs, r.values, r.sigma, strict=True)
        )
        console.print(
            f"fitted {JOINT_LETTERS[j]} in {r.iterations} iterations ({r.rollouts} rollouts): "
            f"{cells}"
        )

    def on_iter(j: int, it: int, cost: float) -> None:
        console.print(f"  {JOINT_LETTERS[j]} iteration {it}: cost {cost:.4g}", style="dim")

    arm_fit = fit_arm(
        replay,
        segments,
        nominal,
        max_iter=max_iter,
        on_joint=on_joint,
        on_iteration=on_iter,
        fit_starts=fit_starts,
    )
    params = arm_fit.params
    identified, unidentifiable = parameter_verdicts(arm_fit)
    for j, verdict in sorted(arm_fit.scales.items()):
        sigma = "" if verdict.sigma is None else f" (data: +-{100 * verdict.sigma:.1f} %)"
        console.print(
            f"torque scale {JOINT_LETTERS[j]}: {verdict.status.value}, twin {verdict.value:.3f}"
            f"{sigma}: {verdict.reason}"
        )
    for name, u in unidentifiable.items():
        if u.known is not None:
            console.print(
                f"{name}: unidentifiable; known {u.known.name} = {u.known.value:.4g} "
                f"+- {u.known.sigma:.2g}"
            )
    nom_q: dict[str, Any] = {}
    fit_q: dict[str, Any] = {}
    # Each twin is scored with the delay offsets that suit it best (one per segment, the
    # part of the delay the timestamps do not see; tuned on the 1 s windows): a nuisance of
    # the measurement, not a parameter of the arm, so the nominal twin gets the same chance.
    scored: dict[str, list[Segment]] = {"nominal": [], "fitted": []}
    for role in ("fit", "validate"):
        for j in sorted({s.joint for s in segments}):
            segs = [s for s in segments if s.joint == j and s.role == role]
            if not segs:
                continue
            key = f"{role}/{JOINT_LETTERS[j]}"
            for twin, p, table in (("nominal", nominal, nom_q), ("fitted", params, fit_q)):
                ready = tune_offsets(replay, p, segs)
                scored[twin].extend(ready)
                for label, w in (("window", window_s), ("open_loop", 0.0)):
                    table.setdefault(key, {})[label] = quality(replay, p, 0.0, ready, w).as_dict()
    outcome = FitOutcome(
        params,
        arm_fit.delay_s,
        arm_fit.results,
        nom_q,
        fit_q,
        time.monotonic() - t0,
        quantum_s=arm_fit.quantum_s,
        fit_starts=fit_starts,
        scored=scored,
        scales=arm_fit.scales,
        identified=identified,
        unidentifiable=unidentifiable,
    )
    return outcome, replay


def fit_metadata(
    outcome: FitOutcome, session: Session | None, window_s: float, log_path: Path | str | None
) -> FitMetadata:
    """What the fitted twin's file keeps of the fit (`FittedTwin.fit`); `log_path`: the log
    (or logs, joined) it read."""
    return FitMetadata(
        method="least squares over MuJoCo rollouts (reach_sim_bridge.fit), multiple "
        f"shooting over {window_s:g} s windows"
        f"{' with fitted starts' if outcome.fit_starts else ''}; docs/identification.md",
        parameters=dict(outcome.identified),
        unidentifiable=dict(outcome.unidentifiable),
        torque_scales={
            JOINT_LETTERS[j]: v.to_json_dict() for j, v in sorted(outcome.scales.items())
        },
        identifiability={
            JOINT_LETTERS[j]: r.fisher.to_json_dict()
            for j, r in sorted(outcome.results.items())
            if r.fisher is not None
        },
        delay_s=outcome.delay_s,
        delay_note="median of the delays the replay used (per command: measured from the "
        "driver's timestamps plus a per-segment offset); not an arm parameter",
        command_step_s=outcome.quantum_s,
        delay_offsets_ms={
            seg.name: round(seg.offset_s * 1e3, 3) for seg in outcome.scored.get("fitted", [])
        },
        quality_fitted=outcome.fitted_quality,
        quality_nominal=outcome.nominal_quality,
        sigma_note="1 sigma from sqrt(diag(s^2 (J^T J)^-1)) at the optimum, s^2 the residual "
        "variance times the residuals' correlation time in rows; it assumes the model exact. "
        "Parameters the data cannot fix are under 'unidentifiable' with the combination they "
        "do fix; each joint's torque scale's verdict under 'torque_scales'",
        arm_seconds=None if session is None else session.arm_seconds + session.move_seconds,
        log=None if log_path is None else str(log_path),
        fit_seconds=outcome.fit_seconds,
    )


def check_controllers(
    names: Sequence[str], truth: ArmParams, fitted: ArmParams, episodes: int, console: Console
) -> tuple[str, list[dict[str, Any]]]:
    """`twin_gap.measure_gap` on the fit: its markdown and per-controller summary."""
    # The controllers and their evaluation are only needed here (and load the actor's weights).
    from policy.campaigns.evaluation import random_episodes
    from policy.campaigns.identification.twin_gap import markdown, measure_gap

    gaps = measure_gap(
        [n.strip() for n in names if n.strip()], truth, fitted, random_episodes(episodes, 0)
    )
    for g in gaps:
        f, n = g.summary()["fitted"], g.summary()["nominal"]
        console.print(
            f"{g.controller}: energy error fitted {100 * f['energy_error_max']:.2f} % "
            f"(nominal {100 * n['energy_error_max']:.2f} %), settling error fitted "
            f"{f['settling_error_max_s']:.3f} s (nominal {n['settling_error_max_s']:.3f} s), "
            f"worst of {len(g.episodes)} episodes; targets "
            f"{'met' if f['meets_targets'] else 'NOT met'}"
        )
    return markdown(gaps), [g.summary() for g in gaps]
