"""The training side of the actor weights format (`policy.controllers.weights` defines it).

`save_actor_npz` writes a torch `Actor` as the controller loads it; `load_actor_npz` reads one
back into an `Actor` to fine-tune.
"""

from __future__ import annotations

import json
import os
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.weights import FORMAT, LAYERS, LEAKY_RELU_SLOPE
from policy.rl.config import DDPGConfig
from policy.rl.networks import Actor
from protocol.alpha5 import DEFAULT_CURRENT_LIMITS_MA


def actor_arrays(actor: Actor) -> dict[str, np.ndarray]:
    """The actor's layers as the file stores them: W0 b0 W1 b1 W2 b2, float64."""
    out: dict[str, np.ndarray] = {}
    for i, layer in enumerate(actor.linears()):
        out[f"W{i}"] = layer.weight.detach().cpu().numpy().astype(np.float64)
        out[f"b{i}"] = layer.bias.detach().cpu().numpy().astype(np.float64)
    return out


def save_actor_npz(
    path: str | Path, actor: Actor, config: DDPGConfig, extra: dict[str, Any] | None = None
) -> None:
    """Weights (npz) plus what the controller needs to rebuild inputs and outputs (json)."""
    path = Path(path)
    arrays: dict[str, Any] = dict(actor_arrays(actor))
    meta = {
        "format": FORMAT,
        "layers": LAYERS,
        "leaky_relu_slope": LEAKY_RELU_SLOPE,
        "current_limits_mA": list(DEFAULT_CURRENT_LIMITS_MA),
        "observation": config.env.observation.to_dict(),
        "env": config.env.to_dict(),
        "config": config.to_dict(),
        **(extra or {}),
    }
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
