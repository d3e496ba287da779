"""The excitation an identification drives each joint with: relay swings at a speed target,
current chirps and pseudo-random current steps (`Wave`, `plan`), around poses of the factory
envelope (`pose`), while a PID holds the other joints (`Excitation`, a `Controller`); the
current each joint needs is learnt from the relays (`Amplitudes`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.alpha5 import FACTORY_MIDDLE, N_JOINTS, TORQUE_PER_AMP_NM
from reach_driver.controllers import ControlState
from reach_sim_bridge.model.params import ArmParams

K_MA = np.asarray(TORQUE_PER_AMP_NM) / 1000.0  # N m per mA, E D C B
#: The middle of the factory envelope: the pose every identification starts and ends at.
HOME = np.array(FACTORY_MIDDLE)
#: Fitting poses P1, P2 and the validation pose P3 (offsets from HOME, rad): D and C at other
#: angles load them differently with gravity.
POSE_OFFSETS = {
    "P1": np.zeros(4),
    "P2": np.array([0.5, -0.45, 0.5, 0.8]),
    "P3": np.array([-0.5, 0.45, -0.45, -0.8]),
}
WINDOW = np.array([0.35, 0.35, 0.35, 0.6])  # rad each side of the pose, the excited joint
GUARD = 0.15  # rad beyond the window: the excited joint is servoed back to its pose
SPEED_CAP = np.array([0.45, 0.45, 0.45, 0.75])  # rad/s, under the factory rate limits
SPEED_FILTER_S = 0.1  # s: the relay judges its speed on readings low-passed this much
STALL_CHECK_S = 0.5  # s: under 0.3 of the aimed progress in this gets the relay more current
HOLD_KP = np.array([3000.0, 3000.0, 3000.0, 300.0])  # mA/rad
HOLD_KD = np.array([200.0, 200.0, 200.0, 20.0])  # mA s/rad
HOLD_KI = np.array([6000.0, 6000.0, 6000.0, 600.0])  # mA/(rad s)
HOLD_I_MAX = np.array([250.0, 250.0, 250.0, 60.0])  # mA the integral may add
CHIRP_SPRING = np.array([600.0, 600.0, 600.0, 60.0])  # mA/rad centring the chirped joint
CHIRP_DAMP = np.array([20.0, 20.0, 20.0, 2.0])  # mA s/rad


@dataclass(frozen=True)
class Wave:
    """One excitation of one joint: relay (speed target), chirp, or random steps."""

    kind: str  # "relay" | "chirp" | "steps"
    pose: str  # "P1" | "P2" | "P3"
    seconds: float
    role: str  # "fit" | "validate"
    speed: float = 0.25  # relay: rad/s peak speed aimed for
    f0: float = 0.3  # chirp: Hz
    f1: float = 3.0
    gain: float = 1.5  # chirp: amplitude / the joint's relay amplitude; steps: spread
    seed: int = 0

    @property
    def label(self) -> str:
        detail = {
            "relay": f"{self.speed:g} rad/s",
            "chirp": f"{self.f0:g}-{self.f1:g} Hz",
            "steps": f"seed {self.seed}",
        }[self.kind]
        return f"{self.kind} {detail} at {self.pose}"


def plan(scale: float = 1.0) -> list[Wave]:
    """The segments of one joint (arm seconds scale with `scale`)."""
    s = scale
    return [
        Wave("relay", "P1", 8.0 * s, "fit", speed=0.15),
        Wave("relay", "P1", 8.0 * s, "fit", speed=0.35),
        Wave("chirp", "P1", 8.0 * s, "fit", f0=0.3, f1=5.0, gain=2.0),
        Wave("relay", "P2", 8.0 * s, "fit", speed=0.25),
        Wave("steps", "P3", 8.0 * s, "validate", gain=0.4, seed=1),
        Wave("chirp", "P3", 6.0 * s, "validate", f0=0.5, f1=2.5, gain=1.3),
    ]


def pose(name: str) -> np.ndarray:
    return HOME + POSE_OFFSETS[name]


@dataclass
class Amplitudes:
    """The excitation current found per joint (mA), adapted by the relay swings."""

    nominal: ArmParams = field(default_factory=ArmParams)
    ratio: dict[int, float] = field(default_factory=dict)  # found / nominal estimate
    found: dict[int, float] = field(default_factory=dict)  # the last relay's amplitude

    def nominal_for(self, joint: int, speed: float) -> float:
        """What the nominal twin needs to hold `speed` against friction (mA)."""
        p = self.nominal
        torque = p.frictionloss[joint] + p.damping[joint] * speed
        return float(torque / K_MA[joint])

    def start(self, joint: int, speed: float) -> float:
        """A relay's first amplitude: the nominal estimate, corrected by earlier relays."""
        return self.nominal_for(joint, speed) * self.ratio.get(joint, 1.0)

    def learn(self, joint: int, speed: float, amplitude: float) -> None:
        self.ratio[joint] = amplitude / self.nominal_for(joint, speed)
        self.found[joint] = amplitude

    def reference(self, joint: int) -> float:
        """The current that chirps and steps are scaled by (mA)."""
        return self.found.get(joint, self.start(joint, 0.25))


class Excitation:
    """A `Controller` exciting one joint with `wave` around `center` while holding the
    others there (PID), with the nominal twin's gravity as feed-forward for all joints."""

    def __init__(
        self,
        joint: int,
        wave: Wave,
        center: np.ndarray,
        period: float,
        amplitude: float,
        amp_max: float,
        gravity: Any,
    ) -> None:
        self.joint = joint
        self.wave = wave
        self.center = np.asarray(center, dtype=float)
        self.period = period
        self.amplitude = float(amplitude)
        self.amp_max = float(amp_max)
        self.gravity = gravity
        self.rng = np.random.default_rng(wave.seed)
        self.reset()

    def reset(self) -> None:
        self.integral = np.zeros(N_JOINTS)
        self.direction = 1.0
        self.peak = 0.0
        self.pass_t = 0.0
        self.stall_t = 0.0
        self.stall_x: float | None = None
        self.speed = 0.0  # the joint's speed readings, low-passed (SPEED_FILTER_S)
        self.step_end = -1.0
        self.step_level = 0.0
        self.flips = 0

    def _hold(self, q: np.ndarray, qdot: np.ndarray) -> np.ndarray:
        err = self.center - q
        self.integral = np.clip(
            self.integral + HOLD_KI * err * self.period, -HOLD_I_MAX, HOLD_I_MAX
        )
        return HOLD_KP * err - HOLD_KD * qdot + self.integral

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q, qdot, t = state.q, state.qdot, float(state.t)
        j, w = self.joint, self.wave
        ff = -np.asarray(self.gravity(q)) / K_MA  # mA holding the nominal twin's weight
        out = ff + self._hold(q, qdot)
        x = q[j] - self.center[j]
        v = qdot[j]
        if abs(x) > WINDOW[j] + GUARD:
            # Outside the window and the guard band: servo back (the hold law, this joint).
            return out
        self.integral[j] = 0.0
        if w.kind == "relay":
            u = self._relay(x, v, t)
        elif w.kind == "chirp":
            tt = t
            phase = 2 * math.pi * (w.f0 * tt + 0.5 * (w.f1 - w.f0) * tt * tt / w.seconds)
            amp = w.gain * self.amplitude
            u = amp * math.sin(phase) - CHIRP_SPRING[j] * x - CHIRP_DAMP[j] * v
        else:
            u = self._steps(x, t)
        if abs(x) > WINDOW[j] and u * x > 0:
            u = 0.0  # never push further out past the window edge
        if abs(v) > SPEED_CAP[j] and u * v > 0:
            u = 0.0  # coast down from above the speed cap
        out[j] = ff[j] + float(np.clip(u, -self.amp_max, self.amp_max))
        return out

    def _relay(self, x: float, v: float, t: float) -> float:
        # Noisy readings (3x the standard noise: 0.06 rad/s) once passed for motion: their
        # peak read 0.2 rad/s on a joint stuck behind 6.6 N m, so its current never rose.
        # The peak is taken on low-passed speeds and a stall from the angle's progress.
        j, w = self.joint, self.wave
        self.speed += (v - self.speed) * min(1.0, self.period / SPEED_FILTER_S)
        self.peak = max(self.peak, abs(self.speed))
        edge = WINDOW[j] * 0.9
        if self.stall_x is None:
            self.stall_t, self.stall_x = t, x
        if (self.direction > 0 and x > edge) or (self.direction < 0 and x < -edge):
            self.direction = -self.direction
            self.flips += 1
            self._adapt(w.speed)
            self.peak = 0.0
            self.pass_t = t
            self.stall_t, self.stall_x = t, x
        elif t - self.stall_t >= STALL_CHECK_S:
            # Not moving: friction above what was tried; more current.
            if abs(x - self.stall_x) < 0.3 * w.speed * (t - self.stall_t):
                self.amplitude = min(self.amplitude * 1.3, self.amp_max)
            self.stall_t, self.stall_x = t, x
        return self.direction * self.amplitude

    def _adapt(self, speed: float) -> None:
        if self.peak < 0.85 * speed:
            self.amplitude = min(self.amplitude * 1.2, self.amp_max)
        elif self.peak > 1.15 * speed:
            self.amplitude *= 0.85

    def _steps(self, x: float, t: float) -> float:
        j, w = self.joint, self.wave
        if t >= self.step_end:
            self.step_end = t + float(self.rng.uniform(0.4, 1.0))
            if self.rng.random() < 0.25:
                self.step_level = 0.0
            else:
                sign = 1.0 if self.rng.random() < 0.5 else -1.0
                if abs(x) > 0.5 * WINDOW[j]:
                    sign = -math.copysign(1.0, x)
                spread = float(self.rng.uniform(1.0 - w.gain, 1.0 + w.gain))
                self.step_level = sign * spread * self.amplitude
        if abs(x) > 0.9 * WINDOW[j] and self.step_level * x > 0:
            self.step_level = -self.step_level
        return self.step_level
