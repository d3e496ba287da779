"""Closed-loop evaluation of a controller on the simulated arm, scored by `reach_driver.metrics`.

The runner steps `Alpha5Arm` directly at the control period: the controller's currents are
held for the period (zero-order hold) while the physics runs its substeps, the way the
firmware holds the last CURRENT packet. The controller sees only (optionally noisy) readings;
the metrics use the simulator's true angles. Every controller goes through this one runner
so the numbers in docs/results.md compare like with like.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from policy.observation import N_JOINTS, WORKSPACE_HIGH, WORKSPACE_LOW
from reach_driver.controllers import load_controller
from reach_driver.metrics import (
    METRIC_KEYS,
    Metrics,
    Trace,
    compute_metrics,
    rmse_floor,
    summarize,
)

DEFAULT_SECONDS = 20.0
DEFAULT_RATE_HZ = 20.0
PHYSICS_DT = 0.002


class Controller(Protocol):
    def reset(self) -> None: ...

    def act(self, state: Any, target: np.ndarray) -> np.ndarray: ...


class ArmLike(Protocol):
    """The part of `reach_sim_bridge.arm.Alpha5Arm` the runner uses."""

    @property
    def q(self) -> np.ndarray: ...

    @property
    def qdot(self) -> np.ndarray: ...

    @property
    def tau(self) -> np.ndarray: ...

    @property
    def current_mA(self) -> np.ndarray: ...

    torque_scale: np.ndarray

    @property
    def position_limits(self) -> np.ndarray: ...

    def reset(self, q: np.ndarray, qdot: np.ndarray | None = ..., jaw_mm: float = ...) -> Any: ...

    def step(self, currents_mA: np.ndarray, jaw_current_mA: float = ..., n: int = ...) -> Any: ...

    def randomize(self, spread: float = ..., rng: np.random.Generator | int | None = ...) -> Any:
        ...


ArmFactory = Callable[[int], ArmLike]
"""Builds a fresh arm for an episode from a seed."""


def _vec4(value: Any, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be 4 numbers (E D C B), got {value!r}") from exc
    if arr.shape != (N_JOINTS,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be 4 finite numbers (E D C B), got {value!r}")
    return arr


@dataclass(frozen=True)
class Episode:
    """A step from ``start`` to ``target`` (arm angles, rad, E D C B)."""

    start: np.ndarray
    target: np.ndarray
    torque_scale: np.ndarray = field(default_factory=lambda: np.ones(N_JOINTS))
    name: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _vec4(self.start, "start"))
        object.__setattr__(self, "target", _vec4(self.target, "target"))
        scale = _vec4(self.torque_scale, "torque_scale")
        if np.any(scale < 0) or np.any(scale > 1):
            raise ValueError(f"torque_scale must be in [0, 1] per joint, got {scale.tolist()}")
        object.__setattr__(self, "torque_scale", scale)

    @classmethod
    def from_dict(cls, data: Any, where: str = "episode") -> Episode:
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected an object with start and target, got {data!r}")
        unknown = set(data) - {"start", "target", "torque_scale", "name"}
        if unknown:
            raise ValueError(f"{where}: unknown keys {sorted(unknown)}")
        missing = {"start", "target"} - set(data)
        if missing:
            raise ValueError(f"{where}: missing {sorted(missing)}")
        try:
            return cls(
                start=data["start"],
                target=data["target"],
                torque_scale=data.get("torque_scale", np.ones(N_JOINTS)),
                name=str(data.get("name", "")),
            )
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"start": self.start.tolist(), "target": self.target.tolist()}
        if np.any(self.torque_scale != 1.0):
            out["torque_scale"] = self.torque_scale.tolist()
        if self.name:
            out["name"] = self.name
        return out


def load_episodes(path: str | Path) -> list[Episode]:
    """Episodes from a JSON list of {"start", "target", "torque_scale"?} objects."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"cannot read targets file {path}: {exc.strerror}") from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from exc
    if not isinstance(data, list) or not data:
        raise ValueError(f"{path}: expected a non-empty JSON list of episodes")
    return [Episode.from_dict(item, f"{path} episode {i}") for i, item in enumerate(data)]


def random_episodes(
    n: int, seed: int, low: np.ndarray = WORKSPACE_LOW, high: np.ndarray = WORKSPACE_HIGH
) -> list[Episode]:
    """``n`` starts and targets drawn uniformly in the evaluation workspace."""
    if n < 1:
        raise ValueError(f"need at least one episode, got {n}")
    rng = np.random.default_rng(seed)
    return [
        Episode(start=rng.uniform(low, high), target=rng.uniform(low, high)) for _ in range(n)
    ]


@dataclass(frozen=True)
class SensorNoise:
    """Gaussian noise on what the controller reads (the paper's noisy evaluation)."""

    q_sigma: float = 0.002  # rad
    qdot_sigma: float = 0.02  # rad/s


@dataclass(frozen=True)
class JointReading:
    """What a controller sees each period: ``.q``, ``.qdot`` (E D C B) and ``.t`` (s)."""

    q: np.ndarray
    qdot: np.ndarray
    t: float


@dataclass(frozen=True)
class RunConfig:
    seconds: float = DEFAULT_SECONDS
    rate_hz: float = DEFAULT_RATE_HZ
    noise: SensorNoise | None = None
    seed: int = 0  # sensor noise and parameter draws of episode i use seed + i
    physics_dt: float = PHYSICS_DT
    param_spread: float = 0.0
    """> 0: each episode's arm has friction, armature, masses and buoyancy scaled by factors
    drawn in [1 - spread, 1 + spread] (the paper's randomly degraded model), unknown to the
    controller."""

    def __post_init__(self) -> None:
        if not (self.seconds > 0 and math.isfinite(self.seconds)):
            raise ValueError(f"seconds must be positive, got {self.seconds}")
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"rate must be positive, got {self.rate_hz} Hz")
        if not 0.0 <= self.param_spread < 1.0:
            raise ValueError(f"param_spread must be in [0, 1), got {self.param_spread}")
        sub = self.period / self.physics_dt
        if abs(sub - round(sub)) > 1e-6 or round(sub) < 1:
            raise ValueError(
                f"the control period 1/{self.rate_hz} s must be a whole number of physics "
                f"steps of {self.physics_dt} s"
            )

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def substeps(self) -> int:
        return int(round(self.period / self.physics_dt))

    @property
    def n_steps(self) -> int:
        return int(round(self.seconds * self.rate_hz))

    def to_dict(self) -> dict[str, Any]:
        return {
            "seconds": self.seconds,
            "rate_hz": self.rate_hz,
            "noise": None if self.noise is None else vars(self.noise).copy(),
            "seed": self.seed,
            "physics_dt": self.physics_dt,
            "param_spread": self.param_spread,
        }


@dataclass(frozen=True)
class EpisodeResult:
    episode: Episode
    trace: Trace
    currents_mA: np.ndarray  # (N+1, 4) commanded over the period ending at each sample
    metrics: Metrics
    rmse_floor: float

    @property
    def final_error(self) -> np.ndarray:
        return self.trace.errors[-1]

    def to_dict(self) -> dict[str, Any]:
        out = self.episode.to_dict()
        out.update(
            reached=self.metrics.reached,
            final_error=self.final_error.tolist(),
            metrics=self.metrics.as_dict(),
            rmse_floor=self.rmse_floor,
        )
        return out


@dataclass(frozen=True)
class Evaluation:
    controller: str
    config: RunConfig
    results: list[EpisodeResult]
    controller_stats: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, float]:
        out = summarize([r.metrics for r in self.results])
        out["rmse_floor"] = float(np.mean([r.rmse_floor for r in self.results]))
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "controller": self.controller,
            "config": self.config.to_dict(),
            "episodes": [r.to_dict() for r in self.results],
            "summary": self.summary(),
            "controller_stats": self.controller_stats,
        }


def default_arm_factory(seed: int) -> ArmLike:
    """The nominal simulated arm (its own seed drives any randomness it has)."""
    from reach_sim_bridge.arm import Alpha5Arm

    arm: ArmLike = Alpha5Arm(dt=PHYSICS_DT, seed=seed)
    return arm


def no_load_speeds() -> np.ndarray:
    from reach_sim_bridge.motor import no_load_speed

    return np.asarray(no_load_speed(), dtype=float)


def check_inside_limits(position_limits: np.ndarray, q: np.ndarray, what: str) -> None:
    """A clear error naming the joints of `q` outside the arm's [min, max] limits."""
    limits = np.asarray(position_limits, dtype=float)
    outside = (q < limits[:, 0]) | (q > limits[:, 1])
    if np.any(outside):
        joints = ", ".join("EDCB"[j] for j in np.flatnonzero(outside))
        raise ValueError(
            f"{what} {q.tolist()} is outside the arm's joint limits on {joints} "
            f"({limits.tolist()})"
        )


def run_episode(
    controller: Controller,
    episode: Episode,
    config: RunConfig = RunConfig(),
    arm_factory: ArmFactory = default_arm_factory,
    episode_seed: int = 0,
) -> EpisodeResult:
    """One episode: reset arm and controller, hold each action for one control period."""
    arm = arm_factory(episode_seed)
    if abs(config.physics_dt - _arm_dt(arm, config.physics_dt)) > 1e-12:
        raise ValueError("the arm's physics step differs from RunConfig.physics_dt")
    check_inside_limits(arm.position_limits, episode.start, "start")
    check_inside_limits(arm.position_limits, episode.target, "target")
    if config.param_spread > 0:
        arm.randomize(config.param_spread, rng=np.random.default_rng([episode_seed, 1]))
    arm.reset(q=episode.start.copy())
    arm.torque_scale = episode.torque_scale.copy()
    controller.reset()
    rng = np.random.default_rng(episode_seed)
    n = config.n_steps
    q = np.empty((n + 1, N_JOINTS))
    qdot = np.empty((n + 1, N_JOINTS))
    tau = np.zeros((n + 1, N_JOINTS))
    power = np.zeros((n + 1, N_JOINTS))
    currents = np.zeros((n + 1, N_JOINTS))
    q[0], qdot[0] = arm.q, arm.qdot
    target = episode.target.copy()
    for k in range(n):
        seen_q, seen_qdot = q[k].copy(), qdot[k].copy()
        if config.noise is not None:
            seen_q += rng.normal(0.0, config.noise.q_sigma, N_JOINTS)
            seen_qdot += rng.normal(0.0, config.noise.qdot_sigma, N_JOINTS)
        action = controller.act(JointReading(seen_q, seen_qdot, k * config.period), target.copy())
        u = np.asarray(action, dtype=float)
        if u.shape != (N_JOINTS,) or not np.all(np.isfinite(u)):
            raise ValueError(
                f"controller returned {action!r} at step {k}: expected 4 finite currents (mA)"
            )
        # Physics steps one at a time so the energy integrates |tau qdot| at the physics rate
        # (the back-EMF makes the torque vary within a held period).
        energy = np.zeros(N_JOINTS)
        for _ in range(config.substeps):
            arm.step(u, n=1)
            energy += np.abs(arm.tau * arm.qdot)
        power[k + 1] = energy / config.substeps
        q[k + 1], qdot[k + 1] = arm.q, arm.qdot
        tau[k + 1] = arm.tau
        currents[k + 1] = u
    trace = Trace(dt=config.period, q=q, qdot=qdot, tau=tau, target=target, power=power)
    floor = rmse_floor(episode.start, target, no_load_speeds(), config.period, n)
    return EpisodeResult(episode, trace, currents, compute_metrics(trace), floor)


def _arm_dt(arm: ArmLike, default: float) -> float:
    return float(getattr(arm, "dt", default))


def evaluate(
    controller: Controller,
    episodes: Sequence[Episode],
    config: RunConfig = RunConfig(),
    name: str = "controller",
    arm_factory: ArmFactory = default_arm_factory,
    on_episode: Callable[[int, EpisodeResult], None] | None = None,
) -> Evaluation:
    results = []
    for i, episode in enumerate(episodes):
        result = run_episode(controller, episode, config, arm_factory, config.seed + i)
        results.append(result)
        if on_episode is not None:
            on_episode(i, result)
    stats: dict[str, Any] = {}
    solve_stats = getattr(controller, "solve_time_stats", None)
    if callable(solve_stats):
        stats["solve_time_s"] = solve_stats()
    return Evaluation(name, config, results, stats)


__all__ = [
    "METRIC_KEYS",
    "Controller",
    "Episode",
    "EpisodeResult",
    "Evaluation",
    "JointReading",
    "RunConfig",
    "SensorNoise",
    "evaluate",
    "load_controller",
    "load_episodes",
    "random_episodes",
    "run_episode",
]
