"""The simulated arms: MuJoCo physics of an arm's MJCF driven by motor currents.

`MotorArm` steps any arm model's joints and jaw (`protocol.models.ArmModel`) with currents;
`Alpha5Arm` is the Alpha 5 of model/alpha5.xml with its run-time parameters (`ArmParams`),
and `reach_sim_bridge.model.bravo7.Bravo7Arm` the Bravo 7. The firmware emulation, the RL
environment and MPC all step these, so the arm they see is the same. Commands are currents
(mA); the motor model (reach_sim_bridge.model.motor) turns them into torque with the current
limit and the back-EMF speed-torque envelope re-evaluated every physics step.

How the back-EMF clamp is integrated (why this shape): at the supply voltage the motor's
torque falls along ``tau = k (V - Ke w) / R``, a damping of ~128 N m s/rad on E/D/C against an
armature of 0.12 kg m^2, i.e. a ~1 ms time constant. Applied explicitly at dt = 2 ms that
chatters (tools/bench_sim.py measures it). So each physics step picks each motor's regime from
its joint speed: current-limited (input torque ``k i``) or voltage-limited (input torque
``+-k V / R`` plus ``k Ke / R`` added to the joint's damping). MuJoCo's Euler integrator
integrates joint damping implicitly, so the back-EMF slope is integrated implicitly too.
(implicitfast would also do that through an affine actuator bias, but it differentiates the
fluid drag every step as well, which halves the speed for a force under 0.5 % of the
damping.) The regime test compares the speed with two thresholds fixed for the control
period, with plain floats, and model arrays are written only when a regime changes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol.alpha5 import JOINT_LETTERS as JOINTS
from protocol.models import ALPHA5, ArmModel
from reach_sim_bridge.model.motor import MotorModel
from reach_sim_bridge.model.params import (
    LINK_BODIES,
    NOSLIP_ITERATIONS,
    ArmParams,
    joint_order,
)

__all__ = ["MODEL_PATH", "Alpha5Arm", "ArmParams", "JOINTS", "MotorArm"]

MODEL_PATH = Path(__file__).resolve().parent / "alpha5.xml"

FloatArray = NDArray[np.float64]

_TCP_SITE = "tcp"
_BUOYANCY_SUFFIX = "_buoyancy"
_PAYLOAD_BODY = "payload"  # where a load held in the jaws goes (`ArmParams.payload_kg`)
COAST_ARMATURE = 1e6
"""kg m^2: a joint with this armature (`MotorArm.coast`) gains 2e-9 rad/s per N m per 2 ms
step (the arm's own: 0.003-0.2). Not more: at 1e9 MuJoCo's solve lost precision, and a replay
of a noise-free log through the true arm came out 0.3 mrad off instead of 4e-9 rad."""


@dataclass(frozen=True)
class _StepConstants:
    """Per-actuator constants (the joints, then the jaw) that `MotorArm.step` needs every call,
    derived once
    per setting of the motors: rebuilding them took most of a short call's time (a replay
    steps a few physics steps per call, tools/bench_sim.py)."""

    motors: tuple[MotorModel, MotorModel]
    key: tuple[object, ...]
    limit: FloatArray
    neg_limit: FloatArray
    torque: FloatArray  # N m per A at the output for the reported torque (the jaw's unscaled)
    backemf: FloatArray
    resistance: FloatArray
    supply: FloatArray
    v: float  # the supply the step's regimes use (the arm's motors')
    limit_f: list[float]
    drive_f: list[float]  # N m per A at the output, torque scale included
    backemf_f: list[float]
    resistance_f: list[float]
    f_volt: list[float]
    base: list[float]
    d_volt: list[float]
    supply_f: list[float]
    neg_limit_f: list[float]
    torque_f: list[float]
    per_actuator: tuple[list[float], ...]  # limit_f, resistance_f, backemf_f, drive_f

    @classmethod
    def of(
        cls,
        motors: tuple[MotorModel, MotorModel],
        base_damping: FloatArray,
        key: tuple[object, ...],
    ) -> _StepConstants:
        arm, jaw = motors
        limit = np.concatenate([mm.current_limits_mA for mm in motors])
        supply = np.array([arm.supply_voltage] * arm.count + [jaw.supply_voltage])
        torque = np.concatenate([arm.torque_scale * arm.torque_per_amp, jaw.torque_per_amp])
        drive = np.concatenate([mm.torque_scale * mm.torque_per_amp for mm in motors])
        backemf = np.concatenate([mm.backemf_per_speed for mm in motors])
        resistance = np.concatenate([mm.resistance for mm in motors])
        v = arm.supply_voltage
        return cls(
            motors=motors,
            key=key,
            limit=limit,
            neg_limit=-limit,
            torque=torque,
            backemf=backemf,
            resistance=resistance,
            supply=supply,
            v=v,
            limit_f=limit.tolist(),
            drive_f=drive.tolist(),
            backemf_f=backemf.tolist(),
            resistance_f=resistance.tolist(),
            f_volt=(drive * v / resistance).tolist(),
            base=base_damping.tolist(),
            d_volt=(base_damping + drive * backemf / resistance).tolist(),
            supply_f=supply.tolist(),
            neg_limit_f=(-limit).tolist(),
            torque_f=torque.tolist(),
            per_actuator=(
                limit.tolist(),
                resistance.tolist(),
                backemf.tolist(),
                drive.tolist(),
            ),
        )


def check_dt(dt: float) -> float:
    """The physics step (s); ValueError unless in (0, 0.01]."""
    if not (math.isfinite(dt) and 0.0 < dt <= 0.01):
        raise ValueError(f"physics dt must be in (0, 0.01] s, got {dt}")
    return float(dt)


class MotorArm:
    """An arm model's joints and jaw in MuJoCo, stepped with motor currents; state in the
    arm's units. Arrays are in the model's joint order (`arm_model.joints`); the MJCF must
    name its joints by device letter, joints first in that order, then the jaw."""

    def __init__(
        self,
        model: mujoco.MjModel,
        arm_model: ArmModel,
        motor: MotorModel,
        jaw_motor: MotorModel,
        dt: float = 0.002,
        seed: int | None = None,
        link_bodies: Sequence[str] = (),
    ) -> None:
        self.arm_model = arm_model
        self.model = model
        self.model.opt.timestep = check_dt(dt)
        self.data = mujoco.MjData(self.model)
        self._scratch = mujoco.MjData(self.model)
        self._rng = np.random.default_rng(seed)
        n = arm_model.n_joints
        self._n = n
        m = self.model
        names = (*arm_model.joint_letters, arm_model.jaw.name)
        joint_ids = [m.joint(name).id for name in names]
        self._qadr = np.array([m.jnt_qposadr[j] for j in joint_ids])
        self._dofadr = np.array([m.jnt_dofadr[j] for j in joint_ids])
        if self._qadr.tolist() != list(range(n + 1)) or self._dofadr.tolist() != list(range(n + 1)):
            raise RuntimeError(f"the MJCF must order its joints {' '.join(names)}")
        self._joint_ids = joint_ids
        self._link_ids = np.array([m.body(name).id for name in link_bodies], dtype=int)
        self._tcp = m.site(_TCP_SITE).id
        self._jaw_range_m = m.jnt_range[joint_ids[n]].copy()
        #: Index of the joint reported modulo 2 pi (a wrist turning without end stops).
        self._wrap: int | None = None

        # Live views into MuJoCo's buffers, used in the stepping loop.
        self._qvel = self.data.qvel
        self._ctrl = self.data.ctrl
        self._damping = m.dof_damping
        self._base_damping = m.dof_damping[self._dofadr].copy()

        self.motor = motor
        self.jaw_motor = jaw_motor
        self._command_mA = np.zeros(n + 1)
        self._step_constants: _StepConstants | None = None
        self._outputs_pending: tuple[_StepConstants, FloatArray] | None = None
        self._current_mA = np.zeros(n + 1)
        self._tau = np.zeros(n + 1)

    @property
    def continuous_joint(self) -> int | None:
        """Index of the joint that turns without end stops and is reported in [0, 2 pi)."""
        return self._wrap

    # -- parameters -------------------------------------------------------------------------
    def _init_params(
        self,
        params: ArmParams,
        collision_geoms: Sequence[str],
        fixed_volumes_l: Sequence[tuple[str, float]] = (),
    ) -> None:
        """Take `ArmParams` for this arm and apply `params`: per joint, the first
        `n_joints` link bodies (the link each joint moves) and their `_buoyancy` bodies;
        `fixed_volumes_l`, bodies that float but are no parameter (the Bravo's jaws: their
        displaced litres), follow the water density; `collision_geoms` are the geoms
        `self_collision` turns on."""
        m, n = self.model, self._n
        if params.n_joints != n:
            raise ValueError(
                f"arm parameters of {params.n_joints} joints ({joint_order(params.n_joints)}) "
                f"do not describe the {self.arm_model.title} ({n} joints "
                f"{' '.join(self.arm_model.joint_letters)})"
            )
        self._param_links = self._link_ids[:n]
        self._wrist = n - 1  # the wrist roll, the last joint: the one `wrist_continuous` frees
        names = [m.body(int(b)).name for b in self._param_links]
        self._buoy_ids = np.array([m.body(name + _BUOYANCY_SUFFIX).id for name in names])
        self._fixed_buoys = [
            (m.body(name + _BUOYANCY_SUFFIX).id, litres) for name, litres in fixed_volumes_l
        ]
        every = [*self._buoy_ids.tolist(), *(b for b, _ in self._fixed_buoys)]
        self._buoy_gravcomp = m.body_gravcomp[self._buoy_ids].copy()
        if np.any(m.body_gravcomp[every] <= 1.0):
            raise RuntimeError("buoyancy bodies need gravcomp > 1 (net upward force)")
        payload = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, _PAYLOAD_BODY)
        #: the body a held load is given to, and its buoyancy's (None: the MJCF has none)
        self._payload = (
            None if payload < 0 else (payload, m.body(_PAYLOAD_BODY + _BUOYANCY_SUFFIX).id)
        )
        self._nominal_mass = m.body_mass[self._param_links].copy()
        self._nominal_inertia = m.body_inertia[self._param_links].copy()
        self._collision_geoms = np.array([m.geom(name).id for name in collision_geoms])
        self._base_damping[:] = 0.0
        self._params = params
        self.nominal_params = params  # what randomize() perturbs around
        self.set_params(params)

    @property
    def params(self) -> ArmParams:
        """The parameters in force, including run-time changes to limits and torque scale."""
        return replace(
            self._params,
            supply_voltage=self.motor.supply_voltage,
            current_limits_mA=tuple(float(v) for v in self.motor.current_limits_mA),
            torque_scale=tuple(float(v) for v in self.motor.torque_scale),
            jaw_current_limit_mA=float(self.jaw_motor.current_limits_mA[0]),
        )

    def set_params(self, params: ArmParams) -> None:
        """Apply parameters to the compiled model in place (no recompilation; state kept);
        ValueError, with nothing changed, for parameters of another number of joints or a
        payload on a model that holds none."""
        n = self._n
        if params.n_joints != n:
            raise ValueError(
                f"arm parameters of {params.n_joints} joints for the {self.arm_model.title} "
                f"({n} joints)"
            )
        if self._payload is None and (params.payload_kg or params.payload_volume_l):
            raise ValueError(f"the {self.arm_model.title}'s model takes no payload")
        if params.motors != self.motor.params or params.jaw_motor != self.jaw_motor.params:
            self.motor = MotorModel(params.motors)
            self.jaw_motor = MotorModel(params.jaw_motor)
        m = self.model
        dof = self._dofadr
        m.dof_armature[dof[:n]] = params.armature
        m.dof_damping[dof[:n]] = params.damping
        m.dof_frictionloss[dof[:n]] = params.frictionloss
        m.dof_armature[dof[n]] = params.jaw_armature
        m.dof_damping[dof[n]] = params.jaw_damping
        self._base_damping[:n] = params.damping
        self._base_damping[n] = params.jaw_damping
        m.dof_frictionloss[dof[n]] = params.jaw_frictionloss

        mass = np.asarray(params.link_mass_kg)
        m.body_mass[self._param_links] = mass
        ratio = mass / self._nominal_mass
        m.body_inertia[self._param_links] = self._nominal_inertia * ratio[:, None]
        # gravcomp g_c on a body of mass m_b gives a net upward force (g_c - 1) m_b g.
        m.body_mass[self._buoy_ids] = params.buoyancy_kg() / (self._buoy_gravcomp - 1.0)
        for body, litres in self._fixed_buoys:
            lift = litres * 1e-3 * params.water_density
            m.body_mass[body] = lift / (m.body_gravcomp[body] - 1.0)

        self._set_payload(params)

        drag = params.fluid_drag and params.in_water
        m.opt.density = params.water_density if drag else 0.0
        m.opt.viscosity = params.fluid_viscosity if drag else 0.0
        m.opt.gravity[:] = params.gravity
        m.opt.noslip_iterations = NOSLIP_ITERATIONS if params.friction_holds else 0
        m.jnt_limited[self._joint_ids[self._wrist]] = 0 if params.wrist_continuous else 1
        self._wrap = self._wrist if params.wrist_continuous else None
        collide = 1 if params.self_collision else 0
        m.geom_contype[self._collision_geoms] = collide
        m.geom_conaffinity[self._collision_geoms] = collide
        if params.self_collision:
            m.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        else:
            m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)

        for motor in (self.motor, self.jaw_motor):
            motor.supply_voltage = params.supply_voltage
        self.motor.current_limits_mA = params.current_limits_mA
        self.motor.torque_scale = params.torque_scale
        self.jaw_motor.current_limits_mA = (params.jaw_current_limit_mA,)
        mujoco.mj_setConst(m, self._scratch)
        self._params = params

    def _set_payload(self, params: ArmParams) -> None:
        """The load held in the jaws: its mass, a solid sphere's inertia (a point mass at no
        volume) and its buoyancy (`set_params` has refused one on a model that holds none)."""
        if self._payload is None:
            return
        m = self.model
        body, buoy = self._payload
        radius = (3.0 * params.payload_volume_l * 1e-3 / (4.0 * math.pi)) ** (1.0 / 3.0)
        m.body_mass[body] = params.payload_kg
        m.body_inertia[body] = 0.4 * params.payload_kg * radius**2
        lift = params.payload_volume_l * 1e-3 * params.water_density
        m.body_mass[buoy] = lift / (m.body_gravcomp[buoy] - 1.0)

    def randomize(
        self, spread: float = 0.2, rng: np.random.Generator | int | None = None
    ) -> ArmParams:
        """Perturb friction, armature, masses and buoyancy by up to +-spread around
        ``nominal_params`` (the arm as built, so repeated calls do not compound), keeping the
        run-time torque scale, current limits and supply; draws from the arm's seeded
        generator unless rng is given. Applies the result and returns it."""
        now = self.params
        drawn = self.nominal_params.randomized(self._rng if rng is None else rng, spread)
        params = replace(
            drawn,
            torque_scale=now.torque_scale,
            current_limits_mA=now.current_limits_mA,
            jaw_current_limit_mA=now.jaw_current_limit_mA,
            supply_voltage=now.supply_voltage,
        )
        self.set_params(params)
        return params

    # -- state ------------------------------------------------------------------------------
    def coast(self, joints: Sequence[int]) -> None:
        """Until parameters are next applied, `joints` (indices in the joint order) keep their
        speed through any torque: their armature is made `COAST_ARMATURE`. A replay that puts
        them on a measured path at every tick wants that path between ticks, not their own
        dynamics."""
        n = self._n
        for j in joints:
            if not 0 <= int(j) < n:
                order = " ".join(self.arm_model.joint_letters)
                raise ValueError(f"joint index must be in 0..{n - 1} ({order}), got {j}")
            dof = self._dofadr[int(j)]
            self.model.dof_armature[dof] = COAST_ARMATURE
            # coasting: nothing to brake them either (at this armature neither would show)
            self.model.dof_frictionloss[dof] = 0.0
            self.model.dof_damping[dof] = 0.0
            self._base_damping[int(j)] = 0.0

    def reset(
        self,
        q: ArrayLike | None = None,
        qdot: ArrayLike | None = None,
        jaw_mm: float = 5.0,
    ) -> None:
        """Put the arm at rest (or moving at qdot) at q; default q is mid-range of each joint."""
        n = self._n
        limits = self.position_limits
        q_arr = limits.mean(axis=1) if q is None else self._vector(q, "q (rad)")
        qdot_arr = np.zeros(n) if qdot is None else self._vector(qdot, "qdot (rad/s)")
        check = np.ones(n, dtype=bool)
        if self._wrap is not None:
            check[self._wrap] = False
        tol = 1e-9
        outside = check & ((q_arr < limits[:, 0] - tol) | (q_arr > limits[:, 1] + tol))
        if np.any(outside):
            letters = self.arm_model.joint_letters
            bad = [
                f"{letters[i]}={q_arr[i]:.4f} not in [{limits[i, 0]:.4f}, {limits[i, 1]:.4f}]"
                for i in np.flatnonzero(outside)
            ]
            raise ValueError("reset position outside the joint ranges: " + ", ".join(bad))
        jaw = float(jaw_mm)
        lo_mm, hi_mm = self._jaw_range_m * 1000.0
        if not (math.isfinite(jaw) and lo_mm - tol <= jaw <= hi_mm + tol):
            raise ValueError(f"jaw_mm must be in [{lo_mm:.1f}, {hi_mm:.1f}] mm, got {jaw_mm}")

        d = self.data
        mujoco.mj_resetData(self.model, d)
        d.qpos[:n] = q_arr
        d.qpos[n] = jaw / 1000.0
        d.qvel[:n] = qdot_arr
        self._damping[: n + 1] = self._base_damping
        self._command_mA[:] = 0.0
        mujoco.mj_forward(self.model, d)
        self._update_outputs()

    def step(
        self,
        currents_mA: ArrayLike,
        jaw_current_mA: float = 0.0,
        n: int = 1,
        work: FloatArray | None = None,
    ) -> None:
        """Hold the commanded currents (the joints in order, then the jaw; mA) for n physics
        steps.

        `work` (one float64 entry per joint), if given, has |tau qdot| added to it at the end
        of every physics step, the values `tau` and `qdot` read there: the energy at the
        physics rate (the back-EMF varies the torque within a held command) for the cost of
        one call, not n (tests/test_arm_model.py checks it to the bit against n single
        steps)."""
        cmd = self._vector(currents_mA, "currents_mA")
        jaw = float(jaw_current_mA)
        if not math.isfinite(jaw):
            raise ValueError(f"jaw_current_mA must be finite, got {jaw_current_mA}")
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"n (physics steps) must be an integer >= 1, got {n!r}")
        nj = self._n
        na = nj + 1
        if work is not None and (
            not isinstance(work, np.ndarray) or work.shape != (nj,) or work.dtype != np.float64
        ):
            raise ValueError(f"work must be a float64 array of {nj} entries (one per joint)")
        command = self._command_mA
        command[:nj] = cmd
        command[nj] = jaw

        c = self._constants()
        # A handful of actuators: plain floats (IEEE doubles, the same arithmetic as
        # numpy's) are faster than arrays at this size.
        v = c.v
        thr_hi, thr_lo, f_cur = [], [], []  # the supply's limits on speed, either way; torque
        for x, lim, r, ke, k in zip(command.tolist(), *c.per_actuator, strict=True):
            a = min(max(x, -lim), lim) / 1000.0
            ra = r * a
            thr_hi.append((v - ra) / ke)
            thr_lo.append((-v - ra) / ke)
            f_cur.append(k * a)
        f_volt, base, d_volt = c.f_volt, c.base, c.d_volt

        m, d = self.model, self.data
        qvel, ctrl, damping = self._qvel, self._ctrl, self._damping
        regime = [2] * na  # forces a write of every actuator in the first step
        actuators = range(na)
        mj_step = mujoco.mj_step
        if work is not None:
            # `_update_outputs`'s clamp and torque, in its order of operations, per joint
            sums = work.tolist()
            commands = self._command_mA[:nj].tolist()
            clamp = list(
                zip(
                    commands,
                    c.backemf_f[:nj],
                    c.supply_f[:nj],
                    c.resistance_f[:nj],
                    c.limit_f[:nj],
                    c.neg_limit_f[:nj],
                    c.torque_f[:nj],
                    strict=True,
                )
            )
            joints = range(nj)
        w = qvel.tolist()  # the speeds each physics step's regimes are chosen from
        for _ in range(int(n)):
            for j in actuators:
                wj = w[j]
                new = 1 if wj > thr_hi[j] else (-1 if wj < thr_lo[j] else 0)
                if new != regime[j]:
                    regime[j] = new
                    if new == 0:
                        ctrl[j] = f_cur[j]
                        damping[j] = base[j]
                    else:
                        ctrl[j] = new * f_volt[j]
                        damping[j] = d_volt[j]
            mj_step(m, d)
            w = qvel.tolist()  # the speeds after it: its work, and the next step's regimes
            if work is not None:
                for j in joints:
                    cm, ke, sv, r, hi_lim, lo_lim, kt = clamp[j]
                    wj = w[j]
                    emf = ke * wj
                    hi = min(hi_lim, 1000.0 * (sv - emf) / r)
                    lo = max(lo_lim, 1000.0 * (-sv - emf) / r)
                    sums[j] += abs(kt * min(max(cm, lo), hi) / 1000.0 * wj)
        if work is not None:
            work[:] = sums
        damping[:na] = self._base_damping  # the model between calls is the nominal one
        # The currents and torques are worked out when read (a replay never reads them), from
        # the speeds and settings at this moment.
        self._outputs_pending = (c, qvel[:na].copy())

    def _constants(self) -> _StepConstants:
        """The motors' constants for `step`, rebuilt only when a setting changed (checked by
        value: the limits and the torque scale may be edited in place)."""
        motors = (self.motor, self.jaw_motor)
        key = (*(mm.state_key() for mm in motors), self._base_damping.tobytes())
        c = self._step_constants
        if (
            c is None
            or c.motors[0] is not motors[0]
            or c.motors[1] is not motors[1]
            or c.key != key
        ):
            c = self._step_constants = _StepConstants.of(motors, self._base_damping, key)
        return c

    def _outputs(self) -> None:
        pending = self._outputs_pending
        if pending is not None:
            self._outputs_pending = None
            self._update_outputs(*pending)

    def _update_outputs(self, c: _StepConstants | None = None, w: FloatArray | None = None) -> None:
        """Current drawn and torque delivered, from the motor model at the final speeds."""
        self._outputs_pending = None
        c = self._constants() if c is None else c
        emf = c.backemf * (self.data.qvel[: self._n + 1] if w is None else w)
        hi = np.minimum(c.limit, 1000.0 * (c.supply - emf) / c.resistance)
        lo = np.maximum(c.neg_limit, 1000.0 * (-c.supply - emf) / c.resistance)
        # Past the no-load speed lo > hi; the back-EMF bound wins (the motor brakes).
        current = np.minimum(np.maximum(self._command_mA, lo), hi)
        self._current_mA[:] = current
        self._tau[:] = c.torque * current / 1000.0

    def _vector(self, values: ArrayLike, name: str) -> FloatArray:
        array = np.asarray(values, dtype=np.float64)
        n = self._n
        if array.shape != (n,):
            order = " ".join(self.arm_model.joint_letters)
            raise ValueError(
                f"{name} needs {n} values in joint order {order}, got shape {array.shape}"
            )
        # a NaN or an infinity anywhere makes the sum one (cheaper than np.isfinite at this
        # size); a sum that overflowed is checked entry by entry
        if not math.isfinite(sum(array.tolist())) and not np.all(np.isfinite(array)):
            raise ValueError(f"{name} must be finite, got {array.tolist()}")
        return array

    @property
    def q(self) -> FloatArray:
        """Joint angles (rad) as the arm reports them."""
        q = self.data.qpos[: self._n].copy()
        if self._wrap is not None:
            q[self._wrap] %= 2.0 * math.pi
        return q

    @property
    def qdot(self) -> FloatArray:
        return self.data.qvel[: self._n].copy()

    @property
    def tau(self) -> FloatArray:
        """Torque the motors delivered at the end of the last step (N m)."""
        self._outputs()
        return self._tau[: self._n].copy()

    @property
    def current_mA(self) -> FloatArray:
        """Current drawn after the limit and back-EMF clamp (mA)."""
        self._outputs()
        return self._current_mA[: self._n].copy()

    @property
    def jaw_current_mA(self) -> float:
        self._outputs()
        return float(self._current_mA[self._n])

    @property
    def jaw_force(self) -> float:
        """Force the jaw motor delivered along its slide (N)."""
        self._outputs()
        return float(self._tau[self._n])

    @property
    def jaw_mm(self) -> float:
        return float(self.data.qpos[self._n] * 1000.0)

    @property
    def jaw_velocity_mm_s(self) -> float:
        return float(self.data.qvel[self._n] * 1000.0)

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def dt(self) -> float:
        return float(self.model.opt.timestep)

    @property
    def torque_scale(self) -> FloatArray:
        """Fraction of nominal torque per joint; edit in place or assign."""
        return self.motor.torque_scale

    @torque_scale.setter
    def torque_scale(self, scale: Sequence[float] | ArrayLike) -> None:
        self.motor.torque_scale = scale

    @property
    def current_limits_mA(self) -> FloatArray:
        """Symmetric current limits per joint (mA); assign to change (CURRENT_LIMITS packet)."""
        return self.motor.current_limits_mA

    @current_limits_mA.setter
    def current_limits_mA(self, limits: Sequence[float] | ArrayLike) -> None:
        self.motor.current_limits_mA = limits

    @property
    def jaw_current_limit_mA(self) -> float:
        return float(self.jaw_motor.current_limits_mA[0])

    @jaw_current_limit_mA.setter
    def jaw_current_limit_mA(self, limit: float) -> None:
        self.jaw_motor.current_limits_mA = (limit,)

    @property
    def position_limits(self) -> FloatArray:
        """[min, max] per joint (rad): the MJCF's ranges (the factory ones; the Alpha's B is
        0..2pi)."""
        return self.model.jnt_range[: self._n].copy()

    @property
    def jaw_limits_mm(self) -> tuple[float, float]:
        return float(self._jaw_range_m[0] * 1000.0), float(self._jaw_range_m[1] * 1000.0)

    # -- kinematics and statics -------------------------------------------------------------
    def end_effector_pose(self) -> tuple[float, float, float, float, float, float]:
        """Tool centre point in the base frame: x, y, z (mm), roll, pitch, yaw (rad, URDF
        rpy convention R = Rz(yaw) Ry(pitch) Rx(roll))."""
        mujoco.mj_kinematics(self.model, self.data)
        return _pose(self.data.site_xpos[self._tcp], self.data.site_xmat[self._tcp])

    def pose_at(self, q: ArrayLike) -> tuple[float, float, float, float, float, float]:
        """`end_effector_pose()` with the joints at q (rad); the arm is not moved."""
        s = self._at(q)
        return _pose(s.site_xpos[self._tcp], s.site_xmat[self._tcp])

    def tcp_kinematics(self, q: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The tool centre point with the joints at q (rad), for inverse kinematics:
        position (m), rotation matrix (columns: the tool axes in the base frame), and the
        position (m/rad) and rotation (rad/rad) Jacobians, 3 x n each, in the base frame."""
        s = self._at(q)
        n = self._n
        jacp = np.zeros((3, self.model.nv))
        jacr = np.zeros((3, self.model.nv))
        mujoco.mj_jacSite(self.model, s, jacp, jacr, self._tcp)
        rot = s.site_xmat[self._tcp].reshape(3, 3).copy()
        return s.site_xpos[self._tcp].copy(), rot, jacp[:, :n].copy(), jacr[:, :n].copy()

    def skeleton(self) -> FloatArray:
        """World positions (m) of the base, each moving link's origin and the tool centre point:
        a polyline that draws the arm (recordings)."""
        mujoco.mj_kinematics(self.model, self.data)
        points = [np.zeros(3)]
        points.extend(self.data.xpos[i] for i in self._link_ids)
        points.append(self.data.site_xpos[self._tcp])
        return np.array(points, dtype=float)

    def _at(self, q: ArrayLike) -> mujoco.MjData:
        scratch = self._scratch
        n = self._n
        scratch.qpos[:n] = self._vector(q, "q (rad)")
        scratch.qpos[n] = self.data.qpos[n]
        scratch.qvel[:] = 0.0
        mujoco.mj_forward(self.model, scratch)
        return scratch

    def gravity_torque(self, q: ArrayLike) -> FloatArray:
        """Torque gravity and buoyancy exert on each joint at rest at q (N m); a controller
        holds the arm still by applying its negative."""
        return self._gravity(self._vector(q, "q (rad)"))

    def gravity_torques(self, qs: ArrayLike) -> FloatArray:
        """`gravity_torque` at each row of `qs` (poses x joints): one check of the whole
        array, not one per pose. Why: a sweep over hundreds of poses per arm (the envelope's
        worst static load) was most of the cost of drawing arms."""
        poses = np.asarray(qs, dtype=np.float64)
        n = self._n
        if poses.ndim != 2 or poses.shape[1] != n or not np.all(np.isfinite(poses)):
            order = " ".join(self.arm_model.joint_letters)
            raise ValueError(f"poses need finite rows of {n} values ({order}), got {poses.shape}")
        return np.array([self._gravity(q) for q in poses]).reshape(poses.shape)

    def _gravity(self, q: FloatArray) -> FloatArray:
        """gravity_torque at a checked q: only MuJoCo's position and velocity stages, where
        gravity compensation (the buoyancy) and the bias forces are computed, at zero speed
        (the full forward step gives the same figures, to the bit, at twice the cost)."""
        scratch = self._scratch
        n = self._n
        scratch.qpos[:n] = q
        scratch.qpos[n] = self.data.qpos[n]
        scratch.qvel[:] = 0.0
        mujoco.mj_fwdPosition(self.model, scratch)
        mujoco.mj_fwdVelocity(self.model, scratch)
        return scratch.qfrc_gravcomp[:n] - scratch.qfrc_bias[:n]

    def mass_matrix(self, q: ArrayLike) -> FloatArray:
        """Joint-space inertia of the joints at q, armature included (kg m^2)."""
        s = self._at(q)
        n = self._n
        full = np.zeros((self.model.nv, self.model.nv))
        mujoco.mj_fullM(self.model, s, full)
        return full[:n, :n].copy()


class Alpha5Arm(MotorArm):
    """Four joints (E D C B) and the jaw, stepped with currents; state in the arm's units."""

    def __init__(
        self, params: ArmParams | None = None, dt: float = 0.002, seed: int | None = None
    ) -> None:
        check_dt(dt)
        p = params if params is not None else ArmParams()
        super().__init__(
            mujoco.MjModel.from_xml_path(str(MODEL_PATH)),
            ALPHA5,
            MotorModel(p.motors, p.supply_voltage, p.current_limits_mA, p.torque_scale),
            MotorModel(p.jaw_motor, p.supply_voltage, (p.jaw_current_limit_mA,)),
            dt,
            seed,
            LINK_BODIES,
        )
        self._init_params(p, ("m3_inline", *LINK_BODIES))
        self.reset()


def _pose(pos_m: ArrayLike, xmat: ArrayLike) -> tuple[float, float, float, float, float, float]:
    pos = np.asarray(pos_m) * 1000.0
    rot = np.asarray(xmat).reshape(3, 3)
    roll = math.atan2(rot[2, 1], rot[2, 2])
    pitch = math.atan2(-rot[2, 0], math.hypot(rot[0, 0], rot[1, 0]))
    yaw = math.atan2(rot[1, 0], rot[0, 0])
    return float(pos[0]), float(pos[1]), float(pos[2]), roll, pitch, yaw
