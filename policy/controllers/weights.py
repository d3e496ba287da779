"""The actor weights format, saved by training and loaded by the controller: one owner.

A pair of files: `NAME.npz` holds the dense layers as float64 arrays W0 b0 W1 b1 W2 b2 (W: out x
in, torch's layout), `NAME.json` beside it what the controller needs to rebuild the inputs and
outputs (the arm it drives, "arm": a `protocol.models` name, absent in files written before
it was recorded and then the Alpha 5; observation config, current limits, activation) plus
the run's config and, under
"provenance", how the actor was trained (`Provenance`: algorithm, demonstrations, teacher,
env steps, wall time, seed, command, and every training stage it descends from).

The shipped pairs are `ddpg_actor` (the `ddpg` entry point, learned from scratch) and
`ddpg_distilled_actor` in `policy/controllers/weights/`, the data folder beside this module (it
has no `__init__.py`, so `policy.controllers.weights` is this module). The controller side
(`ActorWeights`) is numpy only: the control loop never imports torch. The training side writes
and reads the same format in `policy.rl.checkpoint`.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import asdict, dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.observation import ObservationConfig
from protocol.files import MAX_WEIGHTS_BYTES, read_bounded, read_json
from protocol.models import ALPHA5, ArmModel, model_named

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DISTILLED_WEIGHTS = WEIGHTS_DIR / "ddpg_distilled_actor.npz"
#: the `ddpg` entry point's weights: the policy learned from scratch (policy.controllers.ddpg)
LEARNED_WEIGHTS = WEIGHTS_DIR / "ddpg_actor.npz"
#: the `ddpg-paper` entry point's: the paper's configuration as stated, trained from scratch
PAPER_WEIGHTS = WEIGHTS_DIR / "ddpg_paper_actor.npz"
#: the control rate of weights whose file does not record the env they were trained in
DEFAULT_CONTROL_HZ = 20.0
#: a training run's folder holding every checkpoint's actor (`CheckpointActor`-STEPS.npz),
#: for reselection on more episodes
CHECKPOINT_ACTORS = "checkpoint-actors"
FORMAT = "reach-stack ddpg actor v1"
LAYERS = ["linear", "leaky_relu", "linear", "leaky_relu", "linear", "tanh"]
#: torch's default slope, what `policy.rl.networks` builds and the json records
LEAKY_RELU_SLOPE = 0.01


#: what `Provenance.demonstrations` and `.teacher` say when there were none
NONE = "none"


@dataclass(frozen=True)
class TrainingStage:
    """One training run in an actor's lineage (a fine-tune starts from the previous stage's
    actor): its run directory's name, what it started from, the env steps and wall time up to
    the checkpoint that was kept, its seed and command. `wall_s` None: not recorded."""

    run: str
    env_steps: int
    wall_s: float | None
    seed: int
    command: str
    init_actor: str | None = None

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainingStage:
        wall = data.get("wall_s")
        return cls(
            run=str(data.get("run", "")),
            env_steps=int(data["env_steps"]),
            wall_s=None if wall is None else float(wall),
            seed=int(data["seed"]),
            command=str(data.get("command", "")),
            init_actor=data.get("init_actor"),
        )


class CheckpointActor(str, Enum):
    """Which actor a checkpoint's file in `CHECKPOINT_ACTORS` holds, named by its file's
    prefix: the one the run keeps (the averaged one with `actor_average_tau`), or the online
    one scored beside an average."""

    KEPT = "actor"
    ONLINE = "online-actor"

    def file(self, env_steps: int) -> str:
        return f"{self.value}-{env_steps:08d}.npz"


@dataclass(frozen=True)
class Provenance:
    """How an actor was trained, said plainly: whether it learned from scratch or imitated a
    teacher is the first thing a user of a "learned" controller needs to know.

    `env_steps` and `wall_s` count every stage of `stages` (the actor's whole lineage);
    `seed` and `command` are the last stage's. `complete` is False when an earlier actor it
    was fine-tuned from has no recorded provenance: the totals then cover the recorded stages
    only, and `note` says what is missing."""

    algorithm: str  #: e.g. "DDPG", "TD3", "TD3 + behaviour cloning (TD3+BC) toward ..."
    demonstrations: str  #: "none", or e.g. "100 episodes of a privileged PD expert"
    teacher: str  #: "none", or the expert the actor imitated and what it could see
    env_steps: int
    wall_s: float
    seed: int
    command: str
    stages: tuple[TrainingStage, ...] = ()
    complete: bool = True
    note: str = ""

    @property
    def from_scratch(self) -> bool:
        """Learned by RL alone: no demonstrations, no teacher, no earlier actor."""
        return (
            self.demonstrations == NONE
            and self.teacher == NONE
            and self.complete
            and all(stage.init_actor is None for stage in self.stages)
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Provenance:
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown provenance fields {sorted(unknown)}")
        return cls(
            algorithm=str(data["algorithm"]),
            demonstrations=str(data["demonstrations"]),
            teacher=str(data["teacher"]),
            env_steps=int(data["env_steps"]),
            wall_s=float(data["wall_s"]),
            seed=int(data["seed"]),
            command=str(data["command"]),
            stages=tuple(TrainingStage.from_dict(s) for s in data.get("stages", ())),
            complete=bool(data.get("complete", True)),
            note=str(data.get("note", "")),
        )


def read_provenance(path: str | Path) -> Provenance | None:
    """The provenance recorded beside the weights at `path` (.npz or .json), None if that
    json has none (files written before it was recorded); the weights are not read."""
    meta_path = Path(path).with_suffix(".json")
    meta = read_json(meta_path, "weights metadata")
    if not isinstance(meta, dict):
        raise ValueError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
    block = meta.get("provenance")
    try:
        return None if block is None else Provenance.from_dict(block)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f"{meta_path}: provenance: {type(exc).__name__}: {exc}") from None


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r:.80}")
    return float(value)


def _read_layers(path: Path) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """W0 b0 .. W(n-1) b(n-1) of an .npz: finite 2-D weights and 1-D biases that chain (a
    ValueError naming the file otherwise, also for a truncated or non-npz file)."""
    data = read_bounded(path, "actor weights", MAX_WEIGHTS_BYTES)
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            n = sum(1 for key in npz.files if key.startswith("W"))
            if n == 0 or any(
                f"W{i}" not in npz.files or f"b{i}" not in npz.files for i in range(n)
            ):
                raise ValueError(f"expected arrays W0 b0 .. W{n - 1} b{n - 1}")
            weights = tuple(np.asarray(npz[f"W{i}"], np.float64) for i in range(n))
            biases = tuple(np.asarray(npz[f"b{i}"], np.float64) for i in range(n))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    except Exception as exc:  # a truncated zip: BadZipFile, EOFError, zlib.error, OSError...
        raise ValueError(f"{path} is not a readable .npz: {type(exc).__name__}: {exc}") from None
    for i, (w, b) in enumerate(zip(weights, biases, strict=True)):
        if w.ndim != 2 or b.ndim != 1 or 0 in w.shape:
            raise ValueError(
                f"{path}: layer {i}: W must be 2-D and b 1-D, got shapes {w.shape}, {b.shape}"
            )
        if b.shape != (w.shape[0],) or (i and w.shape[1] != weights[i - 1].shape[0]):
            raise ValueError(f"{path}: layer {i} shapes do not chain")
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(b))):
            raise ValueError(f"{path}: layer {i} holds NaN or infinite values")
    return weights, biases


def provenance_of(weights: Path, around: str) -> Callable[[], dict[str, Any]]:
    """What `reach-driver controllers` shows for a controller built on the weights at
    `weights`: how they were trained (their json's "provenance") and what the controller adds
    around the network. Read only when asked."""

    def provenance() -> dict[str, Any]:
        recorded = read_provenance(weights)
        if recorded is None:
            raise ValueError(f"{weights.with_suffix('.json')} records no provenance")
        return {**recorded.to_dict(), "weights": weights.name, "around_the_network": around}

    return provenance


@dataclass(frozen=True)
class ActorWeights:
    """Dense layers (W: out x in, b) with LeakyReLU between them and tanh at the end: an actor
    for an arm of `model` (one output per joint)."""

    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    leaky_slope: float
    observation: ObservationConfig
    current_limits_mA: np.ndarray
    metadata: dict[str, Any]
    model: ArmModel = ALPHA5

    @classmethod
    def load(cls, path: str | Path) -> ActorWeights:
        """Read `path` (.npz) and the .json beside it, every field checked here so that a
        file that loads also runs: a ValueError (FileNotFoundError if absent) names the file
        and what is wrong."""
        path = Path(path)
        meta_path = path.with_suffix(".json")
        if not path.is_file():
            raise FileNotFoundError(f"no actor weights at {path}")
        if not meta_path.is_file():
            raise FileNotFoundError(f"no metadata {meta_path} beside the weights {path}")
        meta = read_json(meta_path, "weights metadata")
        if not isinstance(meta, dict):
            raise ValueError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
        if meta.get("format") != FORMAT:
            raise ValueError(f"{meta_path}: unknown weights format {meta.get('format')!r:.80}")
        if meta.get("layers", LAYERS) != LAYERS:
            raise ValueError(f"{meta_path}: layers must be {LAYERS}, got {meta['layers']!r:.80}")
        weights, biases = _read_layers(path)
        if "observation" not in meta:
            raise ValueError(f"{meta_path}: no observation config (key 'observation')")
        try:
            model = model_named(str(meta.get("arm", ALPHA5.name)))  # absent: the Alpha 5
            observation = ObservationConfig.from_dict(meta["observation"])
            limits = np.asarray(meta.get("current_limits_mA", model.current_limits_mA), float)
            slope = _number(meta.get("leaky_relu_slope", LEAKY_RELU_SLOPE), "leaky_relu_slope")
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{meta_path}: {exc}") from None
        n, size = model.n_joints, observation.size_for(model.n_joints)
        if limits.shape != (n,) or not np.all(np.isfinite(limits)) or np.any(limits < 0):
            raise ValueError(
                f"{meta_path}: current_limits_mA needs {n} finite values >= 0 ({model.title})"
            )
        if weights[0].shape[1] != size or weights[-1].shape[0] != n:
            raise ValueError(
                f"{path}: network maps {weights[0].shape[1]} -> {weights[-1].shape[0]}, "
                f"the observation config needs {size} -> {n} ({model.title})"
            )
        try:
            actor = cls(weights, biases, slope, observation, limits, meta, model)
            _ = actor.control_hz, actor.provenance  # what the controller and `controllers` read
            out = actor.forward(np.zeros(size))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{meta_path}: {type(exc).__name__}: {exc}") from None
        if out.shape != (n,) or not np.all(np.isfinite(out)):
            raise ValueError(f"{path}: the network's output at rest is not finite")
        return actor

    def __post_init__(self) -> None:
        # float32, transposed and contiguous: what torch computed, at matmul speed
        object.__setattr__(
            self, "_wt", tuple(np.ascontiguousarray(w.T, dtype=np.float32) for w in self.weights)
        )
        object.__setattr__(self, "_b32", tuple(b.astype(np.float32) for b in self.biases))
        if not 0.0 <= self.leaky_slope < 1.0:
            raise ValueError(f"leaky_relu_slope must be in [0, 1), got {self.leaky_slope}")

    @property
    def control_hz(self) -> float:
        """The control rate the actor was trained at (its env's `control_hz`)."""
        env = self.metadata.get("env") or {}
        hz = float(env.get("control_hz", DEFAULT_CONTROL_HZ)) if isinstance(env, dict) else 0.0
        if not (np.isfinite(hz) and hz > 0):
            raise ValueError(f"weights metadata: control_hz must be > 0, got {hz}")
        return hz

    @property
    def provenance(self) -> Provenance | None:
        """How this actor was trained (None for a file written without it)."""
        block = self.metadata.get("provenance")
        return None if block is None else Provenance.from_dict(block)

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
