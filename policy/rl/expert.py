"""The demonstrator: a saturated PD on the TRUE state, for DDPGfD / TD3+BC-style training.

It reads the env's arm directly (privileged), so it lives beside the env, not in it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from policy.rl.env import NO_LOAD_SPEEDS, ReachAlphaEnv
from protocol.alpha5 import N_JOINTS
from reach_sim_bridge.model.params import ArmParams

# what the demonstrator knows of the arm: the nominal model, not an episode's perturbed one
NOMINAL_DAMPING = np.asarray(ArmParams().damping, dtype=np.float64)  # N m s/rad
NOMINAL_FRICTIONLOSS = np.asarray(ArmParams().frictionloss, dtype=np.float64)  # N m


@dataclass(frozen=True)
class PDExpert:
    """Saturated PD on the TRUE state with gravity and friction feed-forward: the
    demonstrator for DDPGfD / TD3+BC-style training (and a privileged baseline).

    Stateless (a function of q, qdot, q_req like the policy), so the actor can represent it.
    Gains are per joint in units of the current limit: a = clip(kd (v_ref - qdot) + ff, -1, 1)
    with v_ref = (kp / kd) e, i.e. a = kp e - kd qdot.

    `energy_lambda` (None: off) caps each joint's speed by the energy-optimal arrival profile
    v = sqrt(lambda |e| / b) (b: the joint's nominal viscous friction). That profile minimises
    friction work b v^2 plus lambda times the integrated error (constant deceleration is the
    Euler-Lagrange solution), so joints with little way to go or much friction move slower,
    while a joint whose remaining time is the longest (the one that sets the settling time)
    keeps full speed. The cruise speed is held by a friction feed-forward that fades out
    within `cruise_gate` of the target, where the plain PD takes over (docs/distilled.md).
    """

    # tuned on the nominal arm at 20 Hz (docs/distilled.md): no overshoot, no steady error
    kp: tuple[float, float, float, float] = (8.0, 8.0, 8.0, 4.0)  # 1/rad
    kd: tuple[float, float, float, float] = (0.4, 0.4, 0.4, 0.1)  # s/rad
    gravity_ff: bool = True
    friction_ff: float = 0.0  # fraction of the current limit pushed along the error
    friction_band: float = 0.003  # rad: width of the tanh that switches friction_ff on
    energy_lambda: float | None = None  # N m / s: weight of integrated error against work
    #: (start, width) rad: the cruise feed-forward is off within `start` of the target and
    #: fully on beyond start + width
    cruise_gate: tuple[float, float] = (0.02, 0.05)
    #: a joint within this fraction of the no-load speed counts as the slowest (full speed)
    full_speed_fraction: float = 0.97

    def __call__(self, env: ReachAlphaEnv) -> np.ndarray:
        arm: Any = env.arm
        q, qdot = np.asarray(arm.q), np.asarray(arm.qdot)
        error = env.target - q
        kp, kd = np.asarray(self.kp), np.asarray(self.kd)
        full_torque = arm.motor.torque_per_amp * env.current_limits_mA / 1000.0
        torque_unit = full_torque * np.maximum(arm.torque_scale, 0.05)
        v_ref = kp / kd * error
        feed_forward = np.zeros(N_JOINTS)
        if self.energy_lambda is not None:
            v_cruise = self.cruise_speed(np.abs(error))
            capped = v_cruise < np.abs(v_ref)
            v_ref = np.where(capped, np.sign(error) * v_cruise, v_ref)
            lo, width = self.cruise_gate
            gate = np.clip((np.abs(error) - lo) / width, 0.0, 1.0) * capped
            speed = np.minimum(v_cruise, NO_LOAD_SPEEDS)  # finite where the gate is on
            friction = NOMINAL_DAMPING * speed + NOMINAL_FRICTIONLOSS
            feed_forward = gate * np.sign(error) * friction / torque_unit
        a = kd * (v_ref - qdot) + feed_forward
        if self.gravity_ff and hasattr(arm, "gravity_torque"):
            a = a - arm.gravity_torque(q) / torque_unit
        a = a + self.friction_ff * np.tanh(error / self.friction_band)
        out: np.ndarray = np.clip(a, -1.0, 1.0)
        return out

    def cruise_speed(self, abs_error: np.ndarray) -> np.ndarray:
        """Speed cap per joint (rad/s); inf where the joint should run flat out."""
        assert self.energy_lambda is not None
        profile = np.sqrt(self.energy_lambda * abs_error / NOMINAL_DAMPING)
        # never slower than arriving together with the slowest joint
        remaining = float(np.max(abs_error / NO_LOAD_SPEEDS)) + 1e-9
        profile = np.maximum(profile, abs_error / remaining)
        out: np.ndarray = np.where(
            profile >= self.full_speed_fraction * NO_LOAD_SPEEDS, np.inf, profile
        )
        return out
