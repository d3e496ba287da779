"""The identification report: a markdown file with the parameters (nominal, fitted, truth), the
prediction quality of both twins and a figure per validation motion (measured against the
nominal and the fitted twin)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from policy.campaigns.identification.driving import Session
from policy.campaigns.identification.fitting import FitOutcome
from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.fit.identifiability import combination_value
from reach_sim_bridge.fit.replay import Replay
from reach_sim_bridge.fit.segments import Segment, segment_delays
from reach_sim_bridge.model.params import ArmParams


def _scored(outcome: FitOutcome, twin: str, seg: Segment) -> Segment:
    """`seg` with the delay offset it was scored with for `twin` (itself if not scored)."""
    for x in outcome.scored.get(twin, []):
        if x.name == seg.name:
            return x
    return seg


def _parameter_lines(outcome: FitOutcome, nominal: ArmParams, truth: ArmParams | None) -> list[str]:
    """The torque scales' verdicts, every parameter as the fit reports it (its value where
    identified, "unidentifiable" and the combination known where not), and what the data pin
    down per joint (the Fisher information's directions)."""
    lines = ["## Torque scales", "", "| joint | verdict | twin | data's 1 sigma | why |"]
    lines.append("|---|---|---|---|---|")
    for j, v in sorted(outcome.scales.items()):
        sigma = "-" if v.sigma is None else f"{100 * v.sigma:.1f} %"
        lines.append(
            f"| {JOINT_LETTERS[j]} | {v.status.value} | {v.value:.3f} | {sigma} | {v.reason} |"
        )
    header = "| parameter | nominal | reported | 1 sigma |"
    rule = "|---|---|---|---|"
    if truth is not None:
        header += " truth | error |"
        rule += "---|---|"
    lines += ["", "## Parameters", "", header, rule]

    def truth_cells(name: str, value: float) -> str:
        if truth is None:
            return ""
        true = combination_value(truth, name)
        # a frictionless joint has no relative error: give the difference
        err = f"{100 * (value - true) / true:+.1f} %" if true != 0 else f"{value - true:+.2g} (abs)"
        return f" {true:.4g} | {err} |"

    for name, e in outcome.identified.items():
        field, rest = name.split("[")
        nom = getattr(nominal, field)[JOINT_LETTERS.index(rest.rstrip("]"))]
        lines.append(
            f"| {name} | {nom:.4g} | {e.value:.4g} | {e.sigma:.2g} |{truth_cells(name, e.value)}"
        )
    for name, u in outcome.unidentifiable.items():
        field, rest = name.split("[")
        nom = getattr(nominal, field)[JOINT_LETTERS.index(rest.rstrip("]"))]
        if u.known is None:
            row = f"| {name} | {nom:.4g} | unidentifiable (twin: {u.twin_value:.4g}) | - |"
            lines.append(row + (" - | - |" if truth is not None else ""))
            continue
        k = u.known
        row = (
            f"| {name} | {nom:.4g} | unidentifiable (twin: {u.twin_value:.4g}); known "
            f"{k.name} = {k.value:.4g} | {k.sigma:.2g} |"
        )
        lines.append(row + truth_cells(k.name, k.value))
    lines += [
        "",
        "## What the data pin down",
        "",
        "Per joint, the directions of its fit's Fisher information in log-parameters, best "
        "determined first: the product of the parameters to the powers given, and its "
        "relative 1 sigma (the residuals' correlation in time counted; the model assumed "
        "exact).",
        "",
    ]
    for j, r in sorted(outcome.results.items()):
        if r.fisher is None:
            continue
        lines.append(f"- **{JOINT_LETTERS[j]}**:")
        for d in r.fisher.directions():
            lines.append(f"  - {100 * d.sigma:.3g} %: {d.describe(r.fisher.refs)}")
    return lines


def write_report(
    outcome: FitOutcome,
    replay: Replay,
    segments: Sequence[Segment],
    out_dir: Path,
    window_s: float,
    session: Session | None,
    truth: ArmParams | None,
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    nominal = ArmParams()
    lines = ["# Identification report", ""]
    if session is not None:
        lines += [
            f"Arm time: {session.arm_seconds:.1f} s excitation + ~{session.move_seconds:.1f} s "
            f"moves; fit: {outcome.fit_seconds:.0f} s CPU-bound wall time.",
            "",
        ]
    delays = np.concatenate([segment_delays(x) for x in outcome.scored.get("fitted", segments)])
    lines += [
        f"Transport delay (measured per command from the driver's timestamps, plus a "
        f"per-segment offset): median {1e3 * float(np.median(delays)):.1f} ms, 99th percentile "
        f"{1e3 * float(np.percentile(delays, 99)):.1f} ms; the arm takes commands every "
        f"{outcome.quantum_s * 1e3:g} ms (chosen by the fit).",
        "",
    ]
    lines += _parameter_lines(outcome, nominal, truth)
    lines += [
        "",
        f"## Prediction quality ({window_s:g} s windows from the measured state, and open "
        "loop over whole segments)",
        "",
        "| motions / joint | twin | R^2 window | RMS window mrad | R^2 open loop | "
        "RMS open loop mrad |",
        "|---|---|---|---|---|---|",
    ]
    for key in outcome.fitted_quality:
        for twin, table in (
            ("nominal", outcome.nominal_quality),
            ("fitted", outcome.fitted_quality),
        ):
            qw, qo = table[key]["window"], table[key]["open_loop"]
            lines.append(
                f"| {key} | {twin} | {qw['r2']:.4f} | {qw['rms_mrad']:.2f} | {qo['r2']:.4f} | "
                f"{qo['rms_mrad']:.2f} |"
            )
    lines += ["", "## Validation motions", ""]
    for seg in segments:
        if seg.role != "validate":
            continue
        j = seg.joint
        t = np.arange(seg.ticks + 1) * seg.period
        fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
        nom_seg = _scored(outcome, "nominal", seg)
        fit_seg = _scored(outcome, "fitted", seg)
        nom_r = replay.simulate(nominal, 0.0, nom_seg, window_s)
        fit_r = replay.simulate(outcome.params, 0.0, fit_seg, window_s)
        axes[0].plot(t, seg.q[:, j], "k", lw=1.5, label="measured")
        axes[0].plot(t, nom_r.q[:, j], "C1", lw=1, label="nominal twin")
        axes[0].plot(t, fit_r.q[:, j], "C0--", lw=1, label="fitted twin")
        axes[0].set_ylabel(f"{JOINT_LETTERS[j]} angle (rad)")
        axes[0].legend(loc="best", fontsize=8)
        axes[1].plot(t, 1e3 * (nom_r.q[:, j] - seg.q[:, j]), "C1", lw=1, label="nominal")
        axes[1].plot(t, 1e3 * (fit_r.q[:, j] - seg.q[:, j]), "C0", lw=1, label="fitted")
        axes[1].set_ylabel("error (mrad)")
        axes[1].legend(loc="best", fontsize=8)
        axes[2].plot(t, seg.command_mA[:, j], "k", lw=1)
        axes[2].set_ylabel("command (mA)")
        axes[2].set_xlabel(f"arm time (s); {window_s:g} s windows start from the measured state")
        fig.suptitle(f"{seg.name}: {seg.meta.get('wave', '')}")
        fig.tight_layout()
        png = out_dir / f"{seg.name}.png"
        fig.savefig(png, dpi=90)
        plt.close(fig)
        lines += [f"![{seg.name}]({png.name})", ""]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
