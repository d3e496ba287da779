"""A model-based controller tuned by the lambda rule: each joint follows a speed reference
proportional to its error, with the closed loop made slower than the loop's dead time.

Why it exists (docs/robustness.md, "`lambda`: a controller told the arm"): the distilled actor
(`ddpg-distilled`) and the MPC were both made for the nominal arm, and on the arms of the
uncertainty envelope they overshoot by what they do not know: the loop's latency, a joint's
inertia and friction. This controller is the other way round: it knows nothing but a twin of
the arm (`ArmParams`, nominal or fitted by `tools/identify.py`) and the loop's latency, and
derives every gain from them, so it tells how much of the overshoot knowing the arm removes.

Every control period (T = 1 / rate_hz):

1. **Observe.** The twin (its MuJoCo model, motors and friction) is run from the last
   estimate through the period under the commands that were in force, and a Kalman filter
   per joint (angle and speed) weighs that prediction against the readings: the readings'
   noise (`noise_q`, `noise_v`) against how far the twin may be wrong (`model_accel`, plus
   `twin_error` of the torques at work, over the joint's inertia). With an exact twin the
   filter averages the noise away at rest; with a rough one it follows the readings.
2. **Predict.** The twin is run on through the commands still in flight, to when the command
   computed now takes effect (`latency_periods` later): a Smith predictor, so the loop's dead
   time is only theta = T / 2, the hold's (with `predict` off, theta = (latency + 1/2) T).
3. **Act,** per joint j, on the predicted angle and speed:

       J_j     the twin's joint-space inertia at that pose (armature + links, diagonal)
       kv_j    = speed_gain * J_j / theta              speed feedback
       tau_j   = J_j / (b_j + kv_j)                    the speed loop's time constant
       K_j     = 1 / (lag_factor tau_j + (1 + lambda_factor) theta)     position gain, 1/s
       v_ref   = clip(K_j e_j, +-max_speed) + integral  e_j = aim - predicted angle
       torque  = b v_ref + M(q) a + c tanh(v_ref / friction_speed) g - G(q)
       a_j     = kv_j / J_j (v_ref_j - qdot_j)          the speed loop's acceleration

   with M the twin's mass matrix (the speed loops' accelerations through it, so a joint
   braking does not shove its neighbours through their goals), b, c the twin's viscous and
   Coulomb friction, G its gravity-buoyancy torque and g_j a gate that fades the friction
   feed-forward out within `friction_band` of the goal (at the goal it only pushed noise
   through the joint's stiction). The aim is the goal less the standoff (below).

An integrating process (speed to angle) behind a first-order lag tau and a dead time theta
closes without overshoot when the position loop's time constant 1/K exceeds the lag by a
factor (`lag_factor`: 2 keeps the lag's damping at 0.7 or more) and the dead time by a margin
(lambda tuning: `lambda_factor` theta). The speed feedback kv is kept to `speed_gain` of
J / theta, below where speed fed back through theta rings. A slow integral (`integral_gain`,
within `integral_band` of the goal, capped at `integral_cap`) adds to v_ref for what the twin
gets wrong (a static load, friction it underestimates).

**Standoff.** A joint at rest wanders with what is left of the readings' noise in the
estimate, and a goal approached head-on is crossed by that wander (a 2 % overshoot is 1 mrad
on a 0.05 rad step; the sensor's noise is 2-6 mrad). The law therefore aims short of the goal,
on the side it came from, by `standoff` times the estimate's standard deviation less what the
overshoot allowance (`overshoot_allowance` of the step) already covers, and never by more than
`standoff_band` of the settling band (docs/metrics.md). The standoff keeps its largest value
since the goal was set: an aim that closed in as the estimate firmed up at rest walked joints
held by friction across their goals in stick-slip late in the episode. The integral only
grows while the joint is still (`integral_speed`), so it answers a static load and not the
approach itself.

The twin is everything: with the arm's own parameters the law is measured to reach every
corner of the envelope tried, with the nominal arm's it reaches almost none of them
(docs/robustness.md). A twin comes from `tools/identify.py`.

On the Bravo 7 (`model=BRAVO7`) the twin is the Bravo's (`Bravo7Arm`: its MJCF's inertia,
damping and friction, in fresh water, or an arm file of its six joints: what it does not name
the MJCF's), the same law on its six joints G F E D C B; an arm file of another arm's joints
is refused naming the arm it fits.

    from policy.controllers.lambda_control import make_controller
    ctrl = make_controller(params="arm.json", latency_periods=1.0)
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from protocol.extras import needs_extra
from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver.controllers import ControlState, drives, engineered
from reach_driver.metrics import settling_band
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.twin import FittedTwin, read_twin

with needs_extra("the lambda controller", "sim"):  # its twin is the MuJoCo model
    from reach_sim_bridge.model.arms import arm_twin, nominal_params


@dataclass(frozen=True)
class LambdaConfig:
    """The tuning: every gain is derived from these and the twin (module docstring)."""

    rate_hz: float = 20.0  # control rate the loop runs at
    latency_periods: float = 0.0  # the loop's latency beyond the hold, in control periods
    lambda_factor: float = 3.0  # closed-loop margin over the dead time (x theta)
    lag_factor: float = 2.0  # 1/K >= 2 tau: the speed lag alone barely rings (damping >= 0.7)
    speed_gain: float = 0.25  # speed feedback, a fraction of J / theta
    max_speed: float = 1.0  # rad/s, under the motors' 1.18 rad/s no-load speed
    friction_speed: float = 0.2  # rad/s: width of the Coulomb feed-forward's tanh
    friction_band: float = 0.01  # rad: the Coulomb feed-forward fades out this near the goal
    integral_gain: float = 0.5  # 1/s^2: rad/s of reference per rad s of integrated error
    integral_band: float = 0.05  # rad: integrate only this close to the goal
    integral_cap: float = 0.05  # rad/s: most speed reference the integral may add
    integral_speed: float = 0.02  # rad/s: integrate only while the joint is this still
    noise_q: float = 0.002  # rad: the angle readings' noise (standard deviation)
    noise_v: float = 0.02  # rad/s: the speed readings' noise
    model_accel: float = 0.005  # rad/s^2: the twin's error floor, as white acceleration
    twin_error: float = 0.05  # the twin's relative error in the torques it models
    standoff: float = 5.0  # aim short of the goal by this many estimate deviations ...
    overshoot_allowance: float = 0.02  # ... less this fraction of the step ...
    standoff_band: float = 0.6  # ... and at most this fraction of the settling band
    predict: bool = True  # run the twin through the commands in flight (a Smith predictor)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"LambdaConfig.{f.name} must be finite and >= 0, got {value!r}")
        positive = (
            "rate_hz",
            "max_speed",
            "friction_speed",
            "friction_band",
            "integral_band",
            "noise_q",
            "noise_v",
        )
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"LambdaConfig.{name} must be > 0, got {getattr(self, name)!r}")

    @property
    def dead_time_s(self) -> float:
        """What the loop cannot see through: the hold's half period, and the latency unless
        the prediction removes it."""
        latency = 0.0 if self.predict else self.latency_periods
        return (latency + 0.5) / self.rate_hz


class LambdaController:
    """Currents (mA, in the arm's joint order) from the measured state, the goal and the twin
    (`ArmParams` on the Alpha 5, the MJCF's on the Bravo 7)."""

    def __init__(
        self,
        params: ArmParams | None = None,
        config: LambdaConfig | None = None,
        *,
        model: ArmModel = ALPHA5,
    ):
        self.model = model
        self.n = model.n_joints
        self.config = config or LambdaConfig()
        self.twin = arm_twin(model, params)
        #: the twin's parameters (the model's nominal ones unless given)
        self.params = self.twin.params
        self.current_limits_mA = np.asarray(self.twin.current_limits_mA, dtype=np.float64)
        #: N m per mA of each joint on the twin (its torque scale included)
        self.torque_per_mA = self.twin.motor.torque_per_amp * self.twin.torque_scale / 1000.0
        # the joints' own viscous and Coulomb friction, as the twin steps them
        dof = np.arange(self.n)
        self.damping = np.asarray(self.twin.model.dof_damping[dof], dtype=np.float64).copy()
        self.friction = np.asarray(self.twin.model.dof_frictionloss[dof], dtype=np.float64).copy()
        self.reset()

    @property
    def period_s(self) -> float:
        """The control period the gains and the prediction assume (the driver runs at it)."""
        return 1.0 / self.config.rate_hz

    def reset(self) -> None:
        """Forget the estimate, the integral and the commands sent."""
        self._integral = np.zeros(self.n)
        self._goal: np.ndarray | None = None
        self._q: np.ndarray | None = None  # the filter's estimate, now
        self._v = np.zeros(self.n)
        #: the estimate's covariance per joint ((angle, speed) x (angle, speed))
        self._cov = np.zeros((self.n, 2, 2))
        self._cov[:, 0, 0] = self.config.noise_q**2
        self._cov[:, 1, 1] = self.config.noise_v**2
        self._model_accel = np.full(self.n, self.config.model_accel)
        self._aim_side = np.zeros(self.n)  # +1 / -1: the side each joint comes from
        self._standoff = np.zeros(self.n)  # the largest standoff since the goal was set
        self._standoff_room = np.zeros((2, self.n))  # allowance, most standoff (rad)
        n = int(np.ceil(self.config.latency_periods)) + 2
        self._sent: deque[np.ndarray] = deque([np.zeros(self.n)] * n, maxlen=n)

    def _run_twin(
        self, q: np.ndarray, v: np.ndarray, t0: float, t1: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The twin's angles and speeds at t1 from (q, v) at t0 (s, relative to now), under
        the commands in force: the twin's own physics (coupling, motors, friction)."""
        cfg, dt = self.config, self.twin.dt
        # whole physics steps, a half rounded down: a step whose middle is t1 would run into
        # the command computed now (a latency of 1.5 periods is 37.5 steps at 20 Hz)
        steps = int(np.ceil((t1 - t0) / dt - 0.5 - 1e-9))
        if steps <= 0:
            return q, v
        # per physics step, which command is in force: the one sent latency_periods before
        # its middle (index -1: sent a period ago; 0, sent now, lands after t1)
        mid = t0 + (np.arange(steps) + 0.5) * dt
        sent = np.floor(mid * cfg.rate_hz - cfg.latency_periods + 1e-9).astype(int)
        if sent[-1] >= 0:
            raise ValueError("the twin cannot run past the command being computed")
        limits = self.twin.position_limits
        self.twin.reset(q=np.clip(q, limits[:, 0], limits[:, 1]), qdot=v)
        starts = [0, *(np.flatnonzero(np.diff(sent)) + 1).tolist(), steps]
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            m = int(sent[a])
            command = self._sent[m] if -m <= len(self._sent) else np.zeros(self.n)
            self.twin.step(command, n=b - a)
        return self.twin.q, self.twin.qdot

    def _filter(
        self, q_pred: np.ndarray, v_pred: np.ndarray, q_read: np.ndarray, v_read: np.ndarray
    ) -> None:
        """One Kalman update per joint: the twin's prediction against the readings. The
        covariance follows a constant-speed model driven by white acceleration of the twin's
        expected error (`_model_accel`, per joint)."""
        cfg = self.config
        t = 1.0 / cfg.rate_hz
        f = np.array([[1.0, t], [0.0, 1.0]])
        g = np.array([t * t / 2.0, t])
        cov = f @ self._cov @ f.T + (self._model_accel**2)[:, None, None] * np.outer(g, g)
        innovation = np.stack([q_read - q_pred, v_read - v_pred], axis=1)
        s = cov + np.diag([cfg.noise_q**2, cfg.noise_v**2])
        gain = cov @ np.linalg.inv(s)
        x = np.stack([q_pred, v_pred], axis=1) + np.einsum("jab,jb->ja", gain, innovation)
        self._q, self._v = x[:, 0].copy(), x[:, 1].copy()
        cov = (np.eye(2) - gain) @ cov
        self._cov = 0.5 * (cov + np.transpose(cov, (0, 2, 1)))

    @property
    def estimate_std(self) -> np.ndarray:
        """The angle estimate's standard deviation per joint (rad)."""
        return np.sqrt(self._cov[:, 0, 0])

    def gains(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K 1/s, kv N m s/rad) per joint at pose q."""
        return self._gains(np.diag(self.twin.mass_matrix(q)))

    def _gains(self, inertia: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        theta = cfg.dead_time_s
        kv = cfg.speed_gain * inertia / theta
        tau = inertia / (self.damping + kv)
        k = 1.0 / (cfg.lag_factor * tau + theta + cfg.lambda_factor * theta)
        return k, kv

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        cfg = self.config
        q = np.asarray(state.q, dtype=np.float64)
        qdot = np.asarray(state.qdot, dtype=np.float64)
        goal = np.asarray(target, dtype=np.float64)
        if q.shape != (self.n,) or qdot.shape != (self.n,) or goal.shape != (self.n,):
            order = " ".join(self.model.joint_letters)
            raise ValueError(
                f"state.q, state.qdot and target must each be {self.n} values ({order})"
            )
        period = 1.0 / cfg.rate_hz
        if self._q is None:
            self._q, self._v = q.copy(), qdot.copy()
        else:
            q_pred, v_pred = self._run_twin(self._q, self._v, -period, 0.0)
            self._filter(q_pred, v_pred, q, qdot)
        if self._goal is None or np.any(goal != self._goal):
            self._integral = np.zeros(self.n)
            self._goal = goal.copy()
            step = goal - self._q
            self._aim_side = np.sign(step)
            self._standoff = np.zeros(self.n)
            self._standoff_room = np.stack(
                [
                    cfg.overshoot_allowance * np.abs(step),
                    cfg.standoff_band * settling_band(step),
                ]
            )
        q, qdot = self._q, self._v
        if cfg.predict:
            q, qdot = self._run_twin(q, qdot, 0.0, cfg.latency_periods * period)
        allowance, most = self._standoff_room
        wanted = np.clip(cfg.standoff * self.estimate_std - allowance, 0.0, most)
        standoff = self._standoff = np.maximum(self._standoff, wanted)
        error = goal - self._aim_side * standoff - q
        mass = self.twin.mass_matrix(q)
        inertia = np.diag(mass)
        gravity = self.twin.gravity_torque(q)
        k, kv = self._gains(inertia)
        near = (np.abs(error) < cfg.integral_band) & (np.abs(qdot) < cfg.integral_speed)
        grown = self._integral + cfg.integral_gain * error / cfg.rate_hz
        self._integral = np.where(near, np.clip(grown, -cfg.integral_cap, cfg.integral_cap), 0.0)
        v_ref = np.clip(k * error, -cfg.max_speed, cfg.max_speed) + self._integral
        torque = (
            self.damping * v_ref
            + mass @ (kv / inertia * (v_ref - qdot))
            + self.friction
            * np.tanh(v_ref / cfg.friction_speed)
            * np.clip(np.abs(error) / cfg.friction_band, 0.0, 1.0)
            - gravity
        )
        out: np.ndarray = np.clip(
            torque / self.torque_per_mA, -self.current_limits_mA, self.current_limits_mA
        )
        # how wrong the twin may be over the next period: twin_error of the torques at work
        load = (
            np.abs(out * self.torque_per_mA)
            + np.abs(gravity)
            + self.friction
            + self.damping * np.abs(qdot)
        )
        self._model_accel = cfg.model_accel + cfg.twin_error * load / inertia
        self._sent.append(out.copy())
        return out


@drives(ALPHA5, BRAVO7)
@engineered
def make_controller(
    params: str | Path | dict[str, Any] | FittedTwin | None = None,
    *,
    model: ArmModel = ALPHA5,
    **kwargs: Any,
) -> LambdaController:
    """Lambda rule on a twin; engineered, no learning.

    Entry point `lambda`: `params` is the twin (an arm parameter file's path, a dict of
    `ArmParams` fields, or a `FittedTwin`; nominal if omitted); keyword arguments are
    `LambdaConfig` fields. Without `latency_periods`, a twin with a fit (a file written by
    `tools/identify.py`, or a dict or `FittedTwin` holding its ``_fit``) gives it: the command
    delay it measured times the control rate. On the Bravo 7 (`model`) `params` are of its six
    joints, the rest its MJCF's; an Alpha 5's are refused in one line."""
    known = {f.name for f in fields(LambdaConfig)}
    unknown = set(kwargs) - known
    if unknown:
        raise ValueError(
            f"unknown lambda options {sorted(unknown)}; known: {sorted(known)} and params"
        )
    config = replace(LambdaConfig(), **kwargs)
    twin: FittedTwin | None
    if params is None:
        twin = None  # the model's nominal twin
    elif isinstance(params, FittedTwin):
        twin = params
    elif isinstance(params, dict):
        twin = FittedTwin.from_json_dict(params, "params", model, nominal_params(model))
    else:
        twin = read_twin(params, model, nominal_params(model))
    if twin is not None and "latency_periods" not in kwargs and twin.delay_s is not None:
        config = replace(config, latency_periods=twin.delay_s * config.rate_hz)
    return LambdaController(None if twin is None else twin.params, config, model=model)
