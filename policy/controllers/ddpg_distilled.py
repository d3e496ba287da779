"""The distilled actor as a controller for the control loop: a numpy forward pass.

What it is: not a policy learned by RL from scratch. The actor was trained by TD3 with a
behaviour-cloning term toward a privileged PD expert (`policy.rl.expert.PDExpert`, which reads
the true state, the masses and the torque scale) and 100 of its demonstration episodes per
stage, in four stages, each fine-tuning the previous one (the weights' json, "provenance";
docs/distilled.md). Around the network, engineered: a reference integral (`ReferenceIntegral`)
and a settle supervisor (`policy.controllers.settle`). Entry points: `ddpg-distilled` (all of
it), `ddpg-distilled-pure` (the actor alone).

A whole `act()` measured p50 82 us, p99 180 us with the settle supervisor, 39 / 92 us for the
actor and integral alone (observation + three float32 matrix products) and 56 / 110 us for
the torch actor (tools/bench_train.py --inference, idle 2-core machine; 0.5 ms budget). The
inputs are built by `policy.controllers.observation.build_observation` with the configuration
saved beside the weights, so the driver feeds the network what training did.
The weights and their format: `policy.controllers.weights`.

    from policy.controllers.ddpg_distilled import make_controller
    ctrl = make_controller()     # policy/controllers/weights/ddpg_distilled_actor.npz,
                                 # reference integral and settle supervisor
    ctrl.reset(); currents_mA = ctrl.act(state, target)   # state has .q .qdot .t (E D C B)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.observation import build_observation, checked_inputs
from policy.controllers.settle import SettleSupervisor
from policy.controllers.settle_law import SettleLaw
from policy.controllers.weights import DISTILLED_WEIGHTS, ActorWeights, provenance_of
from protocol.alpha5 import N_JOINTS
from protocol.models import ALPHA5
from reach_driver.controllers import ControlState, learned


@dataclass(frozen=True)
class ReferenceIntegral:
    """Integral action around the stateless policy: it is shown the target shifted by
    `gain` times the integrated error, once a joint is within `band` of its target, by at most
    `cap`.

    Why: the policy stops a few mrad short wherever static friction (0.7 N m, 6 % of the
    current limit on E, D, C) holds the joint against its small final command, and on an arm
    whose masses or buoyancy differ from the model; with no memory it cannot correct that
    (docs/distilled.md, "Fine-tuning"). Shifting the reference is the classic outer-loop fix
    that leaves the learned network untouched. The integral restarts whenever the target
    changes or the joint leaves the band, so the approach itself is the policy's alone.
    `gain` 0 turns it off (the actor alone, entry point `ddpg-distilled-pure`).
    """

    gain: float = 1.0  # 1/s
    band: float = 0.02  # rad
    cap: float = 0.01  # rad
    default_dt: float = 0.05  # s, when the state carries no time

    def __post_init__(self) -> None:
        if not (self.gain >= 0 and self.band > 0 and self.cap >= 0 and self.default_dt > 0):
            raise ValueError(
                f"reference integral needs gain >= 0 and band, cap, default_dt > 0, got {self}"
            )


class DistilledController:
    """The actor: currents (mA, E D C B) from the joint state and the target, with an optional
    integral on the reference it is shown (`ReferenceIntegral`)."""

    def __init__(
        self,
        weights: ActorWeights,
        current_limits_mA: Any = None,
        integral: ReferenceIntegral | None = None,
        settle: SettleLaw | None = None,
    ) -> None:
        if weights.model.name != ALPHA5.name:
            raise ValueError(
                f"the weights hold an actor for the {weights.model.title}; this controller "
                f"drives the {ALPHA5.title}"
            )
        self.weights = weights
        limits = weights.current_limits_mA if current_limits_mA is None else current_limits_mA
        self.current_limits_mA = np.asarray(limits, dtype=np.float64)
        if self.current_limits_mA.shape != (N_JOINTS,) or np.any(self.current_limits_mA < 0):
            raise ValueError(f"current_limits_mA needs 4 values >= 0, got {limits!r}")
        self.integral = integral or ReferenceIntegral(gain=0.0)
        self.settle = None if settle is None else SettleSupervisor(settle, self.current_limits_mA)
        self.reset()

    def reset(self) -> None:
        """Forget the reference integral (the network itself has no memory)."""
        self.offset = np.zeros(N_JOINTS)
        self._target: np.ndarray | None = None
        self._t: float | None = None
        self._hold_goal: np.ndarray | None = None
        self._hold = np.zeros(N_JOINTS)
        if self.settle is not None:
            self.settle.reset()

    def report(self) -> dict[str, Any]:
        """For the driver's run summary: the settle supervisor's report (and a line saying it),
        if it is on."""
        if self.settle is None:
            return {}
        settle = self.settle.report()
        latency = settle["latency_periods"]
        timed = "not timed" if latency is None else f"timed at {latency:.2f} periods"
        engaged = ", ".join(
            f"{joint} ({e['reason']} at {e['at_s']:.2f} s"
            + (f", released {e['releases']}x" if e["releases"] else "")
            + ")"
            for joint, e in settle["engaged"].items()
        )
        summary = f"settle supervisor: loop latency {timed}; engaged {engaged or 'no joint'}"
        return {"summary": summary, "settle": settle}

    def observation(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        """The network's input for `state` and `target` as given (no reference integral)."""
        q, qdot, goal = self._checked(state, target)
        return build_observation(q, qdot, goal, self.weights.observation)

    @staticmethod
    def _checked(state: ControlState, target: np.ndarray) -> tuple[np.ndarray, ...]:
        return checked_inputs(state.q, state.qdot, target)

    def shown_target(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        """The target the network is shown: `target` plus the reference integral."""
        q, _, target = self._checked(state, target)
        return self._shift(q, getattr(state, "t", None), target)

    def _shift(self, q: np.ndarray, t: float | None, target: np.ndarray) -> np.ndarray:
        cfg = self.integral
        if cfg.gain == 0:
            return target
        dt = cfg.default_dt
        if t is not None and self._t is not None and 0 < t - self._t <= 4 * cfg.default_dt:
            dt = float(t) - self._t
        self._t = None if t is None else float(t)
        if self._target is None or np.any(target != self._target):
            self.offset = np.zeros(N_JOINTS)
            self._target = target.copy()
        error = target - q
        grown = np.clip(self.offset + cfg.gain * error * dt, -cfg.cap, cfg.cap)
        self.offset = np.where(np.abs(error) < cfg.band, grown, 0.0)
        out: np.ndarray = target + self.offset
        return out

    def _hold_at(self, goal: np.ndarray) -> np.ndarray:
        """The actor's command at rest on the goal: its learned hold current there."""
        if self._hold_goal is None or np.any(goal != self._hold_goal):
            obs = build_observation(goal, np.zeros(N_JOINTS), goal, self.weights.observation)
            self._hold = self.weights.forward(obs) * self.current_limits_mA
            self._hold_goal = goal.copy()
        return self._hold

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q, qdot, goal = self._checked(state, target)
        t = getattr(state, "t", None)
        shown = self._shift(q, t, goal)
        action = self.weights.forward(build_observation(q, qdot, shown, self.weights.observation))
        out: np.ndarray = action * self.current_limits_mA
        if self.settle is not None:
            t_ = None if t is None else float(t)
            out = self.settle.update(t_, q, qdot, goal, out, self._hold_at(goal))
        return out


AROUND_THE_ACTOR = (
    "engineered: a reference integral (1/s, within 0.02 rad, at most 0.01 rad) and a settle "
    "supervisor (policy/controllers/settle.py)"
)


@learned(provenance_of(DISTILLED_WEIGHTS, AROUND_THE_ACTOR))
def make_controller(
    weights: str | Path | None = None,
    current_limits_mA: Any = None,
    integral_gain: float = ReferenceIntegral.gain,
    integral_band: float = ReferenceIntegral.band,
    integral_cap: float = ReferenceIntegral.cap,
    settle: Any = True,
) -> DistilledController:
    """TD3+BC actor + reference integral + settle law.

    Entry point `ddpg-distilled`: the actor distilled from a privileged PD expert (shipped
    weights, or those at `weights`) with its reference integral (`integral_gain` 0 turns it
    off) and the settle supervisor of `policy.controllers.settle` (docs/robustness.md).
    `settle`: true for its defaults, a dict of `SettleLaw` fields, or false for the actor and
    integral alone, the controller that chatters on a few per cent of degraded arms
    (docs/chatter.md)."""
    integral = ReferenceIntegral(gain=integral_gain, band=integral_band, cap=integral_cap)
    return DistilledController(
        ActorWeights.load(weights or DISTILLED_WEIGHTS),
        current_limits_mA,
        integral,
        SettleLaw.from_param(settle),
    )


@learned(provenance_of(DISTILLED_WEIGHTS, "nothing: the actor alone"))
def make_pure_controller(
    weights: str | Path | None = None, current_limits_mA: Any = None
) -> DistilledController:
    """TD3+BC actor alone (no integral, no settle law).

    Entry point `ddpg-distilled-pure`: the actor distilled from a privileged PD expert,
    stateless, as trained."""
    return make_controller(weights, current_limits_mA, integral_gain=0.0, settle=False)
