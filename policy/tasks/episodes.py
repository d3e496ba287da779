"""What every evaluation backend shares: the episode, the run settings, the one rollout type,
the one scorer and the one sensor-noise wrapper.

A backend (`policy.campaigns.direct`, `policy.campaigns.via_driver`, `policy.rl.batched`) only
produces a `Trace` of the simulator's TRUE state; `score` turns it into an `EpisodeResult` with
`reach_driver.metrics`, so docs/results.md and training's checkpoint selection compare like
with like.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.observation import Workspace
from policy.tasks.arm import PHYSICS_DT
from protocol.files import read_json
from protocol.models import ALPHA5, ArmModel
from reach_driver.controllers import Controller, ControlState
from reach_driver.metrics import (
    Metrics,
    OvershootAnatomy,
    Trace,
    compute_metrics,
    overshoot_anatomy,
    rmse_floor,
    summarize,
)
from reach_sim_bridge.model.motor import model_no_load_speed
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.sensors import SensorNoise

DEFAULT_SECONDS = 20.0
DEFAULT_RATE_HZ = 20.0
PERTURBATION_STREAM = 1
"""Episode seed `s` draws its arm's parameter perturbation from `default_rng([s, 1])`, apart
from its sensor noise (`default_rng(s)`), so switching noise on does not change the arm."""


def _joints(value: Any, what: str, model: ArmModel = ALPHA5) -> np.ndarray:
    n, letters = model.n_joints, " ".join(model.joint_letters)
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be {n} numbers ({letters}), got {value!r}") from exc
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be {n} finite numbers ({letters}), got {value!r}")
    return arr


@dataclass(frozen=True)
class Episode:
    """A step from ``start`` to ``target`` (arm angles, rad, in `model`'s joint order: E D C B
    on the Alpha 5, G F E D C B on the Bravo 7). ``torque_scale``: one per joint, or one for
    all (the default: 1, full torque)."""

    start: np.ndarray
    target: np.ndarray
    torque_scale: np.ndarray = field(default_factory=lambda: np.ones(()))
    name: str = ""
    model: ArmModel = ALPHA5

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _joints(self.start, "start", self.model))
        object.__setattr__(self, "target", _joints(self.target, "target", self.model))
        given: Any = self.torque_scale
        if np.ndim(given) == 0:  # one for every joint
            given = [given] * self.model.n_joints
        scale = _joints(given, "torque_scale", self.model)
        if np.any(scale < 0) or np.any(scale > 1):
            raise ValueError(f"torque_scale must be in [0, 1] per joint, got {scale.tolist()}")
        object.__setattr__(self, "torque_scale", scale)

    @classmethod
    def from_dict(cls, data: Any, where: str = "episode", model: ArmModel = ALPHA5) -> Episode:
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
                torque_scale=data.get("torque_scale", 1.0),
                name=str(data.get("name", "")),
                model=model,
            )
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{where}: {exc}") from exc

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"start": self.start.tolist(), "target": self.target.tolist()}
        if np.any(self.torque_scale != 1.0):
            out["torque_scale"] = self.torque_scale.tolist()
        if self.name:
            out["name"] = self.name
        return out


def load_episodes(path: str | Path, model: ArmModel = ALPHA5) -> list[Episode]:
    """Episodes of `model` from a JSON list of {"start", "target", "torque_scale"?} objects."""
    path = Path(path)
    data = read_json(path, "targets file")  # a UserFileError (ValueError) says what is wrong
    if not isinstance(data, list) or not data:
        raise ValueError(f"{path}: expected a non-empty JSON list of episodes")
    return [Episode.from_dict(item, f"{path} episode {i}", model) for i, item in enumerate(data)]


def random_episodes(
    n: int,
    seed: int,
    low: np.ndarray | None = None,
    high: np.ndarray | None = None,
    *,
    model: ArmModel = ALPHA5,
) -> list[Episode]:
    """``n`` starts and targets of `model` drawn uniformly in its evaluation workspace
    (`Workspace.of(model)`) unless ``low`` and ``high`` are given."""
    if n < 1:
        raise ValueError(f"need at least one episode, got {n}")
    workspace = Workspace.of(model)
    lo = np.asarray(workspace.low if low is None else low, dtype=float)
    hi = np.asarray(workspace.high if high is None else high, dtype=float)
    rng = np.random.default_rng(seed)
    return [
        Episode(start=rng.uniform(lo, hi), target=rng.uniform(lo, hi), model=model)
        for _ in range(n)
    ]


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
    params: ArmParams | None = None
    """The arm every episode runs on (a `--params` file, e.g. an identified twin); None is the
    nominal model. `param_spread` perturbs around it."""
    latency_periods: float = 0.0
    """Control latency in control periods: the command computed from the state at t takes
    effect at t + latency (the previous one stays in force until then), rounded to physics
    steps. Emulates a slow link or host on the direct backend (docs/robustness.md)."""

    def __post_init__(self) -> None:
        if not (self.seconds > 0 and math.isfinite(self.seconds)):
            raise ValueError(f"seconds must be positive, got {self.seconds}")
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"rate must be positive, got {self.rate_hz} Hz")
        if not (math.isfinite(self.latency_periods) and 0.0 <= self.latency_periods <= 10.0):
            raise ValueError(f"latency_periods must be in [0, 10], got {self.latency_periods}")
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
    def latency_substeps(self) -> int:
        return int(round(self.latency_periods * self.substeps))

    @property
    def n_steps(self) -> int:
        return int(round(self.seconds * self.rate_hz))

    def perturbation_rng(self, episode_seed: int) -> np.random.Generator:
        return np.random.default_rng([episode_seed, PERTURBATION_STREAM])

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "seconds": self.seconds,
            "rate_hz": self.rate_hz,
            "noise": None if self.noise is None else asdict(self.noise),
            "seed": self.seed,
            "physics_dt": self.physics_dt,
            "param_spread": self.param_spread,
        }
        if self.latency_periods:
            out["latency_periods"] = self.latency_periods
        if self.params is not None:
            out["params"] = self.params.to_json_dict()
        return out


DEFAULT_RUN = RunConfig()


@dataclass(frozen=True)
class EpisodeResult:
    """The one rollout type: an episode's true trace, the commands and its scores."""

    episode: Episode
    trace: Trace
    currents_mA: np.ndarray  # (N+1, joints) commanded over the period ending at each sample
    metrics: Metrics
    rmse_floor: float

    @property
    def final_error(self) -> np.ndarray:
        return self.trace.errors[-1]

    @property
    def overshoot(self) -> OvershootAnatomy | None:
        """How the overshoot came about (docs/metrics.md, "Overshoot"); None without one."""
        tr = self.trace
        return overshoot_anatomy(tr.q, tr.qdot, tr.target, tr.dt, self.episode.model.joint_letters)

    def to_dict(self) -> dict[str, Any]:
        out = self.episode.to_dict()
        overshoot = self.overshoot
        out.update(
            reached=self.metrics.reached,
            final_error=self.final_error.tolist(),
            metrics=self.metrics.as_dict(),
            overshoot=None if overshoot is None else overshoot.as_dict(),
            rmse_floor=self.rmse_floor,
        )
        return out


def no_load_speeds(model: ArmModel = ALPHA5) -> np.ndarray:
    return np.asarray(model_no_load_speed(model), dtype=float)


def score(episode: Episode, trace: Trace, currents_mA: np.ndarray) -> EpisodeResult:
    """The one scorer: `reach_driver.metrics` on the true trace, and its RMSE floor.

    The commands go into the trace (unless it has them) so the rest metric counts their
    reversals, whichever backend produced it."""
    if trace.command_mA is None:
        trace = dataclasses.replace(trace, command_mA=np.asarray(currents_mA, dtype=float))
    n = trace.q.shape[0] - 1
    floor = rmse_floor(episode.start, trace.target, no_load_speeds(episode.model), trace.dt, n)
    return EpisodeResult(episode, trace, currents_mA, compute_metrics(trace), floor)


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


class NoisyReadings:
    """A controller that reads through `SensorNoise` (the paper's noisy evaluation).

    Every backend wraps the controller in this, with the episode's own generator, so the
    direct and the via-driver paths see the same noise realisation for the same seed."""

    def __init__(self, inner: Controller, noise: SensorNoise, rng: np.random.Generator) -> None:
        self.inner = inner
        self.noise = noise
        self.rng = rng

    def reset(self) -> None:
        self.inner.reset()

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q, qdot = self.noise.apply(state.q, state.qdot, self.rng)
        return np.asarray(self.inner.act(ControlState(q, qdot, float(state.t)), target))


def reading(controller: Controller, config: RunConfig, episode_seed: int) -> Controller:
    """`controller` as it reads the arm in episode `episode_seed` (noisy if configured)."""
    if config.noise is None:
        return controller
    return NoisyReadings(controller, config.noise, np.random.default_rng(episode_seed))


def check_inside_limits(
    position_limits: np.ndarray, q: np.ndarray, what: str, model: ArmModel = ALPHA5
) -> None:
    """A clear error naming the joints of `q` (of `model`) outside the arm's [min, max]
    limits."""
    limits = np.asarray(position_limits, dtype=float)
    outside = (q < limits[:, 0]) | (q > limits[:, 1])
    if np.any(outside):
        joints = ", ".join(model.joint_letters[j] for j in np.flatnonzero(outside))
        raise ValueError(
            f"{what} {q.tolist()} is outside the arm's joint limits on {joints} ({limits.tolist()})"
        )
