"""Model predictive control baseline: the paper's cost on a per-joint model of the arm.

Cost (paper, section V): J = sum_k ||q_ref - q_k||^2_Q + ||qdot_k||^2_Qv + ||du_k||^2_R,
with du_k = u_k - u_{k-1} (u_{-1} the current last sent) and Qv = 0 by default.

Prediction model, per joint j (decoupled; what it uses and why):
    J_j qddot = k_j u - b_j qdot - f_j tanh(qdot / eps) + g_j(q) + d_j
- J_j: the diagonal of the nominal MJCF's joint-space inertia at the measured pose (armature +
  link inertia), held over the horizon; b_j, f_j: nominal viscous and Coulomb friction
  (`ArmParams`); k_j: output torque per amp of the shared motor model; g_j: gravity and
  buoyancy torque of the nominal model, linearised at the measured pose (couples D and C);
  d_j: a torque disturbance estimated from one-step prediction errors (offset-free MPC), the
  only way the controller learns about the simulator's hidden perturbations.
- Discretisation: exact zero-order hold of the linear part over the control period, with the
  Coulomb term taken at the end of the interval (implicit, so its steep slope near zero speed
  cannot make the prediction unstable the way an explicit step would).
Constraints: current limits as bounds on u; the back-EMF envelope -V <= R u_k + Ke qdot_{k+1}
<= V (linear; the speed at the end of each held interval must be one the supply can sustain
at that current); joint limits on predicted angles k >= 1 only, softened by slacks with an
L1 + L2 penalty. Solved by CasADi's sqpmethod with qrqp, warm-started from the shifted
previous solution, with a capped number of SQP iterations so the worst case is bounded.

One controller for the Alpha 5 (E D C B) and the Bravo 7 (G F E D C B): the model's numbers
come from its twin (`reach_sim_bridge.model.arms.arm_twin`: the Alpha's with `ArmParams`, the
Bravo's MJCF), the weights' defaults per model (`DEFAULT_WEIGHTS`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

import numpy as np

from protocol.extras import needs_extra
from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver.controllers import ControlState, drives, engineered
from reach_sim_bridge.model.params import ArmParams

with needs_extra("the mpc controller", "mpc"):  # CasADi, and MuJoCo for the nominal model
    import casadi as ca
    import mujoco

    from reach_sim_bridge.model.arms import arm_twin

SOLVERS = ("ipopt", "sqp-qrqp", "sqp-osqp", "sqp-qpoases")
Weights = tuple[float, ...]  # one per joint, in the model's order (empty: the model's default)


@dataclass(frozen=True)
class DefaultWeights:
    """One model's default weights per joint in its order: Q, Qv and R (`MPCConfig`)."""

    q_weight: Weights
    qdot_weight: Weights
    r_weight: Weights


#: Default weights per model (`ArmModel.name`).
DEFAULT_WEIGHTS: Mapping[str, DefaultWeights] = MappingProxyType(
    {
        # horizon and R chosen by tools/tune_mpc.py (docs/results.md, "MPC tuning")
        ALPHA5.name: DefaultWeights(
            (100.0, 100.0, 100.0, 100.0), (0.0, 0.0, 0.0, 0.0), (100.0, 100.0, 100.0, 1000.0)
        ),
        # The virtual Bravo 7 (tuned on its twin in fresh water, not on a real arm;
        # tests/test_mpc.py): heavily damped joints that stick, so current changes cost
        # less (R) and speed is weighed (Qv) against the overshoot the Alpha's weights gave
        # (5-13 % on 0.2-0.45 rad steps of every joint; these: under 3 %).
        BRAVO7.name: DefaultWeights((100.0,) * 6, (30.0,) * 6, (10.0,) * 6),
    }
)


def _weights(value: Any, name: str, model: ArmModel) -> Weights:
    """One value for every joint of `model`, or one per joint (ValueError naming them)."""
    n = model.n_joints
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.size == 1:
        arr = np.repeat(arr, n)
    if arr.size != n or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        order = " ".join(model.joint_letters)
        raise ValueError(f"{name} needs {n} finite non-negative values ({order}), got {value!r}")
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class MPCConfig:
    """Weights (Q per rad^2, Qv per (rad/s)^2, R per A^2 of current change; per joint of
    `model`, its `DEFAULT_WEIGHTS` unless given) and solver knobs. `params` is the Alpha 5
    twin's (the Bravo 7's twin is its MJCF: other parameters are refused)."""

    horizon: int = 20
    rate_hz: float = 20.0
    q_weight: Weights = ()
    qdot_weight: Weights = ()
    r_weight: Weights = ()
    bound_weight: float = 1e4  # per rad^2 of predicted joint-limit violation (and per rad L1)
    friction_smoothing: float = 0.02  # rad/s: eps of the tanh Coulomb model
    disturbance_gain: float = 0.3  # 0 disables the offset-free disturbance estimate
    max_sqp_iter: int = 4
    solver: str = "ipopt"  # see SOLVERS and docs/results.md for measured solve times
    time_fraction: float = 0.8  # ipopt's wall-time cap as a fraction of the control period
    params: ArmParams = field(default_factory=ArmParams)
    model: ArmModel = ALPHA5

    def __post_init__(self) -> None:
        defaults = DEFAULT_WEIGHTS[self.model.name]
        for name in ("q_weight", "qdot_weight", "r_weight"):
            value = getattr(self, name)
            if isinstance(value, tuple) and not value:
                value = getattr(defaults, name)
            object.__setattr__(self, name, _weights(value, name, self.model))
        if self.model is not ALPHA5 and self.params != ArmParams():
            arm_twin(self.model, self.params)  # refused: no parameters describe it
        if self.horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {self.horizon}")
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"rate_hz must be positive, got {self.rate_hz}")
        if not self.friction_smoothing > 0:
            raise ValueError("friction_smoothing must be > 0 rad/s")
        if not 0 <= self.disturbance_gain <= 1:
            raise ValueError("disturbance_gain must be in [0, 1]")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if not 0 < self.time_fraction <= 1:
            raise ValueError("time_fraction must be in (0, 1]")
        if self.max_sqp_iter < 1:
            raise ValueError("max_sqp_iter must be >= 1")

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz


class NominalModel:
    """The prediction model's numbers, from the model's twin and motor model (no
    perturbation): the Alpha 5 with `params`, the Bravo 7 as its MJCF describes it."""

    def __init__(self, params: ArmParams, model: ArmModel = ALPHA5) -> None:
        self.n = n = model.n_joints
        self.arm = arm_twin(model, params if model is ALPHA5 else None)
        motor = self.arm.motor
        self.torque_per_amp = motor.torque_per_amp * motor.torque_scale
        self.backemf = motor.backemf_per_speed
        self.resistance = motor.resistance
        self.supply = motor.supply_voltage
        self.current_limit_a = motor.current_limits_mA / 1000.0
        # the joints' viscous and Coulomb friction, as the twin steps them
        self.damping = np.asarray(self.arm.model.dof_damping[:n], dtype=float).copy()
        self.coulomb = np.asarray(self.arm.model.dof_frictionloss[:n], dtype=float).copy()
        self.position_limits = self.arm.position_limits
        self._data = mujoco.MjData(self.arm.model)
        self._full = np.zeros((self.arm.model.nv, self.arm.model.nv))

    def inertia(self, q: np.ndarray) -> np.ndarray:
        """Diagonal of the joint-space inertia at q (kg m^2), armature included."""
        d, n = self._data, self.n
        d.qpos[:n] = q
        d.qpos[n] = 0.005  # the jaws 5 mm open
        mujoco.mj_forward(self.arm.model, d)
        mujoco.mj_fullM(self.arm.model, d, self._full)
        return np.diag(self._full)[:n].copy()

    def gravity(self, q: np.ndarray, step: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
        """Gravity-buoyancy torque at q and its Jacobian (central differences)."""
        n = self.n
        g0 = self.arm.gravity_torque(q)
        jac = np.zeros((n, n))
        for i in range(n):
            dq = np.zeros(n)
            dq[i] = step
            jac[:, i] = (self.arm.gravity_torque(q + dq) - self.arm.gravity_torque(q - dq)) / (
                2 * step
            )
        return g0, jac


def zoh_coefficients(inertia: np.ndarray, damping: np.ndarray, period: float) -> np.ndarray:
    """Per joint (phi_v, gam_v, phi_q, gam_q) of the exact ZOH step of J qdd = tau - b qd.

    qd+ = phi_v qd + gam_v tau;  q+ = q + phi_q qd + gam_q tau.
    """
    a = damping / inertia
    e = np.exp(-a * period)
    phi_v = e
    gam_v = (1 - e) / damping
    phi_q = (1 - e) / a
    gam_q = (period - phi_q) / damping
    return np.stack([phi_v, gam_v, phi_q, gam_q])


@dataclass
class _Layout:
    n: int  # stages (the horizon)
    joints: int = 4

    @property
    def stage(self) -> int:  # u, q, qdot, slack: one per joint each
        return 4 * self.joints

    def _part(self, k: int, i: int) -> slice:
        start = k * self.stage + i * self.joints
        return slice(start, start + self.joints)

    def u(self, k: int) -> slice:
        return self._part(k, 0)

    def q(self, k: int) -> slice:  # predicted state k+1
        return self._part(k, 1)

    def v(self, k: int) -> slice:
        return self._part(k, 2)

    def s(self, k: int) -> slice:
        return self._part(k, 3)

    @property
    def size(self) -> int:
        return self.n * self.stage


@dataclass(frozen=True)
class Prediction:
    """The optimal plan of the last solve: currents u_k (A) and predicted states k = 1..N."""

    u: np.ndarray  # (N, joints) A
    q: np.ndarray  # (N, joints) rad
    qdot: np.ndarray  # (N, joints) rad/s
    success: bool


class MPCController:
    """Receding-horizon current commands (mA, in the arm's joint order) for a joint-space
    target."""

    def __init__(self, config: MPCConfig | None = None) -> None:
        self.config = config or MPCConfig()
        self.model = NominalModel(self.config.params, self.config.model)
        self._layout = _Layout(self.config.horizon, self.model.n)
        self._solver, self._lbg, self._ubg = self._build()
        self.solve_times: list[float] = []
        self.failures = 0
        self.reset()

    # -- problem ------------------------------------------------------------------------------
    def _build(self) -> tuple[ca.Function, np.ndarray, np.ndarray]:
        c, m, lay = self.config, self.model, self._layout
        n, j = c.horizon, m.n
        w = ca.SX.sym("w", lay.size)
        # parameters: q0, v0, qref, uprev, zoh(4 x j), g0, G(j x j), d
        p = ca.SX.sym("p", 4 * j + 4 * j + j + j * j + j)
        q0, v0, qref, uprev = p[0:j], p[j : 2 * j], p[2 * j : 3 * j], p[3 * j : 4 * j]
        zoh = ca.reshape(p[4 * j : 8 * j], 4, j)  # rows: phi_v, gam_v, phi_q, gam_q
        g0 = p[8 * j : 9 * j]
        gjac = ca.reshape(p[9 * j : 9 * j + j * j], j, j)
        dist = p[9 * j + j * j : 10 * j + j * j]
        k_t = ca.DM(m.torque_per_amp)
        fc = ca.DM(m.coulomb)
        ke, res, vsup = ca.DM(m.backemf), ca.DM(m.resistance), m.supply
        qw, vw, rw = ca.DM(c.q_weight), ca.DM(c.qdot_weight), ca.DM(c.r_weight)
        eps = c.friction_smoothing

        cost: ca.SX = ca.SX(0)
        g: list[ca.SX] = []
        lbg: list[float] = []
        ubg: list[float] = []
        q_prev, v_prev, u_prev = q0, v0, uprev
        for k in range(n):
            u, q, v, s = w[lay.u(k)], w[lay.q(k)], w[lay.v(k)], w[lay.s(k)]
            tau = k_t * u + g0 + ca.mtimes(gjac, q_prev - q0) + dist - fc * ca.tanh(v / eps)
            v_next = zoh[0, :].T * v_prev + zoh[1, :].T * tau
            q_next = q_prev + zoh[2, :].T * v_prev + zoh[3, :].T * tau
            g += [v - v_next, q - q_next]
            lbg += [0.0] * 2 * j
            ubg += [0.0] * 2 * j
            emf = res * u + ke * v  # back-EMF envelope at the end of the held interval
            g.append(emf)
            lbg += [-vsup] * j
            ubg += [vsup] * j
            lo = ca.DM(m.position_limits[:, 0])
            hi = ca.DM(m.position_limits[:, 1])
            g += [q + s - lo, q - s - hi]  # soft joint bounds: q >= lo - s, q <= hi + s
            lbg += [0.0] * j + [-ca.inf] * j
            ubg += [ca.inf] * j + [0.0] * j
            e = qref - q
            du = u - u_prev
            cost += ca.sum1(qw * e**2) + ca.sum1(vw * v**2) + ca.sum1(rw * du**2)
            cost += c.bound_weight * (ca.sum1(s**2) + ca.sum1(s))
            q_prev, v_prev, u_prev = q, v, u
        nlp = {"x": w, "p": p, "f": cost, "g": ca.vertcat(*g)}
        opts: dict[str, Any]
        if c.solver == "ipopt":
            plugin = "ipopt"
            opts = {
                "print_time": False,
                "error_on_fail": False,
                "ipopt": {
                    "print_level": 0,
                    "sb": "yes",
                    "max_iter": 100,
                    "warm_start_init_point": "yes",
                    "tol": 1e-6,
                    "mu_strategy": "adaptive",
                    "max_wall_time": c.time_fraction * c.period,
                },
            }
        else:
            plugin = "sqpmethod"
            qp = c.solver.removeprefix("sqp-")
            qp_opts: dict[str, Any] = {"error_on_fail": False}
            if qp == "qrqp":
                qp_opts.update(print_iter=False, print_header=False)
            elif qp == "qpoases":
                qp_opts.update(printLevel="none", sparse=True)
            elif qp == "osqp":
                qp_opts.update(
                    warm_start_primal=True,
                    warm_start_dual=True,
                    osqp={
                        "verbose": False,
                        "eps_abs": 1e-5,
                        "eps_rel": 1e-5,
                        "max_iter": 4000,
                        "polish": True,
                    },
                )
            opts = {
                "qpsol": qp,
                "qpsol_options": qp_opts,
                "max_iter": c.max_sqp_iter,
                "print_header": False,
                "print_iteration": False,
                "print_status": False,
                "print_time": False,
                "error_on_fail": False,
                "convexify_strategy": "regularize",
            }
        # CasADi's JIT (compiler="shell") was measured no faster here: ipopt's own work
        # dominates, so the functions stay interpreted (and no compiler is needed).
        bounds = np.array(lbg, dtype=float), np.array(ubg, dtype=float)
        return ca.nlpsol("mpc", plugin, nlp, opts), *bounds

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lay, m = self._layout, self.model
        lbx = np.full(lay.size, -np.inf)
        ubx = np.full(lay.size, np.inf)
        for k in range(lay.n):
            lbx[lay.u(k)] = -m.current_limit_a
            ubx[lay.u(k)] = m.current_limit_a
            lbx[lay.s(k)] = 0.0
        return lbx, ubx

    # -- controller interface -------------------------------------------------------------------
    def reset(self) -> None:
        self._w0: np.ndarray | None = None
        self._lam_g: np.ndarray | None = None
        self._lam_x: np.ndarray | None = None
        self._u_prev = np.zeros(self.model.n)
        self._dist = np.zeros(self.model.n)
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._lbx, self._ubx = self._bounds()
        self.prediction: Prediction | None = None

    @property
    def disturbance(self) -> np.ndarray:
        """Current estimate of the unmodelled joint torque (N m), in the arm's joint order."""
        return self._dist.copy()

    def _update_disturbance(self, q: np.ndarray, v: np.ndarray) -> None:
        """Torque that explains the last period's speed change beyond what the model predicted."""
        if self._last is None or self.config.disturbance_gain == 0:
            return
        q_prev, v_prev, u_prev, zoh, g_prev = self._last
        fc = self.model.coulomb * np.tanh(v / self.config.friction_smoothing)
        model_tau = self.model.torque_per_amp * u_prev + g_prev - fc
        implied = (v - zoh[0] * v_prev) / zoh[1]
        innovation = implied - model_tau - self._dist
        self._dist = self._dist + self.config.disturbance_gain * innovation

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q = np.asarray(state.q, dtype=float)
        v = np.asarray(state.qdot, dtype=float)
        qref = np.asarray(target, dtype=float)
        n = self.model.n
        if q.shape != (n,) or v.shape != (n,) or qref.shape != (n,):
            order = " ".join(self.config.model.joint_letters)
            raise ValueError(f"state.q, state.qdot and target must each be {n} values ({order})")
        self._update_disturbance(q, v)
        c, m, lay = self.config, self.model, self._layout
        inertia = m.inertia(q)
        zoh = zoh_coefficients(inertia, m.damping, c.period)
        g0, gjac = m.gravity(q)
        p = np.concatenate(
            [
                q,
                v,
                qref,
                self._u_prev,
                zoh.reshape(-1, order="F"),
                g0,
                gjac.reshape(-1, order="F"),
                self._dist,
            ]
        )
        w0 = self._warm_start(q, v)
        args: dict[str, Any] = dict(
            x0=w0, p=p, lbx=self._lbx, ubx=self._ubx, lbg=self._lbg, ubg=self._ubg
        )
        if self._lam_g is not None:
            args.update(lam_g0=self._lam_g, lam_x0=self._lam_x)
        t0 = time.perf_counter()
        sol = self._solver(**args)
        self.solve_times.append(time.perf_counter() - t0)
        if not self._solver.stats().get("success", False):
            self.failures += 1  # the iterate is still used: the wall-time cap ends a solve
        w = np.asarray(sol["x"]).reshape(-1)
        n = c.horizon
        self.prediction = Prediction(
            u=np.array([w[lay.u(k)] for k in range(n)]),
            q=np.array([w[lay.q(k)] for k in range(n)]),
            qdot=np.array([w[lay.v(k)] for k in range(n)]),
            success=bool(self._solver.stats().get("success", False)),
        )
        u = np.clip(w[lay.u(0)], -m.current_limit_a, m.current_limit_a)
        self._w0 = w
        self._lam_g = np.asarray(sol["lam_g"]).reshape(-1)
        self._lam_x = np.asarray(sol["lam_x"]).reshape(-1)
        self._last = (q, v, u.copy(), zoh, g0)
        self._u_prev = u
        return u * 1000.0

    def _warm_start(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        lay = self._layout
        if self._w0 is None:
            w = np.zeros(lay.size)
            for k in range(lay.n):
                w[lay.q(k)] = q
                w[lay.v(k)] = v
            return w
        w = np.empty(lay.size)  # shift by one stage, repeat the last
        w[: -lay.stage] = self._w0[lay.stage :]
        w[-lay.stage :] = self._w0[-lay.stage :]
        return w

    def solve_time_stats(self) -> dict[str, float]:
        """Median, 99th percentile and max solve time (s) since construction, how many
        solves took longer than the control period, and how many ended unconverged."""
        t = np.asarray(self.solve_times)
        if t.size == 0:
            return {
                "p50": math.nan,
                "p99": math.nan,
                "max": math.nan,
                "n": 0,
                "over_period": 0,
                "unconverged": 0,
            }
        return {
            "p50": float(np.percentile(t, 50)),
            "p99": float(np.percentile(t, 99)),
            "max": float(t.max()),
            "n": int(t.size),
            "over_period": int(np.sum(t > self.config.period)),
            "unconverged": self.failures,
        }


@drives(ALPHA5, BRAVO7)
@engineered
def make_controller(*, model: ArmModel = ALPHA5, **kwargs: Any) -> MPCController:
    """MPC on a nominal model; engineered, no learning.

    Entry point `mpc`: the paper's cost on a per-joint model of the arm (`model`: the Alpha 5
    or the Bravo 7); keyword arguments are `MPCConfig` fields."""
    known = set(MPCConfig.__dataclass_fields__) - {"model"}
    unknown = set(kwargs) - known
    if unknown:
        raise ValueError(f"unknown MPC options {sorted(unknown)}; known: {sorted(known)}")
    return MPCController(replace(MPCConfig(model=model), **kwargs))
