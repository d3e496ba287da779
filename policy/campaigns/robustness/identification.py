"""A robustness campaign's arms identified through the driver (`policy.campaigns.identify`):
the fits `--twin-from` reads, resumable, and their table against the hidden arms."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich.console import Console

from policy.campaigns.identify import (
    IdentifyJob,
    IdentifyResult,
    Verdict,
    fit_row,
    run_identify_job,
    run_row,
    verdict,
    verdict_counts,
)
from policy.campaigns.parallel import run_on_ray
from policy.campaigns.robustness.arms import Arm, arm_file, arm_noise, arm_params, envelope_meta
from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.model.params import save_arm_params

SUMMARY_FILE = "identify-summary.json"


def identify_arms(
    arms: Sequence[Arm],
    out: Path,
    seed: int,
    console: Console,
    *,
    speed: float = 1.0,
    identify_args: Sequence[str] = (),
    workers: int | None = None,
    address: str | None = None,
    virtual: bool = False,
) -> list[dict[str, Any]]:
    """Identify each arm through the driver (`policy.campaigns.identify`): OUT/SET-INDEX.json,
    the fit `--twin-from OUT` reads, beside its log (.log.npz) and the hidden arm
    (.hidden.json); OUT/identify-summary.json has every arm's fit against its truth. Arms
    already fitted in OUT are skipped, so an interrupted campaign resumes. `virtual`: each arm
    excited in the identification's own process instead (`IdentifyJob.virtual`), its sensor
    noise seeded by the arm's index."""
    out.mkdir(parents=True, exist_ok=True)
    summary_path = out / SUMMARY_FILE
    runs: dict[str, dict[str, Any]] = {}
    if summary_path.exists():
        runs = {r["arm"]: r for r in json.loads(summary_path.read_text(encoding="utf-8"))}
    todo: list[IdentifyJob] = []
    for a in arms:
        stem = arm_file(a).removesuffix(".json")
        hidden = save_arm_params(arm_params(a), out / f"{stem}.hidden.json", envelope_meta(a, seed))
        if (out / arm_file(a)).exists():
            continue
        todo.append(
            IdentifyJob(
                stem,
                hidden.read_text(encoding="utf-8"),
                arm_noise(a),
                speed=speed,
                identify_args=tuple(identify_args),
                virtual=virtual,
                seed=a.index,
            )
        )
    skipped = len(arms) - len(todo)
    console.print(
        f"identifying {len(todo)} arms into {out}"
        + (f" ({skipped} already fitted there, skipped)" if skipped else "")
    )
    t0 = time.monotonic()
    finished = 0

    def keep(result: IdentifyResult) -> None:
        nonlocal finished
        finished += 1
        if result.ok:
            assert result.fitted_json is not None
            (out / f"{result.name}.json").write_text(result.fitted_json, encoding="utf-8")
            (out / f"{result.name}.failed.txt").unlink(missing_ok=True)  # an earlier attempt's
        else:
            (out / f"{result.name}.failed.txt").write_text(
                "\n".join(result.tail) + "\n", encoding="utf-8"
            )
        if result.log_npz is not None:
            (out / f"{result.name}.log.npz").write_bytes(result.log_npz)
        runs[result.name] = run_row(result)
        summary_path.write_text(json.dumps(list(runs.values()), indent=1), encoding="utf-8")
        elapsed = time.monotonic() - t0
        state = "fitted" if result.ok else f"FAILED ({result.returncode}), see .failed.txt"
        console.print(
            f"{result.name}: {state} in {result.wall_s:.0f} s; {finished}/{len(todo)} done, "
            f"eta {elapsed / finished * (len(todo) - finished):.0f} s"
        )

    if todo:
        if workers is None and address is None:
            for job in todo:
                keep(run_identify_job(job))
        else:
            run_on_ray(run_identify_job, todo, workers, address, keep)
    return identify_rows(arms, out, runs)


def identify_rows(
    arms: Sequence[Arm], out: Path, runs: dict[str, dict[str, Any]]
) -> list[dict[str, Any]]:
    """Each arm's fit in ``out`` against its hidden arm (recomputed from the files), or how
    its identification failed."""
    rows = []
    for a in arms:
        stem = arm_file(a).removesuffix(".json")
        fit, hidden = out / f"{stem}.json", out / f"{stem}.hidden.json"
        if fit.exists():
            truth, fitted = (json.loads(f.read_text(encoding="utf-8")) for f in (hidden, fit))
            rows.append(fit_row(stem, truth, fitted, runs.get(stem)))
        elif stem in runs:
            rows.append(runs[stem])
    return rows


def identify_table(rows: Sequence[dict[str, Any]]) -> str:
    """The fits against their hidden arms, one line per arm (markdown): the true torque
    scales where not 1; each joint's torque scale as the fit reports it (its value where
    identified or taken as the anchor, "?" where unidentifiable); the worst error of what the
    fit reports (a value where it identified the parameter, the combination it gave where it
    did not: `policy.campaigns.identify.reported_errors`) and which; the PID's energy on the
    fitted and the nominal twin against the arm's (`--check-controller pid`, worst episode);
    and the validation motions' replay RMS through the fitted (and the nominal) twin."""
    lines = [
        "| arm | true torque scales | reported scale E / D / C / B | worst reported error "
        "| PID energy error fitted (nominal) | validation RMS fitted (nominal) [mrad] |",
        "|---|---|---|---|---|---|",
    ]

    def num(value: Any, fmt: str) -> str:
        return "-" if value is None else format(value, fmt)

    for r in rows:
        if "joints" not in r:
            lines.append(f"| {r['arm']} | failed ({r.get('returncode')}) | | | | |")
            continue
        j = [r["joints"][x] for x in JOINT_LETTERS]
        weak = ", ".join(
            f"{x} {q['true_torque_scale']:.2f}"
            for x, q in zip(JOINT_LETTERS, j, strict=True)
            if q["true_torque_scale"] != 1
        )
        scales = " / ".join(
            "?" if q.get("scale_status") == "unidentifiable" else f"{q['torque_scale']:.2f}"
            for q in j
        )
        worst, which = 0.0, "-"
        for q in j:
            for name, e in q.get("reported", {}).items():
                if e["error"] is not None and abs(e["error"]) > abs(worst):
                    worst, which = e["error"], name if e["as"] == "value" else e["as"]
        gap = next((g for g in r.get("controller_gap") or [] if g["controller"] == "pid"), None)
        energy = (
            "-"
            if gap is None
            else f"{100 * gap['fitted']['energy_error_max']:.1f} % "
            f"({100 * gap['nominal']['energy_error_max']:.0f} %)"
        )
        rms = ", ".join(
            f"{x} {num(q['validate_rms_mrad_fitted'], '.1f')} "
            f"({num(q['validate_rms_mrad_nominal'], '.0f')})"
            for x, q in zip(JOINT_LETTERS, j, strict=True)
        )
        lines.append(
            f"| {r['arm']} | {weak or 'all 1'} | {scales} | {100 * worst:+.1f} % ({which}) "
            f"| {energy} | {rms} |"
        )
    return "\n".join(lines)


ENERGY_TOLERANCE = 0.05
"""Issue 46's: a PID's energy on the fitted twin within 5 % of its energy on the arm."""


def verdict_table(rows: Sequence[dict[str, Any]]) -> str:
    """Issue 46's target over the fits, per parameter (markdown): how many are reported within
    10 % of the arm's, reported unidentifiable with the combination the data fix within 10 %,
    or confidently wrong (`policy.campaigns.identify.verdict`); then each wrong one, and how
    many fitted twins put the PID's energy within 5 % of the arm's (worst episode, with
    `--check-controller pid`)."""
    kinds = list(Verdict)
    counts = verdict_counts(rows)
    lines = [
        "| parameter | " + " | ".join(k.value for k in kinds) + " |",
        "|---|" + "---|" * len(kinds),
    ]
    for name in sorted(counts):
        lines.append(f"| {name} | " + " | ".join(str(counts[name][k]) for k in kinds) + " |")
    total = {k: sum(c[k] for c in counts.values()) for k in kinds}
    lines.append("| all | " + " | ".join(str(total[k]) for k in kinds) + " |")
    for r in rows:
        for letter, joint in r.get("joints", {}).items():
            for name, e in joint.get("reported", {}).items():
                if verdict(e).wrong:
                    what = name if e["as"] == "value" else f"{name} as {e['as']}"
                    lines.append(
                        f"- {r['arm']} {letter}: {what} {e['fitted']:.4g}, "
                        f"true {e['true']:.4g} ({100 * e['error']:+.1f} %)"
                    )
    gaps = [
        g["fitted"]["energy_error_max"]
        for r in rows
        for g in r.get("controller_gap") or []
        if g["controller"] == "pid"
    ]
    if gaps:
        ok = sum(g <= ENERGY_TOLERANCE for g in gaps)
        lines.append(
            f"- PID energy within 5 % of the arm's on {ok} of {len(gaps)} fitted twins "
            f"(worst {100 * max(gaps):.1f} %)"
        )
    return "\n".join(lines)
