"""The trained DDPG actor as a controller for the control loop: a numpy forward pass.

A whole `act()` (observation + three float32 matrix products) measured p50 29 us, p99 under
50 us against 52 / 80 us for the torch actor (tools/bench_train.py --inference; 0.5 ms
budget). The inputs are built by `policy.observation.build_observation` with the
configuration saved beside the weights, so the driver feeds the network what training did.

    from policy.ddpg_controller import make_controller
    ctrl = make_controller()                 # shipped weights, policy/weights/ddpg_actor.npz
    ctrl.reset(); currents_mA = ctrl.act(state, target)   # state has .q .qdot .t (E D C B)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policy.observation import ObservationConfig, build_observation
from protocol.alpha5 import DEFAULT_CURRENT_LIMITS_MA, N_JOINTS
from reach_driver.controllers import ControlState

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "ddpg_actor.npz"


@dataclass(frozen=True)
class ActorWeights:
    """Dense layers (W: out x in, b) with LeakyReLU between them and tanh at the end."""

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    leaky_slope: float
    observation: ObservationConfig
    current_limits_mA: np.ndarray
    metadata: dict[str, Any]

    @classmethod
    def load(cls, path: str | Path) -> ActorWeights:
        """Read `path` (.npz) and the .json beside it; errors say which file is wrong."""
        path = Path(path)
        meta_path = path.with_suffix(".json")
        if not path.is_file():
            raise FileNotFoundError(f"no actor weights at {path}")
        if not meta_path.is_file():
            raise FileNotFoundError(f"no metadata {meta_path} beside the weights {path}")
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{meta_path} is not valid JSON: {exc}") from exc
        if meta.get("format") != "reach-stack ddpg actor v1":
            raise ValueError(f"{meta_path}: unknown weights format {meta.get('format')!r}")
        with np.load(path) as data:
            n = sum(1 for key in data.files if key.startswith("W"))
            if n == 0 or any(
                f"W{i}" not in data.files or f"b{i}" not in data.files for i in range(n)
            ):
                raise ValueError(f"{path}: expected arrays W0 b0 .. W{n - 1} b{n - 1}")
            weights = tuple(np.asarray(data[f"W{i}"], np.float64) for i in range(n))
            biases = tuple(np.asarray(data[f"b{i}"], np.float64) for i in range(n))
        observation = ObservationConfig.from_dict(meta["observation"])
        if weights[0].shape[1] != observation.size or weights[-1].shape[0] != N_JOINTS:
            raise ValueError(
                f"{path}: network maps {weights[0].shape[1]} -> {weights[-1].shape[0]}, "
                f"the observation config needs {observation.size} -> {N_JOINTS}"
            )
        for i, (w, b) in enumerate(zip(weights, biases, strict=True)):
            if b.shape != (w.shape[0],) or (i and w.shape[1] != weights[i - 1].shape[0]):
                raise ValueError(f"{path}: layer {i} shapes do not chain")
        limits = np.asarray(meta.get("current_limits_mA", DEFAULT_CURRENT_LIMITS_MA), float)
        return cls(
            weights, biases, float(meta.get("leaky_relu_slope", 0.01)), observation, limits, meta
        )

    def __post_init__(self) -> None:
        # float32, transposed and contiguous: what torch computed, at matmul speed
        object.__setattr__(
            self, "_wt", tuple(np.ascontiguousarray(w.T, dtype=np.float32) for w in self.weights)
        )
        object.__setattr__(self, "_b32", tuple(b.astype(np.float32) for b in self.biases))
        if not 0.0 <= self.leaky_slope < 1.0:
            raise ValueError(f"leaky_relu_slope must be in [0, 1), got {self.leaky_slope}")

    def forward(self, obs: np.ndarray) -> np.ndarray:
        """Actions in [-1, 1] for one observation (n,) or a batch (B, n)."""
        x = np.asarray(obs, dtype=np.float32)
        wt: tuple[np.ndarray, ...] = self._wt  # type: ignore[attr-defined]
        b32: tuple[np.ndarray, ...] = self._b32  # type: ignore[attr-defined]
        last = len(wt) - 1
        for i in range(last + 1):
            x = x @ wt[i]
            x += b32[i]
            if i < last:
                x = np.maximum(x, self.leaky_slope * x)  # LeakyReLU for slope < 1
        out: np.ndarray = np.tanh(x)
        return out


@dataclass(frozen=True)
class ReferenceIntegral:
    """Integral action around the stateless policy: it is shown the target shifted by
    `gain` times the integrated error, once a joint is within `band` of its target, by at most
    `cap`.

    Why: the policy stops a few mrad short wherever static friction (0.7 N m, 6 % of the
    current limit on E, D, C) holds the joint against its small final command, and on an arm
    whose masses or buoyancy differ from the model; with no memory it cannot correct that
    (docs/training.md, "Fine-tuning"). Shifting the reference is the classic outer-loop fix
    that leaves the learned network untouched. The integral restarts whenever the target
    changes or the joint leaves the band, so the approach itself is the policy's alone.
    `gain` 0 turns it off (the pure policy, entry point `ddpg-pure`).
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


class DDPGController:
    """The actor: currents (mA, E D C B) from the joint state and the target, with an optional
    integral on the reference it is shown (`ReferenceIntegral`)."""

    def __init__(
        self,
        weights: ActorWeights,
        current_limits_mA: Any = None,
        integral: ReferenceIntegral | None = None,
    ) -> None:
        self.weights = weights
        limits = weights.current_limits_mA if current_limits_mA is None else current_limits_mA
        self.current_limits_mA = np.asarray(limits, dtype=np.float64)
        if self.current_limits_mA.shape != (N_JOINTS,) or np.any(self.current_limits_mA < 0):
            raise ValueError(f"current_limits_mA needs 4 values >= 0, got {limits!r}")
        self.integral = integral or ReferenceIntegral(gain=0.0)
        self.reset()

    def reset(self) -> None:
        """Forget the reference integral (the network itself has no memory)."""
        self.offset = np.zeros(N_JOINTS)
        self._target: np.ndarray | None = None
        self._t: float | None = None

    def observation(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        """The network's input for `state` and `target` as given (no reference integral)."""
        q, qdot, goal = self._checked(state, target)
        return build_observation(q, qdot, goal, self.weights.observation)

    @staticmethod
    def _checked(state: ControlState, target: np.ndarray) -> tuple[np.ndarray, ...]:
        target = np.asarray(target, dtype=np.float64)
        if target.shape != (N_JOINTS,) or not np.all(np.isfinite(target)):
            raise ValueError(f"target must be 4 finite angles (rad, E D C B), got {target!r}")
        q = np.asarray(state.q, dtype=np.float64)
        qdot = np.asarray(state.qdot, dtype=np.float64)
        if q.shape != (N_JOINTS,) or qdot.shape != (N_JOINTS,):
            raise ValueError(
                f"state.q and state.qdot must have shape (4,), got {q.shape}, {qdot.shape}"
            )
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qdot))):
            raise ValueError(f"state must be finite, got q={q}, qdot={qdot}")
        return q, qdot, target

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

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q, qdot, goal = self._checked(state, target)
        shown = self._shift(q, getattr(state, "t", None), goal)
        action = self.weights.forward(build_observation(q, qdot, shown, self.weights.observation))
        out: np.ndarray = action * self.current_limits_mA
        return out


def make_controller(
    weights: str | Path | None = None,
    current_limits_mA: Any = None,
    integral_gain: float = ReferenceIntegral.gain,
    integral_band: float = ReferenceIntegral.band,
    integral_cap: float = ReferenceIntegral.cap,
) -> DDPGController:
    """The shipped controller: the DDPG actor (shipped weights, or those at `weights`) with its
    reference integral (`integral_gain` 0 for the pure policy)."""
    integral = ReferenceIntegral(gain=integral_gain, band=integral_band, cap=integral_cap)
    return DDPGController(
        ActorWeights.load(weights or DEFAULT_WEIGHTS), current_limits_mA, integral
    )


def make_pure_controller(
    weights: str | Path | None = None, current_limits_mA: Any = None
) -> DDPGController:
    """The DDPG actor alone, stateless, as trained: no reference integral."""
    return make_controller(weights, current_limits_mA, integral_gain=0.0)
