"""The uncertainty envelope: every arm a controller may meet, its corners and random draws.

The twin's parameters come from a datasheet and assumptions; the envelope spans what they may
really be (docs/robustness.md gives the sources). A `Variant` is one arm of the envelope, as
the evaluation runs it: its `ArmParams`, a per-joint torque scale, a sensor-noise multiple
and a control latency. Some corners cannot be controlled by anyone: at 25 % torque a joint's
drive cannot overcome 6.6 N m of Coulomb friction. `infeasible()` says which from the motor
model and the worst static gravity-buoyancy load over the workspace, and `corners()` and
`draws()` leave those arms out (and count them).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from policy.controllers.observation import WORKSPACE_HIGH, WORKSPACE_LOW
from policy.tasks.episodes import Episode, RunConfig
from protocol.alpha5 import JOINT_LETTERS, N_JOINTS
from protocol.models import ALPHA5, ArmModel
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.motor import MotorModel
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.sensors import SensorNoise


def has_envelope(model: ArmModel) -> bool:
    """Whether the uncertainty envelope, and the training env's perturbation of the arm's
    parameters around the nominal ones, are defined for `model`: the Alpha 5's only (the
    ranges below, its weak joints and its latencies are the Alpha's)."""
    return model is ALPHA5


Span = tuple[float, float]


@dataclass(frozen=True)
class Envelope:
    """The ranges (see docs/robustness.md for where each comes from).

    Absolute ranges are in N m; relative ones scale the base arm's value per joint."""

    #: Coulomb friction of E, D and C (N m): 0 (an identified ROS twin) to 6.6 (the
    #: datasheet's input-side friction referred through the gearbox).
    coulomb_edc: Span = (0.0, 6.6)
    #: Coulomb friction of B (N m), the same sources for the wrist's smaller drive.
    coulomb_b: Span = (0.0, 0.16)
    #: viscous friction, armature: relative factor range
    viscous: Span = (0.5, 1.5)
    armature: Span = (0.5, 1.5)
    #: link masses and displaced volumes (buoyancy): relative factor range
    link_mass: Span = (0.8, 1.2)
    buoyancy: Span = (0.8, 1.2)
    #: torque scale of the one joint that is weak (a worn drive); the others are at 1
    torque_scale: Span = (0.25, 1.0)
    #: multiple of the standard sensor noise (0.002 rad, 0.02 rad/s)
    noise: Span = (1.0, 3.0)
    #: control latency in control periods
    latency_periods: Span = (0.0, 2.0)
    #: an arm is feasible when each joint's stall torque is at least this multiple of its
    #: Coulomb friction plus its worst static gravity-buoyancy load (a margin to accelerate)
    headroom: float = 1.2

    def __post_init__(self) -> None:
        for name in (
            "coulomb_edc",
            "coulomb_b",
            "viscous",
            "armature",
            "link_mass",
            "buoyancy",
            "torque_scale",
            "noise",
            "latency_periods",
        ):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi):
                raise ValueError(f"envelope {name} must be 0 <= low <= high, got {(lo, hi)}")
        if self.torque_scale[1] > 1.0 or self.torque_scale[0] <= 0.0:
            raise ValueError(f"torque_scale must lie in (0, 1], got {self.torque_scale}")


@dataclass(frozen=True)
class Variant:
    """One arm of the envelope, as an evaluation runs it."""

    name: str
    params: ArmParams
    torque_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    noise_scale: float = 1.0
    latency_periods: float = 0.0
    factors: dict[str, float] = field(default_factory=dict)  # what was drawn, for reports

    def run_config(self, base: RunConfig) -> RunConfig:
        """`base` on this arm: its params, its noise multiple (if base has noise), latency."""
        noise = base.noise
        if noise is not None:
            noise = SensorNoise(
                noise.position_std * self.noise_scale, noise.velocity_std * self.noise_scale
            )
        return replace(base, params=self.params, noise=noise, latency_periods=self.latency_periods)

    def episode(self, episode: Episode) -> Episode:
        """`episode` on this arm (its torque scale; the episode's own is replaced)."""
        return replace(episode, torque_scale=np.asarray(self.torque_scale, dtype=float))

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "factors": dict(self.factors),
            "torque_scale": list(self.torque_scale),
            "noise_scale": self.noise_scale,
            "latency_periods": self.latency_periods,
        }


@dataclass(frozen=True)
class Feasibility:
    """Per joint: the torque the weakest drive has at stall and what it must overcome."""

    stall_torque: np.ndarray  # N m, torque scale included
    required: np.ndarray  # N m: Coulomb friction + worst static gravity-buoyancy load
    headroom: float

    @property
    def weak_joints(self) -> list[str]:
        short = self.stall_torque < self.headroom * self.required
        return [JOINT_LETTERS[j] for j in range(N_JOINTS) if short[j]]

    @property
    def ok(self) -> bool:
        return not self.weak_joints

    def reason(self) -> str:
        return "; ".join(
            f"{JOINT_LETTERS[j]}: stall {self.stall_torque[j]:.2f} N m < {self.headroom:g} x "
            f"{self.required[j]:.2f} N m (friction + load)"
            for j in range(N_JOINTS)
            if JOINT_LETTERS[j] in self.weak_joints
        )


_GRID = 7  # poses per joint of D C B over the workspace for the worst static load


def worst_static_load(params: ArmParams, arm: Alpha5Arm | None = None) -> np.ndarray:
    """Largest |gravity + buoyancy torque| per joint (N m) over a grid of the workspace;
    `arm`, if given, is set to `params` and reused (a model compiled once for many arms)."""
    if arm is None:
        arm = Alpha5Arm(params=params)
    else:
        arm.set_params(params)
    axes = [np.linspace(WORKSPACE_LOW[j], WORKSPACE_HIGH[j], _GRID) for j in (1, 2, 3)]
    poses = [[WORKSPACE_LOW[0], d, c, b] for d, c, b in itertools.product(*axes)]
    return np.abs(arm.gravity_torques(poses)).max(axis=0)


def feasibility(
    params: ArmParams,
    torque_scale: Sequence[float],
    headroom: float,
    arm: Alpha5Arm | None = None,
) -> Feasibility:
    """Whether each joint can move at all on this arm (the motor model's stall torque);
    `arm` as `worst_static_load` takes it."""
    motor = MotorModel(params.motors, params.supply_voltage, params.current_limits_mA, torque_scale)
    required = np.asarray(params.frictionloss) + worst_static_load(params, arm)
    return Feasibility(motor.stall_torque(), required, headroom)


def _scaled(values: Sequence[float], factor: float) -> tuple[float, float, float, float]:
    out = np.asarray(values, dtype=float) * factor
    return (float(out[0]), float(out[1]), float(out[2]), float(out[3]))


def make_variant(
    base: ArmParams,
    name: str,
    *,
    coulomb_edc: float,
    coulomb_b: float,
    viscous: float,
    armature: float,
    link_mass: float,
    buoyancy: float,
    weak_joint: int | None,
    torque_scale: float,
    noise: float,
    latency_periods: float,
) -> Variant:
    """An arm from factors: absolute Coulomb friction, the rest relative to `base`."""
    params = replace(
        base,
        frictionloss=(coulomb_edc, coulomb_edc, coulomb_edc, coulomb_b),
        damping=_scaled(base.damping, viscous),
        armature=_scaled(base.armature, armature),
        link_mass_kg=_scaled(base.link_mass_kg, link_mass),
        link_volume_l=_scaled(base.link_volume_l, buoyancy),
    )
    scale = [1.0] * N_JOINTS
    if weak_joint is not None:
        scale[weak_joint] = torque_scale
    factors = {
        "coulomb_edc": coulomb_edc,
        "coulomb_b": coulomb_b,
        "viscous": viscous,
        "armature": armature,
        "link_mass": link_mass,
        "buoyancy": buoyancy,
        "weak_joint": -1.0 if weak_joint is None else float(weak_joint),
        "torque_scale": torque_scale if weak_joint is not None else 1.0,
        "noise": noise,
        "latency_periods": latency_periods,
    }
    return Variant(
        name, params, (scale[0], scale[1], scale[2], scale[3]), noise, latency_periods, factors
    )


@dataclass(frozen=True)
class Selection:
    """Feasible variants, and the infeasible ones left out with the reason."""

    variants: list[Variant]
    infeasible: list[tuple[Variant, str]]


def corners(envelope: Envelope = Envelope(), base: ArmParams | None = None) -> Selection:
    """Every corner: each range at its low and high end (E D C's friction together, each
    relative factor on all joints together), and no weak joint or one of E D C B at the
    lowest torque scale: 2^8 x 5 = 1280 arms before the infeasible ones are left out."""
    e = envelope
    base = base or ArmParams()
    two = [
        e.coulomb_edc,
        e.coulomb_b,
        e.viscous,
        e.armature,
        e.link_mass,
        e.buoyancy,
        e.noise,
        e.latency_periods,
    ]
    weak: list[int | None] = [None, *range(N_JOINTS)]
    keep: list[Variant] = []
    out: list[tuple[Variant, str]] = []
    loads: dict[tuple[float, float], np.ndarray] = {}
    for bits in itertools.product((0, 1), repeat=len(two)):
        values = [span[b] for span, b in zip(two, bits, strict=True)]
        cf, cb, visc, arm, mass, buoy, noise, lat = values
        for w in weak:
            tag = "-" if w is None else JOINT_LETTERS[w]
            name = "corner " + "".join("LH"[b] for b in bits) + tag
            v = make_variant(
                base,
                name,
                coulomb_edc=cf,
                coulomb_b=cb,
                viscous=visc,
                armature=arm,
                link_mass=mass,
                buoyancy=buoy,
                weak_joint=w,
                torque_scale=e.torque_scale[0],
                noise=noise,
                latency_periods=lat,
            )
            if (mass, buoy) not in loads:
                loads[(mass, buoy)] = worst_static_load(v.params)
            feas = _feasibility_with(v, loads[(mass, buoy)], e.headroom)
            if feas.ok:
                keep.append(v)
            else:
                out.append((v, feas.reason()))
    return Selection(keep, out)


def _feasibility_with(variant: Variant, load: np.ndarray, headroom: float) -> Feasibility:
    p = variant.params
    motor = MotorModel(p.motors, p.supply_voltage, p.current_limits_mA, variant.torque_scale)
    return Feasibility(motor.stall_torque(), np.asarray(p.frictionloss) + load, headroom)


def draws(
    n: int, seed: int, envelope: Envelope = Envelope(), base: ArmParams | None = None
) -> Selection:
    """`n` feasible arms drawn uniformly from the envelope (each range independently, the
    weak joint uniform over none and E D C B); infeasible draws are redrawn and returned
    too, so a report can say how much of the envelope no controller can serve."""
    if n < 1:
        raise ValueError(f"need at least one draw, got {n}")
    rng = np.random.default_rng([seed, 0xE7])
    e = envelope
    base = base or ArmParams()
    keep: list[Variant] = []
    out: list[tuple[Variant, str]] = []
    arm = Alpha5Arm(params=base)  # one model, set to each draw's parameters in turn
    for i in itertools.count():
        if len(keep) == n:
            break

        def u(span: Span) -> float:
            return float(rng.uniform(span[0], span[1]))

        w_index = int(rng.integers(0, N_JOINTS + 1))
        v = make_variant(
            base,
            f"draw {seed}:{i}",
            coulomb_edc=u(e.coulomb_edc),
            coulomb_b=u(e.coulomb_b),
            viscous=u(e.viscous),
            armature=u(e.armature),
            link_mass=u(e.link_mass),
            buoyancy=u(e.buoyancy),
            weak_joint=None if w_index == N_JOINTS else w_index,
            torque_scale=u(e.torque_scale),
            noise=u(e.noise),
            latency_periods=u(e.latency_periods),
        )
        feas = feasibility(v.params, v.torque_scale, e.headroom, arm)
        if feas.ok:
            keep.append(v)
        else:
            out.append((v, feas.reason()))
    return Selection(keep, out)
