"""The training side of the actor weights format (`policy.controllers.weights` defines it).

`save_actor_npz` writes a torch `Actor` as the controller loads it, with how it was trained
(`provenance`); `load_actor_npz` reads one back into an `Actor` to fine-tune.
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.weights import (
    FORMAT,
    LAYERS,
    LEAKY_RELU_SLOPE,
    NONE,
    Provenance,
    TrainingStage,
    read_provenance,
)
from policy.rl.config import Algorithm, DDPGConfig
from policy.rl.networks import Actor


def actor_arrays(actor: Actor) -> dict[str, np.ndarray]:
    """The actor's layers as the file stores them: W0 b0 W1 b1 W2 b2, float64."""
    out: dict[str, np.ndarray] = {}
    for i, layer in enumerate(actor.linears()):
        out[f"W{i}"] = layer.weight.detach().cpu().numpy().astype(np.float64)
        out[f"b{i}"] = layer.bias.detach().cpu().numpy().astype(np.float64)
    return out


#: the demonstrator of `policy.rl.expert`, and what it reads that the actor never sees
TEACHER = "PDExpert (privileged: true state, masses, torque scale)"


def algorithm(config: DDPGConfig) -> str:
    """What the config trains: SAC; DDPG, or TD3 if any of its three changes is on, with
    CrossQ's critic where set; + behaviour cloning when the actor loss imitates the
    teacher."""
    if config.algorithm is Algorithm.SAC:
        critics = "twin critics" if config.twin_critics else "one critic"
        return f"SAC ({critics}, learned temperature; the mean action is the policy)"
    plain = not config.twin_critics and config.policy_delay == 1 and config.target_noise == 0
    name = "DDPG" if plain else "TD3"
    if config.crossq_critic:
        name += " with CrossQ's critic (batch renormalisation, no target networks)"
    if config.bc_weight > 0:
        name += (
            f" + behaviour cloning toward the teacher (weight {config.bc_weight:g} -> "
            f"{config.bc_weight_final:g})"
        )
    return name


def _with_earlier(this: str, earlier: str) -> str:
    return this if earlier == this else f"{this}; earlier stages: {earlier}"


def provenance(config: DDPGConfig, stage: TrainingStage) -> Provenance:
    """How an actor trained by `config` up to `stage` was made. A fine-tune (`init_actor`)
    carries the provenance of the actor it started from: its stages come first and count in
    the totals; an `init_actor` without one makes the provenance incomplete, and says so."""
    demos = config.demo_episodes
    this = Provenance(
        algorithm=algorithm(config),
        demonstrations=(
            f"{demos} episode{'s' if demos != 1 else ''} of a privileged PD expert"
            if demos > 0
            else NONE
        ),
        teacher=TEACHER if config.bc_weight > 0 or demos > 0 else NONE,
        env_steps=stage.env_steps,
        wall_s=round(stage.wall_s or 0.0, 1),
        seed=stage.seed,
        command=stage.command,
        stages=(stage,),
    )
    if config.init_actor is None:
        return this
    try:
        earlier = read_provenance(config.init_actor)
    except (OSError, ValueError):
        earlier = None
    if earlier is None:
        return replace(
            this,
            complete=False,
            note=f"fine-tuned from {config.init_actor}, which records no provenance: the "
            "totals cover this stage only",
        )
    return replace(
        this,
        algorithm=_with_earlier(this.algorithm, earlier.algorithm),
        demonstrations=_with_earlier(this.demonstrations, earlier.demonstrations),
        teacher=_with_earlier(this.teacher, earlier.teacher),
        env_steps=earlier.env_steps + this.env_steps,
        wall_s=round(earlier.wall_s + this.wall_s, 1),
        stages=(*earlier.stages, stage),
        complete=earlier.complete,
        note=earlier.note,
    )


def save_actor_npz(
    path: str | Path,
    actor: Actor,
    config: DDPGConfig,
    extra: dict[str, Any] | None = None,
    stage: TrainingStage | None = None,
) -> None:
    """Weights (npz) plus what the controller needs to rebuild inputs and outputs (json), and
    for a trained actor (`stage`: the run, env steps and wall time so far, seed, command) its
    provenance."""
    path = Path(path)
    arrays: dict[str, Any] = dict(actor_arrays(actor))
    model = config.env.model
    meta = {
        "format": FORMAT,
        "arm": model.name,
        "layers": LAYERS,
        "leaky_relu_slope": LEAKY_RELU_SLOPE,
        "current_limits_mA": list(model.current_limits_mA),
        "observation": config.env.observation.to_dict(),
        "env": config.env.to_dict(),
        "config": config.to_dict(),
        **(extra or {}),
    }
    if stage is not None:
        meta["env_steps"] = stage.env_steps
        meta["wall_s"] = stage.wall_s
        meta["provenance"] = provenance(config, stage).to_dict()
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1, default=_json_default))


def load_actor_npz(actor: Actor, path: str | Path) -> None:
    """Copy the layers of `path` (.npz only; the json is not needed) into `actor`."""
    import torch  # here, not at the top: the controller side loads without torch

    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    linears = actor.linears()
    hidden = tuple(layer.out_features for layer in linears[:-1])
    for i, layer in enumerate(linears):
        w, b = arrays.get(f"W{i}"), arrays.get(f"b{i}")
        if (
            w is None
            or b is None
            or w.shape != tuple(layer.weight.shape)
            or b.shape != tuple(layer.bias.shape)
        ):
            raise ValueError(
                f"{path}: layer {i} does not fit a {hidden} actor "
                f"with {linears[0].in_features} inputs"
            )
        with torch.no_grad():
            layer.weight.copy_(torch.from_numpy(w))
            layer.bias.copy_(torch.from_numpy(b))


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Enum):
        return obj.value
    raise TypeError(f"not JSON serialisable: {type(obj)}")
