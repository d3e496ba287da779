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
from reach_sim_bridge.fit.identifiability import Fisher, correlation_time, marginal_information
from reach_sim_bridge.fit.replay import (
    DELAY,
    VELOCITY_WEIGHT_S,
    ParamRef,
    Replay,
    param_value,
    params_with,
    ref_name,
    with_payload,
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
    #: what the data say about `refs` and the probed parameters at the optimum
    fisher: Fisher | None = None
    #: the residuals' correlation time (rows) the uncertainties were inflated by
    correlation_rows: float = 1.0

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


LOAD = "link_mass_kg"
"""The `ArmParams` field of a fitted gravity-buoyancy load (an effective link mass)."""
SCALED = ("armature", "damping", "frictionloss")
"""A joint's parameters that, with its loads, move it as its torque scale does: multiplied
together by one factor they change none of its motions
(`reach_sim_bridge.fit.identifiability`)."""


def buoyant_kg(params: ArmParams, link: int) -> float:
    """The mass of water link `link` (E D C B index) displaces."""
    return params.link_volume_l[link] * 1e-3 * params.water_density


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
    peak_mA = max(float(np.max(np.abs(s.command_mA[:, j]))) for s in segments)
    load = 0.0
    for s in segments:  # each with the load it held
        arm.set_params(with_payload(params, s))
        for q in s.q[:: max(1, len(s.q) // 50)]:
            load = max(load, abs(float(arm.gravity_torque(q)[j])))
    drive = params.torque_scale[j] * float(arm.motor.torque_per_amp[j]) * peak_mA / 1000.0
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
    probe: Sequence[ParamRef] = (),
) -> FitResult:
    """Levenberg-Marquardt over `refs` (log of each physical value; the delay in seconds)
    on the residuals of `segments`, starting from `start` and `delay_s`.

    With `fit_starts`, each window's starting angle and speed of the excited joint are fitted
    too (`Segment.start_fix`, from the segments' own or zero). Why: a window started from a
    noisy reading carries the reading's error, and a lighter twin forgets it sooner; at 3x
    sensor noise that biased D's and C's armature 13-19 % low (docs/identification.md). The
    starts are separable (each moves its own window only), so their Jacobian costs two
    rollouts whatever their number. Off by default: beside an arm still far from the data
    the starts soak up its errors, so `fit_arm` fits them only in its polish.

    With the joint's torque scale among `refs`, its other parameters are fitted over the
    scale (armature / s, damping / s, friction / s, a load's net weight / s): the coordinates
    the data fix one by one, the scale being the one left
    (`reach_sim_bridge.fit.identifiability`). In the physical ones the data's valley runs
    along all of them at once, and Levenberg-Marquardt crawled along it (a D at 70 % torque
    stopped at 81 % on a noise-free log).

    `probe`: parameters not fitted (held as in `start`) whose information the result's
    `fisher` holds beside the fitted ones' (a joint's torque scale: what would the data say
    if it were free)."""
    refs = tuple(refs)
    if not segments:
        raise ValueError("no segments to fit")
    joint = segments[0].joint
    segs = replay.with_starts(segments) if fit_starts else list(segments)
    counts = [0 if s.start_fix is None else s.start_fix.shape[0] for s in segs]
    n_fix = sum(counts) if fit_starts else 0
    n_par = len(refs)
    is_log = np.concatenate([[r[0] != DELAY for r in refs], np.zeros(2 * n_fix, dtype=bool)])
    scale_ref: ParamRef = ("torque_scale", joint)
    si = refs.index(scale_ref) if scale_ref in refs else -1
    # per ref: fitted over the scale (`over`), and the part of it that does not scale
    # (`fixed`: the water a load displaces)
    over = np.array(
        [
            si >= 0 and i != si and (r[0] == LOAD or (r[1] == joint and r[0] in SCALED))
            for i, r in enumerate(refs)
        ],
        dtype=bool,
    )
    fixed = np.array(
        [buoyant_kg(start, r[1]) if r[0] == LOAD and over[i] else 0.0 for i, r in enumerate(refs)]
    )
    s0 = start.torque_scale[joint]

    def coordinate(i: int, ref: ParamRef) -> float:
        value = param_value(start, delay_s, ref)
        if ref[0] == DELAY:
            return value
        if over[i]:
            value = (value - fixed[i]) / s0
        return math.log(max(value, FRICTION_FLOOR))

    x0 = np.array([coordinate(i, r) for i, r in enumerate(refs)])
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
            # over the scale: what the drive could break at full torque (as `start` has it)
            c = ceiling / s0 if si >= 0 else ceiling
            return math.log(max(c, 10 * FRICTION_FLOOR))
        return math.log(1e3)

    upper = np.concatenate([[top(r) for r in refs], np.full(2 * n_fix, np.inf)])
    step = np.where(is_log[:n_par], 0.01, 0.0005)
    rollouts0 = replay.rollouts
    row_window = replay.residual_windows(segs, velocity_weight) if n_fix else None

    def physical_of(x: FloatArray) -> FloatArray:
        out = np.where(is_log[:n_par], np.exp(x[:n_par]), x[:n_par])
        if si >= 0:
            out = np.where(over, fixed + out * out[si], out)
        return out

    def unpack(x: FloatArray) -> tuple[ArmParams, float]:
        physical = physical_of(x)
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

    def residual_parts(x: FloatArray) -> list[FloatArray]:
        """Each segment's `residuals` at `x`, unweighted (together: `residuals` of all)."""
        p, d = unpack(x)
        return [replay.residuals(p, d, [s], velocity_weight) for s in starts_at(x)]

    def weighed(parts: list[FloatArray]) -> FloatArray:
        r = np.concatenate(parts)
        return r if weights is None else r * weights

    def fun(x: FloatArray) -> FloatArray:
        return weighed(residual_parts(x))

    # the last `own_starts` (x's bytes, result): `fisher_at` asks again at the optimum, where
    # the last Jacobian did
    own_memo: list[tuple[bytes, FloatArray]] = []

    def own_starts(x: FloatArray, r0: FloatArray) -> FloatArray:
        """Per residual row, its derivative by its own window's start angle and speed (every
        window's start moved at once: window w's rows answer its own start only)."""
        if own_memo and own_memo[0][0] == x.tobytes():
            return own_memo[0][1]
        out = np.empty((r0.size, 2))
        for block, h in enumerate(START_STEP):
            xp = x.copy()
            xp[n_par + block * n_fix : n_par + (block + 1) * n_fix] += h
            out[:, block] = (fun(xp) - r0) / h
        own_memo[:] = [(x.tobytes(), out)]
        return out

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
        starts = np.zeros((r0.size, 2 * n_fix))
        own = own_starts(x, r0)
        for block in range(2):
            starts[np.arange(r0.size), block * n_fix + row_window] = own[:, block]
        return np.hstack([jac, starts])

    def fisher_at(x: FloatArray, r0: FloatArray, jac: FloatArray, sigma2: float) -> Fisher:
        """The information about the log of each fitted physical parameter and each probed
        one, the window starts (and a fitted delay) marginalized out."""
        p_at, d_at = unpack(x)
        segs_at = starts_at(x)
        logs = [i for i in range(n_par) if is_log[i]]
        # d log(physical) / dx: the identity, but for what is fitted over the scale
        phys = physical_of(x)
        dlog = np.eye(n_par)
        for i in np.flatnonzero(over):
            share = (phys[i] - fixed[i]) / phys[i]
            dlog[i, i] = share
            dlog[i, si] = share
        sub = dlog[np.ix_(logs, logs)]
        cols = list((jac[:, logs] @ np.linalg.inv(sub)).T)
        for ref in probe:
            v = max(param_value(p_at, d_at, ref), FRICTION_FLOOR)
            h = -0.01 if ref[0] == "torque_scale" else 0.01  # a scale is at most 1
            moved = params_with(p_at, [ref], [v * math.exp(h)])
            rp = replay.residuals(moved, d_at, segs_at, velocity_weight)
            cols.append(((rp if weights is None else rp * weights) - r0) / h)
        delay = [jac[:, i] for i in range(n_par) if not is_log[i]]
        starts = own_starts(x, r0) if n_fix and row_window is not None else None
        info = marginal_information(
            np.column_stack(cols),
            sigma2,
            np.column_stack(delay) if delay else None,
            starts,
            row_window,
        )
        refs_f = tuple([refs[i] for i in logs] + list(probe))
        values = tuple(param_value(p_at, d_at, ref) for ref in refs_f)
        return Fisher(refs_f, values, info)

    x = np.clip(x0, lower, upper)
    parts = residual_parts(x)
    r = weighed(parts)
    if row_window is not None and row_window.size != r.size:
        raise RuntimeError(f"{r.size} residuals for {row_window.size} window rows")
    cost = float(r @ r)
    costs = [cost]
    lam = 1e-3
    it = 0
    jac = jacobian(x, r)
    jac_at_x = True  # the Jacobian is at x (it is a function of x alone)
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
            parts_new = residual_parts(x_new)
            r_new = weighed(parts_new)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                improved = True
                gain = (cost - cost_new) / max(cost, 1e-30)
                x, r, cost, parts = x_new, r_new, cost_new, parts_new
                jac_at_x = False
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 4.0
        costs.append(cost)
        if on_iteration is not None:
            on_iteration(it, cost)
        if not improved or gain < tol:
            break
        jac = jacobian(x, r)
        jac_at_x = True
    # Uncertainty at the optimum: the Jacobian there (the last one, unless a step was taken
    # after it).
    if not jac_at_x:
        jac = jacobian(x, r)
    dof = max(r.size - x.size, 1)
    # residuals correlated in time carry fewer independent samples than rows: the variance
    # per row times the correlation time, in rows (`correlation_time`)
    segs_end = starts_at(x)
    blocks = []
    for seg, one in zip(segs_end, parts, strict=True):  # each segment's residuals at x
        windows = 0 if seg.start_fix is None else seg.start_fix.shape[0]
        rows = (one.size - 2 * windows) // (2 if velocity_weight > 0 else 1)
        blocks.append(one[:rows])
    tau = correlation_time(blocks)
    sigma2 = cost / dof * tau
    physical = physical_of(x)
    # d physical / dx, to carry the uncertainty over to the physical values
    grad = np.diag(np.where(is_log[:n_par], physical, 1.0))
    for i in np.flatnonzero(over):
        grad[i, i] = grad[i, si] = physical[i] - fixed[i]
    try:
        cov_x = sigma2 * np.linalg.inv(jac.T @ jac)[:n_par, :n_par]
        std = np.sqrt(np.maximum(np.diag(grad @ cov_x @ grad.T), 0.0))
    except np.linalg.LinAlgError:
        std = np.full(n_par, np.inf)
    fisher = fisher_at(x, r, jac, sigma2)
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
        fisher=fisher,
        correlation_rows=tau,
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
DRIVE_SCALES: tuple[float, ...] = (1.0, 0.5, 0.25)
"""`coarse_start` tries the grid at each of these torque scales of the joint's drive: a way to
span what a worn drive makes a joint look like (armature, friction and load over the scale, up
to 4x at the envelope's 25 %) with a grid around the nominal arm. The best point is then
expressed at the start's own scale (`equivalent`): the data cannot tell the two apart
(`reach_sim_bridge.fit.identifiability`), so the grid must not choose the scale. It once did,
by a tie-break between 1 and 0.25: an arm with 3.5 N m of friction on E and D at 70 % torque
came out with E, D and C at a quarter torque and a quarter of their friction."""


def equivalent(
    params: ArmParams, joint: int, scale: float, loads: Sequence[ParamRef] = ()
) -> ArmParams:
    """The arm that moves `joint` as `params` does with its drive at torque scale `scale`:
    the joint's armature, damping and Coulomb friction and the net weight in water of each
    link in `loads` multiplied by scale / (its scale now), the displaced volumes kept. Exact
    but for the links' own inertia (they do not scale)."""
    ratio = scale / params.torque_scale[joint]
    refs: list[ParamRef] = [("armature", joint), ("damping", joint), ("frictionloss", joint)]
    values = [param_value(params, 0.0, r) * ratio for r in refs]
    for ref in loads:
        buoyant = buoyant_kg(params, ref[1])
        refs.append(ref)
        values.append(buoyant + (params.link_mass_kg[ref[1]] - buoyant) * ratio)
    refs.append(("torque_scale", joint))
    values.append(scale)
    return params_with(params, refs, [max(v, FRICTION_FLOOR) for v in values])


def coarse_start(
    replay: Replay,
    segments: Sequence[Segment],
    base: ArmParams,
    refs: Sequence[ParamRef],
    velocity_weight: float = VELOCITY_WEIGHT_S,
    scales: Sequence[float] = DRIVE_SCALES,
    grid: Sequence[ParamRef] | None = None,
) -> list[ArmParams]:
    """Where Levenberg-Marquardt starts: `base`, or `base` with `refs` set to the best point
    of `COARSE_GRID` (around the nominal arm's values) at `base`'s torque scale if it fits
    the segments better; then the best of the grid tried at the other torque scales in
    `scales`, expressed at `base`'s (`at_own_scale`). Both, for `fit_arm` to start from
    each: neither start's cost says which basin holds the arm (a healthy C started from the
    half-torque grid's point, at 0.57 of the cost of the full-torque one's, stopped 20 % off
    in friction; a D behind 4.3 N m of friction started from the full-torque one's, 1.8 x
    the other's, stayed at 300 times the true arm's cost). `grid`: the refs to grid (default
    all of `refs`); the rest keep `base`'s values, a load among them carried over to `base`'s
    scale all the same. From the nominal arm alone a frictionless joint under 3x sensor
    noise was fitted at 7x its damping (and once at 20x its armature): the residual far from
    the arm is no guide."""
    nominal = ArmParams()
    joint = segments[0].joint
    axes: list[list[tuple[ParamRef, float]]] = []
    for name, j in refs if grid is None else grid:
        if name not in COARSE_GRID:  # the delay, a torque scale: kept as in `base`
            continue
        ref_value = getattr(nominal, name)[j]
        axes.append([((name, j), max(f * ref_value, FRICTION_FLOOR)) for f in COARSE_GRID[name]])
    loads = [r for r in refs if r[0] == LOAD]
    poses = np.concatenate([s.q[:: max(1, s.ticks // 40)] for s in segments])

    def cost(p: ArmParams) -> float:
        res = replay.residuals(p, 0.0, segments, velocity_weight)
        return float(res @ res)

    own = base.torque_scale[joint]
    starts: list[tuple[float, ArmParams, bool]] = [(cost(base), base, True)]
    for scale in scales:
        at_scale = params_with(base, [("torque_scale", joint)], [scale])
        found: tuple[float, ArmParams] | None = None
        for point in itertools.product(*axes):
            trial = params_with(at_scale, [ref for ref, _ in point], [v for _, v in point])
            # a point is replayed only as far as it takes to see it cost more than the best
            # so far (`Replay.cost`): the best, and its cost, are the same
            best = math.inf if found is None else found[0]
            c = replay.cost(trial, 0.0, segments, velocity_weight, above=best)
            if found is None or c < found[0]:
                found = (c, trial)
        if found is None:
            continue
        if scale == own:
            starts.append((found[0], found[1], True))
        else:
            there = at_own_scale(replay, found[1], joint, own, loads, poses)
            starts.append((cost(there), there, False))
    return [
        min((x for x in starts if x[2]), key=lambda x: x[0])[1],
        *[p for _, p, _ in sorted((x for x in starts if not x[2]), key=lambda x: x[0])[:1]],
    ]


def at_own_scale(
    replay: Replay,
    params: ArmParams,
    joint: int,
    scale: float,
    loads: Sequence[ParamRef],
    poses: FloatArray,
) -> ArmParams:
    """`params` with `joint`'s drive at torque scale `scale`, moving the joint as before: its
    armature, damping and friction scaled as in `equivalent`, and its fitted `loads` (link
    masses) set so that its gravity-buoyancy torque over the scale at `poses` is as before,
    in least squares. Why not `equivalent`'s loads: the links a joint carries that are not
    fitted (the C link, for C and D) do not scale, so the fitted ones must carry their share
    (a C grid point at a quarter torque, its wrist alone scaled, started the fit at 18 times
    the cost of the point itself and stopped 20 % off in friction)."""
    out = equivalent(params, joint, scale)
    if not loads:
        return out
    arm = replay.arm
    ratio = scale / params.torque_scale[joint]

    def torque(p: ArmParams) -> FloatArray:
        arm.set_params(p)
        return np.array([float(arm.gravity_torque(q)[joint]) for q in poses])

    target = torque(params) * ratio
    here = torque(out)
    # the torque is linear in each link's net weight: one column per fitted load
    cols = []
    for ref in loads:
        m = out.link_mass_kg[ref[1]]
        cols.append(torque(params_with(out, [ref], [m + 0.1])) - here)
    step, *_ = np.linalg.lstsq(np.column_stack(cols) / 0.1, target - here, rcond=None)
    masses = [
        max(out.link_mass_kg[r[1]] + float(d), buoyant_kg(out, r[1]) + FRICTION_FLOOR)
        for r, d in zip(loads, step, strict=True)
    ]
    return params_with(out, loads, masses)
