"""System identification of the Alpha 5 twin by simulation (docs/identification.md).

The data are current-mode motions of one joint at a time (`Segment`: the states a control loop
saw on its tick grid and the currents it held over each period, as `reach_driver`'s
`LoopTrace` gives them). The twin is `Alpha5Arm`, the model the controllers use. A
parameter set is scored by replaying the logged commands open loop through MuJoCo:

- multiple shooting: each segment is cut into windows of `window_s`; each window starts
  from the measured state, so a rollout cannot drift further than one window;
- the joints not being excited are held on their measured path (their position and
  velocity are set to the logged values at every tick), so one joint's fit does not
  depend on the others' parameters beyond what the pose makes them load it with;
- the link's transport delay `delay_s` shifts every command: command row i (held over
  (t[i-1], t[i]] by the host) acts over (t[i-1] + delay, t[i] + delay]; a fraction of a
  physics step is blended so the residual is continuous in the delay.

`fit_joint` runs Levenberg-Marquardt with forward-difference Jacobians over log-parameters
(armature, viscous damping, Coulomb friction of the joint, optionally a link mass: the net
gravity-buoyancy load) and the delay, and gives each an uncertainty from the Jacobian at
the optimum, sqrt(diag(sigma^2 (J^T J)^-1)). Numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocol.alpha5 import JOINT_LETTERS, N_JOINTS
from reach_sim_bridge.arm import Alpha5Arm
from reach_sim_bridge.params import ArmParams

FloatArray = NDArray[np.float64]

DELAY = "delay_s"
"""The name of the transport-delay parameter (not an `ArmParams` field)."""

MAX_DELAY_S = 0.1
DEFAULT_WINDOW_S = 1.0
VELOCITY_WEIGHT_S = 0.02
"""Velocity residuals (rad/s) are weighted by this (s) next to position residuals (rad)."""
SKIP_TICKS = 3
"""Ticks at the start of a segment not used: the joints leave position mode there."""

#: A parameter: (ArmParams field, joint index) or (DELAY, -1).
ParamRef = tuple[str, int]


@dataclass(frozen=True)
class Segment:
    """One logged excitation: the loop's tick grid, one row per tick.

    ``command_mA[i]`` is the current the host held over the period ending at sample i (row 0
    is before the first command), as `reach_driver.records.LoopTrace.command_mA`."""

    name: str
    joint: int  # index in E D C B of the joint being excited
    role: str  # "fit" or "validate"
    period: float  # s between ticks
    q: FloatArray  # (n + 1, 4) rad
    qdot: FloatArray  # (n + 1, 4) rad/s
    command_mA: FloatArray  # (n + 1, 4)
    current_mA: FloatArray | None = None  # measured, NaN where not reported
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("q", "qdot", "command_mA"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.ndim != 2 or arr.shape[1] != N_JOINTS or arr.shape[0] < 2:
                raise ValueError(f"segment {self.name}: {name} must be (n+1, 4), got {arr.shape}")
            object.__setattr__(self, name, arr)
        if not self.q.shape == self.qdot.shape == self.command_mA.shape:
            raise ValueError(f"segment {self.name}: q, qdot and command_mA differ in length")
        if not 0 <= self.joint < N_JOINTS:
            raise ValueError(f"segment {self.name}: joint index {self.joint} not in 0..3")
        if self.role not in ("fit", "validate"):
            raise ValueError(f"segment {self.name}: role must be fit or validate")

    @property
    def ticks(self) -> int:
        return int(self.q.shape[0] - 1)

    @property
    def seconds(self) -> float:
        return self.ticks * self.period


@dataclass(frozen=True)
class Rollout:
    """The twin's prediction of a segment: NaN where no prediction (window starts)."""

    q: FloatArray
    qdot: FloatArray


def params_with(base: ArmParams, refs: Sequence[ParamRef], values: Sequence[float]) -> ArmParams:
    """`base` with the `ArmParams` entries named by `refs` set (the delay is skipped)."""
    changes: dict[str, list[float]] = {}
    for (name, index), value in zip(refs, values, strict=True):
        if name == DELAY:
            continue
        vec = changes.setdefault(name, list(getattr(base, name)))
        vec[index] = float(value)
    fields: dict[str, Any] = {k: tuple(v) for k, v in changes.items()}
    return replace(base, **fields)


def param_value(params: ArmParams, delay_s: float, ref: ParamRef) -> float:
    name, index = ref
    return float(delay_s) if name == DELAY else float(getattr(params, name)[index])


def ref_name(ref: ParamRef) -> str:
    name, index = ref
    return name if name == DELAY else f"{name}[{JOINT_LETTERS[index]}]"


class Replay:
    """Replays logged segments on one `Alpha5Arm` (reused across parameter sets)."""

    def __init__(
        self,
        base: ArmParams | None = None,
        dt: float = 0.002,
        window_s: float = DEFAULT_WINDOW_S,
        teacher_force: bool = True,
    ) -> None:
        self.arm = Alpha5Arm(params=base, dt=dt)
        self.window_s = window_s
        self.teacher_force = teacher_force
        self.rollouts = 0

    def simulate(
        self, params: ArmParams, delay_s: float, seg: Segment, window_s: float | None = None
    ) -> Rollout:
        """The twin `params` driven by the segment's commands (see the module docstring).
        ``window_s`` <= 0 or inf: one window from the first usable tick to the end."""
        arm = self.arm
        arm.set_params(params)
        self.rollouts += 1
        period, dt = seg.period, arm.dt
        substeps = int(round(period / dt))
        if abs(substeps * dt - period) > 1e-9 or substeps < 1:
            raise ValueError(f"segment period {period} s is not a whole number of {dt} s steps")
        window = self.window_s if window_s is None else window_s
        w_ticks = (
            seg.ticks
            if not (window > 0 and math.isfinite(window))
            else max(1, int(round(window / period)))
        )
        delay = min(max(float(delay_s), 0.0), MAX_DELAY_S)
        whole = int(math.floor(delay / period + 1e-12))
        rem_steps = (delay - whole * period) / dt
        a = min(int(math.floor(rem_steps)), substeps - 1)
        frac = min(max(rem_steps - a, 0.0), 1.0)
        cmd = seg.command_mA
        n = seg.ticks
        q_out = np.full_like(seg.q, np.nan)
        qd_out = np.full_like(seg.qdot, np.nan)
        others = [i for i in range(N_JOINTS) if i != seg.joint]
        data = arm.data
        # Windows start at the same ticks whatever the delay, so every candidate delay is
        # scored on the same samples (the residual keeps its length while the fit moves it).
        first = SKIP_TICKS + int(math.ceil(MAX_DELAY_S / period - 1e-12))
        for s in range(first, n, w_ticks):
            end = min(s + w_ticks, n)
            arm.reset(q=seg.q[s], qdot=seg.qdot[s])
            for k in range(s, end):
                if self.teacher_force and k > s:
                    for i in others:
                        data.qpos[i] = seg.q[k, i]
                        data.qvel[i] = seg.qdot[k, i]
                old = cmd[max(k - whole, 1)]
                new = cmd[min(k + 1 - whole, n)]
                rest = substeps
                if a > 0:
                    arm.step(old, n=a)
                    rest -= a
                if frac > 1e-9:
                    arm.step(frac * old + (1.0 - frac) * new, n=1)
                    rest -= 1
                if rest > 0:
                    arm.step(new, n=rest)
                q_out[k + 1] = arm.q
                qd_out[k + 1] = arm.qdot
        return Rollout(q_out, qd_out)

    def residuals(
        self,
        params: ArmParams,
        delay_s: float,
        segments: Sequence[Segment],
        velocity_weight: float = VELOCITY_WEIGHT_S,
        window_s: float | None = None,
    ) -> FloatArray:
        """Position (rad) and weighted velocity residuals of each segment's excited joint."""
        parts = []
        for seg in segments:
            r = self.simulate(params, delay_s, seg, window_s)
            j = seg.joint
            ok = np.isfinite(r.q[:, j])
            parts.append(r.q[ok, j] - seg.q[ok, j])
            if velocity_weight > 0:
                parts.append(velocity_weight * (r.qdot[ok, j] - seg.qdot[ok, j]))
        return np.concatenate(parts) if parts else np.zeros(0)


@dataclass(frozen=True)
class Quality:
    """How well a twin predicts segments: the excited joint's angle."""

    r2: float
    rms_rad: float
    r2_velocity: float
    rms_velocity: float
    samples: int

    def as_dict(self) -> dict[str, float]:
        return {
            "r2": self.r2,
            "rms_mrad": self.rms_rad * 1e3,
            "r2_velocity": self.r2_velocity,
            "rms_velocity_rad_s": self.rms_velocity,
            "samples": self.samples,
        }


def quality(
    replay: Replay,
    params: ArmParams,
    delay_s: float,
    segments: Sequence[Segment],
    window_s: float | None = None,
) -> Quality:
    """R^2 and RMS of the excited joint's predicted angle and speed over `segments` (R^2
    against each segment's own mean)."""
    res_q, tot_q, res_v, tot_v = [], [], [], []
    for seg in segments:
        r = replay.simulate(params, delay_s, seg, window_s)
        j = seg.joint
        ok = np.isfinite(r.q[:, j])
        meas_q, meas_v = seg.q[ok, j], seg.qdot[ok, j]
        res_q.append(r.q[ok, j] - meas_q)
        tot_q.append(meas_q - meas_q.mean())
        res_v.append(r.qdot[ok, j] - meas_v)
        tot_v.append(meas_v - meas_v.mean())
    rq, tq = np.concatenate(res_q), np.concatenate(tot_q)
    rv, tv = np.concatenate(res_v), np.concatenate(tot_v)
    return Quality(
        r2=float(1.0 - rq @ rq / max(tq @ tq, 1e-30)),
        rms_rad=float(np.sqrt(np.mean(rq**2))),
        r2_velocity=float(1.0 - rv @ rv / max(tv @ tv, 1e-30)),
        rms_velocity=float(np.sqrt(np.mean(rv**2))),
        samples=int(rq.size),
    )


@dataclass(frozen=True)
class FitResult:
    """One joint's fit: values, 1-sigma uncertainties, and the cost history."""

    joint: int
    refs: tuple[ParamRef, ...]
    values: tuple[float, ...]
    sigma: tuple[float, ...]
    params: ArmParams
    delay_s: float
    rms_residual: float
    iterations: int
    rollouts: int
    costs: tuple[float, ...]

    def table(self) -> dict[str, dict[str, float]]:
        return {
            ref_name(r): {"value": v, "sigma": s}
            for r, v, s in zip(self.refs, self.values, self.sigma, strict=True)
        }


def default_refs(joint: int, fit_delay: bool = True) -> list[ParamRef]:
    """What a current-controlled joint reveals (docs/identification.md): its armature,
    viscous and Coulomb friction, the net gravity-buoyancy load where there is one (D: the
    link D moves, C: the wrist link, which is most of C's load), and the link's delay."""
    refs: list[ParamRef] = [("armature", joint), ("damping", joint), ("frictionloss", joint)]
    letter = JOINT_LETTERS[joint]
    if letter == "D":
        refs.append(("link_mass_kg", joint))
    elif letter == "C":
        refs.append(("link_mass_kg", JOINT_LETTERS.index("B")))
    if fit_delay:
        refs.append((DELAY, -1))
    return refs


FRICTION_FLOOR = 1e-4  # N m: log-parameters need a positive start


def fit_joint(
    replay: Replay,
    segments: Sequence[Segment],
    start: ArmParams,
    delay_s: float,
    refs: Sequence[ParamRef],
    max_iter: int = 12,
    tol: float = 1e-4,
    velocity_weight: float = VELOCITY_WEIGHT_S,
    on_iteration: Callable[[int, float], None] | None = None,
) -> FitResult:
    """Levenberg-Marquardt over `refs` (log of each physical value; the delay in seconds)
    on the residuals of `segments`, starting from `start` and `delay_s`."""
    refs = tuple(refs)
    if not segments:
        raise ValueError("no segments to fit")
    joint = segments[0].joint
    is_log = np.array([r[0] != DELAY for r in refs])
    x0 = np.array(
        [
            math.log(max(param_value(start, delay_s, r), FRICTION_FLOOR))
            if lg
            else param_value(start, delay_s, r)
            for r, lg in zip(refs, is_log, strict=True)
        ]
    )
    lower = np.where(is_log, math.log(FRICTION_FLOOR), 0.0)
    upper = np.where(is_log, math.log(1e3), MAX_DELAY_S)
    step = np.where(is_log, 0.01, 0.0005)
    rollouts0 = replay.rollouts

    def unpack(x: FloatArray) -> tuple[ArmParams, float]:
        physical = np.where(is_log, np.exp(x), x)
        delay = delay_s
        for r, v in zip(refs, physical, strict=True):
            if r[0] == DELAY:
                delay = float(v)
        return params_with(start, refs, physical.tolist()), delay

    def fun(x: FloatArray) -> FloatArray:
        p, d = unpack(x)
        return replay.residuals(p, d, segments, velocity_weight)

    def jacobian(x: FloatArray, r0: FloatArray) -> FloatArray:
        cols = []
        for i in range(x.size):
            h = step[i] if x[i] + step[i] <= upper[i] else -step[i]
            xp = x.copy()
            xp[i] += h
            cols.append((fun(xp) - r0) / h)
        return np.column_stack(cols)

    x = np.clip(x0, lower, upper)
    r = fun(x)
    cost = float(r @ r)
    costs = [cost]
    lam = 1e-3
    it = 0
    jac = jacobian(x, r)
    for it in range(1, max_iter + 1):
        g = jac.T @ r
        h = jac.T @ jac
        diag = np.maximum(np.diag(h), 1e-12)
        improved = False
        for _ in range(8):
            try:
                dx = np.linalg.solve(h + lam * np.diag(diag), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            x_new = np.clip(x + dx, lower, upper)
            r_new = fun(x_new)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                improved = True
                gain = (cost - cost_new) / max(cost, 1e-30)
                x, r, cost = x_new, r_new, cost_new
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 4.0
        costs.append(cost)
        if on_iteration is not None:
            on_iteration(it, cost)
        if not improved or gain < tol:
            break
        jac = jacobian(x, r)
    # Uncertainty at the optimum (the last Jacobian is at x unless the step was refused).
    jac = jacobian(x, r)
    dof = max(r.size - x.size, 1)
    sigma2 = cost / dof
    try:
        cov = sigma2 * np.linalg.inv(jac.T @ jac)
        std_x = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        std_x = np.full(x.size, np.inf)
    physical = np.where(is_log, np.exp(x), x)
    std = np.where(is_log, physical * std_x, std_x)
    params, delay = unpack(x)
    return FitResult(
        joint=joint,
        refs=refs,
        values=tuple(float(v) for v in physical),
        sigma=tuple(float(s) for s in std),
        params=params,
        delay_s=delay,
        rms_residual=math.sqrt(cost / max(r.size, 1)),
        iterations=it,
        rollouts=replay.rollouts - rollouts0,
        costs=tuple(costs),
    )


JOINT_ORDER = ("E", "B", "C", "D")
"""Fitting order: E and B carry no gravity load; C's load (the wrist link) is fitted before
D, whose load includes it."""


def fit_arm(
    replay: Replay,
    segments: Sequence[Segment],
    start: ArmParams | None = None,
    delay_s: float = 0.0,
    fit_delay: bool = True,
    max_iter: int = 12,
    on_joint: Callable[[int, FitResult], None] | None = None,
    on_iteration: Callable[[int, int, float], None] | None = None,
) -> tuple[ArmParams, float, dict[int, FitResult]]:
    """Fit every joint that has "fit" segments, in `JOINT_ORDER`, each from the arm found so
    far; the delay found by one joint starts the next. Returns the arm, the delay (the
    median of the joints' delay estimates) and each joint's result."""
    params = start if start is not None else ArmParams()
    delay = delay_s
    results: dict[int, FitResult] = {}
    delays: list[float] = []
    for letter in JOINT_ORDER:
        j = JOINT_LETTERS.index(letter)
        segs = [s for s in segments if s.joint == j and s.role == "fit"]
        if not segs:
            continue

        def note(it: int, cost: float, j: int = j) -> None:
            if on_iteration is not None:
                on_iteration(j, it, cost)

        result = fit_joint(
            replay,
            segs,
            params,
            delay,
            default_refs(j, fit_delay),
            max_iter=max_iter,
            on_iteration=note,
        )
        params = result.params
        if fit_delay:
            delays.append(result.delay_s)
            delay = result.delay_s
        results[j] = result
        if on_joint is not None:
            on_joint(j, result)
    if delays:
        delay = float(np.median(delays))
    return params, delay, results


def load_segments(path: Any) -> list[Segment]:
    """Segments from an `.npz` log written by `save_segments` (tools/identify.py)."""
    import json

    with np.load(path, allow_pickle=False) as data:
        index = json.loads(str(data["index"]))
        out = []
        for i, meta in enumerate(index):
            cur = data[f"s{i}_current_mA"] if f"s{i}_current_mA" in data else None
            out.append(
                Segment(
                    name=meta["name"],
                    joint=int(meta["joint"]),
                    role=meta["role"],
                    period=float(meta["period"]),
                    q=data[f"s{i}_q"],
                    qdot=data[f"s{i}_qdot"],
                    command_mA=data[f"s{i}_command_mA"],
                    current_mA=cur,
                    meta=dict(meta.get("meta", {})),
                )
            )
    return out


def save_segments(segments: Sequence[Segment], path: Any, header: dict[str, Any]) -> None:
    """One `.npz`: per segment q, qdot, command_mA, current_mA, and a JSON index (name,
    joint, role, period, meta) plus `header` (how the log was made)."""
    import json

    arrays: dict[str, Any] = {}
    index = []
    for i, seg in enumerate(segments):
        arrays[f"s{i}_q"] = seg.q
        arrays[f"s{i}_qdot"] = seg.qdot
        arrays[f"s{i}_command_mA"] = seg.command_mA
        if seg.current_mA is not None:
            arrays[f"s{i}_current_mA"] = np.asarray(seg.current_mA, dtype=float)
        index.append(
            {
                "name": seg.name,
                "joint": seg.joint,
                "role": seg.role,
                "period": seg.period,
                "meta": seg.meta,
            }
        )
    np.savez_compressed(
        path, index=np.array(json.dumps(index)), header=np.array(json.dumps(header)), **arrays
    )
