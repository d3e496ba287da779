"""Identification campaigns: many hidden virtual arms identified through the driver, on Ray.

`lambda` meets the overshoot target only on an arm it knows (docs/robustness.md, "Eighteenth
round" on), so what it is worth is measured arm by arm: serve the hidden arm, identify it the
way a real arm is identified, give the fit to the controller. One `IdentifyJob` does the first
two on one arm, exactly as a person would on a workstation:

- ``reach-sim --params HIDDEN.json --sensor-noise Q,V --speed S --link LINK`` in a
  subprocess (its own process, so its physics keeps the wall clock while the driver works);
- ``python -m policy.campaigns.identification --port LINK --out FIT.json --truth
  HIDDEN.json`` (what ``tools/identify.py`` runs) in another: the excitation through
  `reach_driver`, then the fit (docs/identification.md). A process of its own so that its
  time budget can be enforced and its output kept for the report.

The job returns the fitted file and the excitation log as bytes, so a Ray cluster's nodes
need no shared disk; `run_on_ray` (`policy.campaigns.parallel`) schedules one job per CPU. An
identification takes 4-5 min of arm time and 6-10 min of fitting on one core.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.fit.identifiability import combination_value
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.twin import FitMetadata, FittedTwin

#: The directory holding the packages (a checkout, or site-packages for an installed wheel).
REPO = Path(__file__).resolve().parents[2]
IDENTIFY_MODULE = "policy.campaigns.identification"
LINK_TIMEOUT_S = 30.0
TAIL_LINES = 30


SIM_FAILED = -2
"""`IdentifyResult.returncode` when reach-sim did not come up (-1: the identification timed
out; otherwise its exit code, tools/identify.py's). A failed arm is reported, not raised, so
one bad arm does not stop a campaign."""


@dataclass(frozen=True)
class IdentifyJob:
    """One hidden arm to identify (small and picklable)."""

    name: str  # the fit's file stem, SET-INDEX
    hidden_json: str  # the arm, a reach-sim --params file's text
    sensor_noise: tuple[float, float]  # rad, rad/s: what the arm's sensors add
    speed: float = 1.0  # reach-sim --speed: 1 keeps host stalls out of the data
    identify_args: tuple[str, ...] = ()  # more tools/identify.py options (--joints, --scale...)
    timeout_s: float = 3600.0  # the identification's wall-clock budget
    #: excite the arm in the identification's own process (`tools/identify.py --virtual`):
    #: no reach-sim, no driver, no link; what the data can tell apart, not what the link does
    virtual: bool = False
    seed: int = 0  # with `virtual`: the sensor noise's seed


@dataclass
class IdentifyResult:
    """What a job brings back: the fit's file and log (bytes), or why there is none."""

    name: str
    returncode: int
    wall_s: float
    fitted_json: str | None = None
    log_npz: bytes | None = None
    tail: list[str] = field(default_factory=list)  # the tool's last lines, bars left out

    @property
    def ok(self) -> bool:
        return self.returncode == 0 and self.fitted_json is not None


def _env() -> dict[str, str]:
    """This checkout first on the subprocesses' path: they run the code the worker checked."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    env["COLUMNS"] = "100"
    return env


def _text(data: str | bytes | None) -> str:
    """A subprocess's output as text (a timeout's comes back as bytes even with text=True)."""
    if data is None:
        return ""
    return data if isinstance(data, str) else data.decode(errors="replace")


def _tail(text: str, n: int = TAIL_LINES) -> list[str]:
    lines = [ln.rstrip() for ln in text.splitlines() if ln.strip() and "━" not in ln]
    return lines[-n:]


def run_identify_job(job: IdentifyJob) -> IdentifyResult:
    """Serve ``job``'s arm on a pty, identify it through the driver, return the fit (or, for
    a `virtual` job, excite and fit it in one process)."""
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="identify-") as tmp:
        root = Path(tmp)
        hidden = root / "hidden.json"
        hidden.write_text(job.hidden_json, encoding="utf-8")
        if job.virtual:
            return _run_virtual(job, root, hidden, t0)
        link = root / "alpha5"
        sim_log = (root / "sim.log").open("w+", encoding="utf-8")
        noise = ",".join(f"{v:.6g}" for v in job.sensor_noise)
        sim = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "reach_sim_bridge.cli",
                "--params",
                str(hidden),
                "--sensor-noise",
                noise,
                "--speed",
                f"{job.speed:g}",
                "--link",
                str(link),
                "--stats-interval",
                "0",
            ],
            stdout=sim_log,
            stderr=subprocess.STDOUT,
            env=_env(),
            cwd=REPO,
        )
        out = root / f"{job.name}.json"
        try:
            deadline = time.monotonic() + LINK_TIMEOUT_S
            while not link.exists() and sim.poll() is None and time.monotonic() < deadline:
                time.sleep(0.1)
            if not link.exists():
                sim_log.seek(0)
                return IdentifyResult(
                    job.name,
                    SIM_FAILED,
                    time.monotonic() - t0,
                    tail=["reach-sim did not serve the arm:", *_tail(sim_log.read())],
                )
            cmd = [
                sys.executable,
                "-m",
                IDENTIFY_MODULE,
                "--port",
                str(link),
                "--out",
                str(out),
                "--truth",
                str(hidden),
                "--no-record",
                "--no-report",
                *job.identify_args,
            ]
            code, text = _run(cmd, job.timeout_s)
        finally:
            sim.terminate()
            try:
                sim.wait(timeout=10)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.wait()
            sim_log.close()
        return _result(job, out, code, text, t0)


def _run_virtual(job: IdentifyJob, root: Path, hidden: Path, t0: float) -> IdentifyResult:
    """`tools/identify.py --virtual` on the job's arm, in a process of its own (its time
    budget enforced, its output kept)."""
    out = root / f"{job.name}.json"
    noise = ",".join(f"{v:.6g}" for v in job.sensor_noise)
    cmd = [
        sys.executable,
        "-m",
        IDENTIFY_MODULE,
        "--virtual",
        str(hidden),
        "--sensor-noise",
        noise,
        "--seed",
        str(job.seed),
        "--out",
        str(out),
        "--truth",
        str(hidden),
        "--no-report",
        *job.identify_args,
    ]
    code, text = _run(cmd, job.timeout_s)
    return _result(job, out, code, text, t0)


def _run(cmd: list[str], timeout_s: float) -> tuple[int, str]:
    """Exit code and output of `cmd` (-1 and what it printed if it ran out of time)."""
    try:
        done = subprocess.run(
            cmd, capture_output=True, text=True, env=_env(), cwd=REPO, timeout=timeout_s
        )
        return done.returncode, done.stdout + done.stderr
    except subprocess.TimeoutExpired as exc:
        text = "".join(_text(x) for x in (exc.stdout, exc.stderr))
        return -1, text + f"\ntimed out after {timeout_s:g} s"


def _result(job: IdentifyJob, out: Path, code: int, text: str, t0: float) -> IdentifyResult:
    log = out.with_suffix(".log.npz")
    return IdentifyResult(
        job.name,
        code,
        time.monotonic() - t0,
        out.read_text(encoding="utf-8") if code == 0 and out.exists() else None,
        log.read_bytes() if log.exists() else None,
        _tail(text),
    )


def _effective(arm: ArmParams, key: str) -> np.ndarray:
    """``arm``'s `key` per joint over its torque scale: what a current-mode identification
    sees."""
    return np.asarray(getattr(arm, key), dtype=float) / np.asarray(arm.torque_scale, float)


def fit_errors(hidden: dict, fitted: dict) -> dict:
    """Per joint, the fit against the hidden arm as the fit can see it: a drive at torque
    scale s turns a current into s times the torque, so from currents the arm looks like one
    with armature, damping and Coulomb friction divided by s (the fit may find a weak drive
    either way: as its scale or as that heavier joint). Ratios of those effective values,
    fitted / true, for the armature and damping, the difference in N m for the Coulomb
    friction, both scales, and the replay's RMS on the validation motions (fitted and
    nominal twin, mrad). `hidden` and `fitted` are parameter files' objects (`FittedTwin`)."""
    truth = ArmParams.from_json_dict(hidden, where="hidden arm")
    twin = FittedTwin.from_json_dict(fitted, where="fitted twin")
    arm = twin.params
    armature = _effective(arm, "armature") / _effective(truth, "armature")
    damping = _effective(arm, "damping") / _effective(truth, "damping")
    coulomb = _effective(arm, "frictionloss") - _effective(truth, "frictionloss")
    fit = twin.fit or FitMetadata()
    out: dict[str, dict] = {}
    for j, letter in enumerate(JOINT_LETTERS):
        row: dict[str, float | None] = {
            "torque_scale": arm.torque_scale[j],
            "true_torque_scale": truth.torque_scale[j],
            "armature_ratio": float(armature[j]),
            "damping_ratio": float(damping[j]),
            "coulomb_error_nm": float(coulomb[j]),
        }
        for which in ("fitted", "nominal"):
            row[f"validate_rms_mrad_{which}"] = fit.window_rms_mrad(f"validate/{letter}", which)
        out[letter] = row
    for letter, reported in reported_errors(truth, twin).items():
        out[letter]["scale_status"] = fit.torque_scales.get(letter, {}).get("status")
        out[letter]["reported"] = reported
        errors = [abs(r["error"]) for r in reported.values() if r["error"] is not None]
        out[letter]["worst_reported_error"] = max(errors) if errors else None
    return out


FRICTION_FLOOR_SHARE = 0.1
"""`reported_errors` gives a Coulomb friction's error relative to at least this share of the
nominal arm's (0.07 N m on E D C, 0.0075 on B): the envelope's arms reach 0 N m."""


def reported_errors(truth: ArmParams, twin: FittedTwin) -> dict[str, dict[str, dict]]:
    """Per joint letter, per parameter the fit reports, what it reported against the truth:
    the value where the fit identified it (`_fit.parameters`, or the twin's own value for a
    torque scale taken as the anchor), the combination it gave where it called the
    parameter unidentifiable (`_fit.unidentifiable`: friction over the torque scale, a net
    weight...). Each: {"as": "value" or the combination, "fitted", "true", "error"} with the
    error relative (see `FRICTION_FLOOR_SHARE`). A file without verdicts (an older fit)
    claimed every value it holds."""
    fit = twin.fit or FitMetadata()
    nominal = ArmParams()
    out: dict[str, dict[str, dict]] = {}
    for j, letter in enumerate(JOINT_LETTERS):
        names = [f"{k}[{letter}]" for k in ("torque_scale", "armature", "damping", "frictionloss")]
        names += [n for n in (*fit.parameters, *fit.unidentifiable) if n.endswith(f"[{letter}]")]
        if fit.torque_scales and letter not in fit.torque_scales:
            continue  # not identified at all
        rows: dict[str, dict] = {}
        for name in dict.fromkeys(names):
            field, _ = name.split("[")
            if name in fit.unidentifiable:
                known = fit.unidentifiable[name].known
                if known is None:
                    rows[name] = {"as": "unidentifiable", "fitted": None, "true": None}
                    rows[name]["error"] = None
                    continue
                combo, got = known.name, known.value
            elif field == "link_mass_kg":
                continue  # an effective mass: only its net weight means anything
            else:
                combo, got = name, float(getattr(twin.params, field)[j])
            true = combination_value(truth, combo)
            floor = 0.0
            if field == "frictionloss":
                floor = FRICTION_FLOOR_SHARE * nominal.frictionloss[j]
                if "/" in combo:
                    floor /= truth.torque_scale[j]
            error = (got - true) / max(abs(true), floor, 1e-12)
            rows[name] = {"as": "value" if combo == name else combo, "fitted": got}
            rows[name].update({"true": true, "error": error})
        out[letter] = rows
    return out


TOLERANCE = 0.10
"""Issue 46's: a parameter reported within 10 % of the arm's, or reported unidentifiable with
the combination the data fix within 10 %."""


class Verdict(Enum):
    """How one parameter of one fit stands against its arm (`verdict`)."""

    VALUE = "value within 10 %"
    COMBINATION = "unidentifiable, combination within 10 %"
    NO_VALUE = "unidentifiable, no value claimed"
    WRONG_VALUE = "WRONG: value off > 10 %"
    WRONG_COMBINATION = "WRONG: combination off > 10 %"

    @property
    def wrong(self) -> bool:
        """Confidently wrong: a value or a combination claimed known, off by more than 10 %."""
        return self in (Verdict.WRONG_VALUE, Verdict.WRONG_COMBINATION)


def verdict(entry: dict) -> Verdict:
    """One `reported_errors` entry against `TOLERANCE`. A torque scale reported unidentifiable
    claims no value (what the data fix of it are the joint's other combinations)."""
    if entry["error"] is None:
        return Verdict.NO_VALUE
    within = abs(entry["error"]) <= TOLERANCE
    if entry["as"] == "value":
        return Verdict.VALUE if within else Verdict.WRONG_VALUE
    return Verdict.COMBINATION if within else Verdict.WRONG_COMBINATION


def verdict_counts(rows: Iterable[dict]) -> dict[str, Counter[Verdict]]:
    """Per parameter (the `ArmParams` field: torque_scale, armature, damping, frictionloss,
    link_mass_kg for a load), how many of the fits in `rows` (`fit_row`s) stand how."""
    out: dict[str, Counter[Verdict]] = {}
    for row in rows:
        for joint in row.get("joints", {}).values():
            for name, entry in joint.get("reported", {}).items():
                out.setdefault(name.split("[")[0], Counter())[verdict(entry)] += 1
    return out


def run_row(result: IdentifyResult) -> dict:
    """How one job ran (JSON-ready): its exit code, wall time and, if it failed, its tail."""
    row: dict = {"arm": result.name, "returncode": result.returncode, "wall_s": result.wall_s}
    if not result.ok:
        row["tail"] = result.tail
    return row


def fit_row(name: str, hidden: dict, fitted: dict, run: dict | None = None) -> dict:
    """One arm's line in the campaign's table: the fit against its hidden arm (`fit_errors`),
    its fit and arm time, and how the job ran when that is known."""
    fit = FittedTwin.from_json_dict(fitted, where=f"{name}: fitted twin").fit
    row: dict = {"arm": name, **(run or {})}
    row["fit_s"] = None if fit is None else fit.fit_seconds
    row["arm_s"] = None if fit is None else fit.arm_seconds
    row["joints"] = fit_errors(hidden, fitted)
    row["controller_gap"] = None if fit is None else fit.controller_gap
    return row
