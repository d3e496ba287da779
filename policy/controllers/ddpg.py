"""`ddpg`: the torque policy learned by reinforcement learning from scratch, run as trained.

Nothing is wrapped around the network: each period the controller builds the observation the
env built in training (`policy.controllers.observation.InputMemory`: the readings, the
target, and the memory channels the weights ask for, the previous action and a leaky
integral of the error), runs the actor (numpy, no torch) and sends its action times the
current limits. What trained it (algorithm, steps, seed, the command that reproduces it) is in
the weights file's provenance (`reach-driver controllers`, docs/training.md).

    from policy.controllers.ddpg import make_controller
    ctrl = make_controller()                  # shipped weights, policy/controllers/weights/
    ctrl.reset(); currents_mA = ctrl.act(state, target)   # state has .q .qdot (E D C B)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.observation import InputMemory, checked_inputs
from policy.controllers.weights import LEARNED_WEIGHTS, PAPER_WEIGHTS, ActorWeights, provenance_of
from protocol.alpha5 import N_JOINTS
from reach_driver.controllers import ControlState, learned


class LearnedController:
    """The actor alone: currents (mA, E D C B) from the readings, the target and the
    network's own memory channels, at the control rate it was trained at (`control_hz`)."""

    def __init__(self, weights: ActorWeights, current_limits_mA: Any = None) -> None:
        self.weights = weights
        limits = weights.current_limits_mA if current_limits_mA is None else current_limits_mA
        self.current_limits_mA = np.asarray(limits, dtype=np.float64)
        if self.current_limits_mA.shape != (N_JOINTS,) or np.any(self.current_limits_mA < 0):
            raise ValueError(f"current_limits_mA needs 4 values >= 0, got {limits!r}")
        self.control_hz = weights.control_hz
        self.memory = InputMemory(weights.observation, 1.0 / self.control_hz)

    def reset(self) -> None:
        """Forget the memory channels: a run starts as an episode did in training."""
        self.memory.reset()

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q, qdot, target = checked_inputs(state.q, state.qdot, target)
        action = self.weights.forward(self.memory.observe(q, qdot, target))
        self.memory.acted(action)
        out: np.ndarray = action * self.current_limits_mA
        return out


@learned(provenance_of(LEARNED_WEIGHTS, "nothing: the actor alone, with its memory channels"))
def make_controller(
    weights: str | Path | None = None, current_limits_mA: Any = None
) -> LearnedController:
    """Torque policy learned by RL from scratch: no demonstrations, no teacher, nothing around.

    Entry point `ddpg`: the actor of the shipped weights (or those at `weights`), its inputs
    built as in training, its output sent as it is."""
    return LearnedController(ActorWeights.load(weights or LEARNED_WEIGHTS), current_limits_mA)


@learned(provenance_of(PAPER_WEIGHTS, "nothing: the actor alone"))
def make_paper_controller(
    weights: str | Path | None = None, current_limits_mA: Any = None
) -> LearnedController:
    """The paper's DDPG as stated, learned from scratch: its networks, noise, reward, steps.

    Entry point `ddpg-paper`: what the paper's configuration (`tools/train.py --config
    paper-per-joint`) learns on this arm, whatever that is (docs/training.md)."""
    return LearnedController(ActorWeights.load(weights or PAPER_WEIGHTS), current_limits_mA)
