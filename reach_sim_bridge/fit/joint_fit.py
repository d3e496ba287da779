"""One joint's fit: Levenberg-Marquardt over log-parameters (`fit_joint`), started from the
best point of a coarse grid and drive scales (`coarse_start`), its friction capped by what
the drive could break (`friction_ceiling`)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.fit.replay import (
    DELAY,
    VELOCITY_WEIGHT_S,
    ParamRef,
    Replay,
    param_value,
    params_with,
    ref_name,
)
from reach_sim_bridge.fit.segments import MAX_DELAY_S, FloatArray, Segment
from reach_sim_bridge.model.params import ArmParams


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
    segments: tuple[Segment, ...] = ()  # as fitted: with their window starts when fitted

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
MAX_LOG_STEP = 1.0
"""`fit_joint` moves no log-parameter by more than this per step (a factor of e): a full
Gauss-Newton step from a start far off (the nominal 0.7 N m of friction on a frictionless
joint, under 3x sensor noise) once threw a joint's damping to the floor, where its gradient
vanishes and the fit cannot come back (docs/identification.md, "Arms of the envelope")."""


MOVED_RAD = 0.05
"""`friction_ceiling`: a joint whose angle spanned this much in its segments was seen moving."""


def friction_ceiling(replay: Replay, params: ArmParams, segments: Sequence[Segment]) -> float:
    """The most Coulomb friction (N m) the segments allow their joint: seen moving, it was
    driven past its friction, so the friction is under the largest torque that could have
    done it (the drive's at the largest current held, at `params`' torque scale, plus the
    gravity-buoyancy load at the poses held). inf for a joint not seen moving. Why: MuJoCo's
    friction constraint is soft, and friction the drive can never break acts as damping; a
    weak B at 3x noise was fitted as 2.25 N m of friction (its drive gave at most 0.86) beside
    a sixth of its armature, and a controller fed that friction forward chattered."""
    j = segments[0].joint
    if max(float(np.ptp(s.q[:, j])) for s in segments) < MOVED_RAD:
        return math.inf
    arm = replay.arm
    arm.set_params(params)
    peak_mA = max(float(np.max(np.abs(s.command_mA[:, j]))) for s in segments)
    drive = params.torque_scale[j] * float(arm.motor.torque_per_amp[j]) * peak_mA / 1000.0
    load = max(
        abs(float(arm.gravity_torque(q)[j]))
        for s in segments
        for q in s.q[:: max(1, len(s.q) // 50)]
    )
    return drive + load


START_STEP = (1e-3, 1e-2)
"""`fit_joint`'s difference steps in a window's start angle (rad) and speed (rad/s)."""


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
    weights: FloatArray | None = None,
    fit_starts: bool = False,
) -> FitResult:
    """Levenberg-Marquardt over `refs` (log of each physical value; the delay in seconds)
    on the residuals of `segments`, starting from `start` and `delay_s`.

    With `fit_starts`, each window's starting angle and speed of the excited joint are fitted
    too (`Segment.start_fix`, from the segments' own or zero). Why: a window started from a
    noisy reading carries the reading's error, and a lighter twin forgets it sooner; at 3x
    sensor noise that biased D's and C's armature 13-19 % low (docs/identification.md). The
    starts are separable (each moves its own window only), so their Jacobian costs two
    rollouts whatever their number. Off by default: beside an arm still far from the data
    the starts soak up its errors, so `fit_arm` fits them only in its polish."""
    refs = tuple(refs)
    if not segments:
        raise ValueError("no segments to fit")
    joint = segments[0].joint
    segs = replay.with_starts(segments) if fit_starts else list(segments)
    counts = [0 if s.start_fix is None else s.start_fix.shape[0] for s in segs]
    n_fix = sum(counts) if fit_starts else 0
    n_par = len(refs)
    is_log = np.concatenate([[r[0] != DELAY for r in refs], np.zeros(2 * n_fix, dtype=bool)])
    x0 = np.array(
        [
            math.log(max(param_value(start, delay_s, r), FRICTION_FLOOR))
            if r[0] != DELAY
            else param_value(start, delay_s, r)
            for r in refs
        ]
    )
    if n_fix:
        fixes = [s.start_fix for s in segs if s.start_fix is not None]
        x0 = np.concatenate([x0, *[f[:, 0] for f in fixes], *[f[:, 1] for f in fixes]])
    lower = np.concatenate(
        [np.where(is_log[:n_par], math.log(FRICTION_FLOOR), 0.0), np.full(2 * n_fix, -np.inf)]
    )
    ceiling = friction_ceiling(replay, start, segs)

    def top(ref: ParamRef) -> float:
        if ref[0] == DELAY:
            return MAX_DELAY_S
        if ref[0] == "torque_scale":
            return 0.0  # a drive delivers at most its full torque
        if ref == ("frictionloss", joint) and math.isfinite(ceiling):
            return math.log(max(ceiling, 10 * FRICTION_FLOOR))
        return math.log(1e3)

    upper = np.concatenate([[top(r) for r in refs], np.full(2 * n_fix, np.inf)])
    step = np.where(is_log[:n_par], 0.01, 0.0005)
    rollouts0 = replay.rollouts
    row_window = replay.residual_windows(segs, velocity_weight) if n_fix else None

    def unpack(x: FloatArray) -> tuple[ArmParams, float]:
        physical = np.where(is_log[:n_par], np.exp(x[:n_par]), x[:n_par])
        delay = delay_s
        for r, v in zip(refs, physical, strict=True):
            if r[0] == DELAY:
                delay = float(v)
        return params_with(start, refs, physical.tolist()), delay

    def starts_at(x: FloatArray) -> list[Segment]:
        if not n_fix:
            return segs
        out, i = [], n_par
        for s, c in zip(segs, counts, strict=True):
            fix = np.column_stack([x[i : i + c], x[n_fix + i : n_fix + i + c]])
            out.append(replace(s, start_fix=fix))
            i += c
        return out

    def fun(x: FloatArray) -> FloatArray:
        p, d = unpack(x)
        r = replay.residuals(p, d, starts_at(x), velocity_weight)
        return r if weights is None else r * weights

    def jacobian(x: FloatArray, r0: FloatArray) -> FloatArray:
        cols = []
        for i in range(n_par):
            h = step[i] if x[i] + step[i] <= upper[i] else -step[i]
            xp = x.copy()
            xp[i] += h
            cols.append((fun(xp) - r0) / h)
        jac = np.column_stack(cols)
        if not n_fix or row_window is None:
            return jac
        # every window's start at once: window w's rows answer its own start only
        starts = np.zeros((r0.size, 2 * n_fix))
        for block, h in enumerate(START_STEP):
            xp = x.copy()
            xp[n_par + block * n_fix : n_par + (block + 1) * n_fix] += h
            starts[np.arange(r0.size), block * n_fix + row_window] = (fun(xp) - r0) / h
        return np.hstack([jac, starts])

    x = np.clip(x0, lower, upper)
    r = fun(x)
    if row_window is not None and row_window.size != r.size:
        raise RuntimeError(f"{r.size} residuals for {row_window.size} window rows")
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
            # each on its own: scaling the whole step would let a parameter the data barely
            # see (friction near zero) shrink the step of the ones they do
            dx = np.where(is_log, np.clip(dx, -MAX_LOG_STEP, MAX_LOG_STEP), dx)
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
    physical = np.where(is_log, np.exp(x), x)[:n_par]
    std = np.where(is_log, np.exp(x) * std_x, std_x)[:n_par]
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
        segments=tuple(starts_at(x)),
    )


#: `coarse_start`'s grid, as multiples of the nominal arm's value of each parameter. Coulomb
#: friction spans the envelope's 0 - 6.6 N m for E D C (the model's 0.7 x 0 ... 10: the
#: sources disagree tenfold), the rest its +-50 % (armature, damping) and the net load's
#: +-20 % of mass and buoyancy (an effective link mass 0.7 - 1.3 x nominal for D).
COARSE_GRID: dict[str, tuple[float, ...]] = {
    "armature": (0.5, 1.0, 2.0),
    "damping": (0.5, 1.0, 2.0),
    "frictionloss": (0.0, 0.15, 1.0, 3.0, 10.0),
    "link_mass_kg": (0.7, 1.0, 1.3),
}
DRIVE_SCALES: tuple[float, ...] = (1.0, 0.25)
"""`coarse_start` tries the grid at each of these torque scales of the joint's drive (the
envelope's weak joint runs at 25 %): a weak D, whose drive fights its own load, was fitted
from full torque as 12.6 N m of Coulomb friction (validation R^2 0.71). The scale found is
kept through the fit (beside the load it is a trade the data hardly see) unless the fit has
it among its own parameters (a weak C's refit)."""
DRIVE_MARGIN = 0.5
"""... and a weaker drive than the first must fit with at most this share of its squared
residual: for a joint without a load a weak drive and a heavier joint move alike, and a
healthy E once came out at a quarter torque by a 0.80 ratio (weak joints measured 0.10-0.45,
a weak B 0.76)."""


def coarse_start(
    replay: Replay,
    segments: Sequence[Segment],
    base: ArmParams,
    refs: Sequence[ParamRef],
    velocity_weight: float = VELOCITY_WEIGHT_S,
) -> ArmParams:
    """`base`, or `base` with `refs` (and the joint's torque scale, `DRIVE_SCALES`) set to the
    best point of `COARSE_GRID` (around the nominal arm's values) if one fits the segments
    better: where Levenberg-Marquardt starts.
    From the nominal arm alone a frictionless joint under 3x sensor noise was fitted at 7x
    its damping (and once at 20x its armature): the residual far from the arm is no guide."""
    nominal = ArmParams()
    joint = segments[0].joint
    axes: list[list[tuple[ParamRef, float]]] = []
    if ("torque_scale", joint) not in refs:
        axes.append([(("torque_scale", joint), s) for s in DRIVE_SCALES])
    for name, j in refs:
        if name not in COARSE_GRID:  # the delay, a torque scale: kept as in `base`
            continue
        ref_value = getattr(nominal, name)[j]
        axes.append([((name, j), max(f * ref_value, FRICTION_FLOOR)) for f in COARSE_GRID[name]])

    def cost(p: ArmParams) -> float:
        res = replay.residuals(p, 0.0, segments, velocity_weight)
        return float(res @ res)

    by_scale: dict[float, tuple[float, ArmParams]] = {}
    for point in itertools.product(*axes):
        trial = params_with(base, [ref for ref, _ in point], [v for _, v in point])
        c, scale = cost(trial), trial.torque_scale[joint]
        if scale not in by_scale or c < by_scale[scale][0]:
            by_scale[scale] = (c, trial)
    best_cost, best = cost(base), base  # unless a grid point does better
    for scale in sorted(by_scale, reverse=True):  # the strongest drive first
        c, trial = by_scale[scale]
        margin = DRIVE_MARGIN if scale < best.torque_scale[joint] else 1.0
        if c < margin * best_cost:
            best_cost, best = c, trial
    return best
