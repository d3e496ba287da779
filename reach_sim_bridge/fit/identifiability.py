"""What an excitation pins down: the Fisher information of one joint's fit (`Fisher`), its
directions from the best to the worst determined (`Fisher.directions`), and the uncertainty of
any product of parameters (`Fisher.sigma`).

Why: in current mode a joint obeys (I_a + M_jj) qdd = s k i - b qd - f_c sgn(qd) + g_j, and
multiplying the drive's torque scale s together with the armature, damping, Coulomb friction
and the net gravity-buoyancy load by one factor changes no motion (only the links' own inertia
M_jj does not scale, a few per cent of the joint's). A fit that picks one point along that
direction and prints it is confidently wrong; the Fisher information shows the direction (its
smallest eigenvalue) and what is fixed across it (any ratio p / s). Everything here is in
log-parameters, so a 1-sigma of 0.05 is 5 % of the value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocol.alpha5 import FACTORY_MIDDLE, JOINT_LETTERS
from reach_sim_bridge.fit.replay import ParamRef, params_with, ref_name
from reach_sim_bridge.fit.segments import FloatArray
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams

INERTIA = "inertia_kgm2"
"""The name of a joint's whole inertia at `FACTORY_MIDDLE` (`joint_inertia`): what its
armature is known as where its torque scale is not. The links' own inertia does not scale
with the drive, so the armature alone over the scale is not what the data fix: a joint at
25 % torque fitted at full torque has armature / 0.25 + 3 x its links' inertia."""
NET_WEIGHT = "net_weight_kg"
"""The name of a link's net weight in water (kg): its mass less the water it displaces (mass
and displaced volume act together)."""
LOAD_RMS = "load_nm"
"""The name of a joint's gravity-buoyancy load as the data fix it (`joint_load`): what a
fitted load (an effective link mass) is known as. The split of D's load between its own link
and the wrist rests on the C link's weight, held at the datasheet's, so a link's net weight
alone is not what the data fix (D's link came out 19 % and 50 % off on envelope arms whose
masses and volumes were 10-20 % off the datasheet's)."""
DRAG = "drag_nm"
"""The name of a joint's friction torque at `DRAG_SPEED`: Coulomb friction plus damping times
that speed, what damping behind a large Coulomb friction is known as."""
DRAG_SPEED = 0.35
"""rad/s: the excitation's fastest relay swing."""
LOAD_SWEEP_RAD = 0.35
"""`joint_load` turns the joint this far either way (the excitation's window)."""


@dataclass(frozen=True)
class Direction:
    """A direction in log-parameter space: the product of the parameters raised to
    `exponents` (the largest of magnitude 1), known to `sigma` (relative, 1 sigma)."""

    exponents: tuple[float, ...]
    sigma: float

    def describe(self, refs: Sequence[ParamRef]) -> str:
        """e.g. "armature[E]^1 damping[E]^0.98 ... torque_scale[E]^1" (terms under 0.05 left
        out): the product that moves by `sigma` at one sigma of the data."""
        terms = [
            f"{ref_name(r)}^{e:+.2f}"
            for r, e in zip(refs, self.exponents, strict=True)
            if abs(e) >= 0.05
        ]
        return " ".join(terms)


@dataclass(frozen=True)
class Fisher:
    """A fit's information about its parameters at the optimum: `info` = J^T J / sigma^2 over
    the log of each of `refs` (fitted or only probed), the nuisances (window starts, a delay)
    marginalized out. `values` are the physical values there."""

    refs: tuple[ParamRef, ...]
    values: tuple[float, ...]
    info: FloatArray

    def __post_init__(self) -> None:
        n = len(self.refs)
        if self.info.shape != (n, n) or len(self.values) != n:
            raise ValueError(f"Fisher information for {n} refs has shape {self.info.shape}")

    def covariance(self) -> FloatArray:
        """The inverse of `info` (a pseudo-inverse where it is singular)."""
        return np.asarray(np.linalg.pinv(self.info, rcond=1e-14, hermitian=True), dtype=float)

    def directions(self) -> list[Direction]:
        """The eigen-directions of `info`, best determined first."""
        vals, vecs = np.linalg.eigh(self.info)
        out = []
        for k in np.argsort(vals)[::-1]:
            v = vecs[:, k]
            big = float(np.max(np.abs(v)))
            v = v / (big if v[int(np.argmax(np.abs(v)))] > 0 else -big)
            sigma = math.inf if vals[k] <= 0 else 1.0 / (math.sqrt(float(vals[k])) * big)
            out.append(Direction(tuple(float(x) for x in v), sigma))
        return out

    def index(self, ref: ParamRef) -> int:
        return self.refs.index(ref)

    def sigma(self, exponents: Mapping[ParamRef, float], given: Sequence[ParamRef] = ()) -> float:
        """1-sigma (relative) of the product of `refs` raised to `exponents`, e.g.
        {friction: 1, scale: -1} for friction / torque scale; with the parameters `given`
        taken as known (a torque scale the anchor fixes), the others free."""
        keep = [i for i, r in enumerate(self.refs) if r not in given]
        e = np.zeros(len(keep))
        for ref, power in exponents.items():
            e[keep.index(self.index(ref))] = power
        sub = self.info[np.ix_(keep, keep)]
        cov = np.linalg.pinv(sub, rcond=1e-14, hermitian=True)
        var = float(e @ cov @ e)
        return math.sqrt(var) if var > 0 else 0.0

    def value(self, exponents: Mapping[ParamRef, float]) -> float:
        """The product itself at the optimum."""
        return math.prod(self.values[self.index(r)] ** p for r, p in exponents.items())

    def to_json_dict(self) -> dict[str, Any]:
        """Per direction (best first) its exponents by parameter name and its 1-sigma."""
        names = [ref_name(r) for r in self.refs]
        return {
            "parameters": names,
            "directions": [
                {
                    "exponents": {n: round(e, 3) for n, e in zip(names, d.exponents, strict=True)},
                    "sigma": _finite(d.sigma),
                }
                for d in self.directions()
            ],
        }


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def marginal_information(
    jac: FloatArray,
    sigma2: float,
    nuisance: FloatArray | None = None,
    grouped: FloatArray | None = None,
    groups: NDArray[np.int64] | None = None,
) -> FloatArray:
    """J^T J / sigma^2 of the columns `jac`, with what nuisances fitted beside them can take
    projected out: the information left about `jac`'s parameters. `nuisance`: columns that
    move every row (a fitted delay); `grouped`: per residual row, its derivatives by the
    nuisances of its own group (`groups`: a window's start moves that window's rows only),
    so each group is projected on its own (after `nuisance`, an approximation where both
    are given)."""
    j = np.array(jac, dtype=float)
    if nuisance is not None and nuisance.size:
        coef, *_ = np.linalg.lstsq(nuisance, j, rcond=None)
        j -= nuisance @ coef
    if grouped is not None and grouped.size:
        n = np.asarray(grouped, dtype=float).reshape(j.shape[0], -1)
        ids = np.zeros(j.shape[0], dtype=np.int64) if groups is None else np.asarray(groups)
        order = np.argsort(ids, kind="stable")
        bounds = np.flatnonzero(np.diff(ids[order])) + 1
        for rows in np.split(order, bounds):
            coef, *_ = np.linalg.lstsq(n[rows], j[rows], rcond=None)
            j[rows] -= n[rows] @ coef
    return (j.T @ j) / max(sigma2, 1e-300)


class ScaleStatus(str, Enum):
    """What the data say about a joint's torque scale."""

    #: fitted against an absolute reference (a load another joint weighed at its full torque)
    IDENTIFIED = "identified"
    #: the reference itself: this drive assumed at its datasheet torque per amp
    ANCHOR = "anchor"
    #: nothing ties it to an absolute reference: only the joint's parameters over it are known
    UNIDENTIFIABLE = "unidentifiable"


@dataclass(frozen=True)
class ScaleVerdict:
    """A joint's torque scale as the fit reports it: `value` is the twin's (for an
    unidentifiable scale, the datasheet's 1: an assumption, not a finding), `sigma` the
    relative 1-sigma the data give it (None for an anchor), `reason` in words."""

    joint: int
    status: ScaleStatus
    value: float
    sigma: float | None
    reason: str

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "status": self.status.value,
            "twin_value": self.value,
            "sigma_relative": None if self.sigma is None else _finite(self.sigma),
            "reason": self.reason,
        }


def combination_value(params: ArmParams, name: str) -> float:
    """An arm's value of a parameter or a combination as the fit names them (`ref_name`'s
    `field[L]`; `net_weight_kg[L]`, the link's mass less the water it displaces;
    `inertia_kgm2[L]`, `joint_inertia`; `load_nm[L]`, `joint_load`; `drag_nm[L]`, the friction
    torque at `DRAG_SPEED`; one over another, `a/b`),
    e.g. the true arm's, to score what a fit reported."""
    value = 1.0
    for k, term in enumerate(name.split("/")):
        field, rest = term.split("[")
        j = JOINT_LETTERS.index(rest.rstrip("]"))
        if field == NET_WEIGHT:
            v = params.link_mass_kg[j] - float(params.buoyancy_kg()[j])
        elif field == INERTIA:
            v = joint_inertia(params, j)
        elif field == LOAD_RMS:
            v = joint_load(params, j)
        elif field == DRAG:
            v = params.frictionloss[j] + params.damping[j] * DRAG_SPEED
        else:
            v = float(getattr(params, field)[j])
        value = value * v if k == 0 else value / v
    return value


def joint_inertia(params: ArmParams, joint: int) -> float:
    """Joint `joint`'s (E D C B index) inertia at `FACTORY_MIDDLE` with the others still: its
    armature plus its links' (kg m^2)."""
    return float(Alpha5Arm(params=params).mass_matrix(np.array(FACTORY_MIDDLE))[joint, joint])


CORRELATION_LAGS = 150
"""`correlation_time` sums the autocorrelation up to this many rows (3 s at 50 Hz)."""


def correlation_time(blocks: Sequence[FloatArray], max_lag: int = CORRELATION_LAGS) -> float:
    """The residuals' integrated autocorrelation time, in rows: 1 + 2 x the sum of their
    autocorrelation over the lags before it first drops to zero, averaged over `blocks` (one
    per segment) by length; 1 for white residuals. The residual variance times it is what
    the Fisher information and the 1-sigma uncertainties divide by: a model error that
    stays for half a second is one piece of evidence, not 25. Without it a wrist at 30 %
    torque had its scale fitted to +-1.5 % and came out 12 % off."""
    total, weight = 0.0, 0
    for block in blocks:
        x = np.asarray(block, dtype=float)
        x = x[np.isfinite(x)]
        n = x.size
        if n < 4:
            continue
        x = x - x.mean()
        var = float(x @ x)
        if var <= 0:
            continue
        tau = 1.0
        for k in range(1, min(max_lag, n - 1)):
            rho = float(x[:-k] @ x[k:]) / var
            if rho <= 0:
                break
            tau += 2.0 * rho
        total += tau * n
        weight += n
    return total / weight if weight else 1.0


def joint_load(params: ArmParams, joint: int) -> float:
    """The RMS of joint `joint`'s gravity-buoyancy torque (N m) as it turns +-`LOAD_SWEEP_RAD`
    about `FACTORY_MIDDLE`, the others there: one number for the load the excitation weighs."""
    arm = Alpha5Arm(params=params)
    q = np.array(FACTORY_MIDDLE)
    torques = []
    for dq in np.linspace(-LOAD_SWEEP_RAD, LOAD_SWEEP_RAD, 7):
        at = q.copy()
        at[joint] += dq
        torques.append(float(arm.gravity_torque(at)[joint]))
    return math.sqrt(float(np.mean(np.square(torques))))


def load_exponents(
    params: ArmParams, joint: int, loads: Sequence[ParamRef]
) -> dict[ParamRef, float]:
    """d log(`joint_load`) / d log(mass) for each load in `loads`: how the load's log moves
    with each fitted mass's (1 % steps), for its uncertainty from the Fisher information."""
    base = math.log(max(joint_load(params, joint), 1e-12))
    out = {}
    for ref in loads:
        m = params.link_mass_kg[ref[1]]
        moved = params_with(params, [ref], [m * math.exp(0.01)])
        out[ref] = (math.log(max(joint_load(moved, joint), 1e-12)) - base) / 0.01
    return out
