"""`ddpg`: the torque policy learned by reinforcement learning from scratch, run as trained.

Nothing is wrapped around the network: each period the controller builds the observation the
env built in training (`policy.controllers.observation.InputMemory`: the readings, the
target, and the memory channels the weights ask for, the previous action and a leaky
integral of the error), runs the actor (numpy, no torch) and sends its action times the
current limits. What trained it (algorithm, steps, seed, the command that reproduces it) is in
the weights file's provenance (`reach-driver controllers`, docs/training.md).

An actor drives the arm it was trained on (its file's "arm"): the shipped one an Alpha 5, one
trained with `tools/train.py --arm bravo7` a Bravo 7; an actor for another arm is refused.

    from policy.controllers.ddpg import make_controller
    ctrl = make_controller()                  # shipped weights, policy/controllers/weights/
    ctrl.reset(); currents_mA = ctrl.act(state, target)   # state has .q .qdot (E D C B)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from policy.controllers.observation import InputMemory, Workspace, checked_inputs
from policy.controllers.weights import LEARNED_WEIGHTS, PAPER_WEIGHTS, ActorWeights, provenance_of
from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver.controllers import ControllerModelError, ControlState, drives, learned


class LearnedController:
    """The actor alone: currents (mA, in the arm's joint order) from the readings, the target
    and the network's own memory channels, at the control rate it was trained at
    (`control_hz`). `model`: the arm it drives (None: the actor's); an actor trained for
    another arm is refused (`ControllerModelError`)."""

    def __init__(
        self, weights: ActorWeights, current_limits_mA: Any = None, model: ArmModel | None = None
    ) -> None:
        self.model = weights.model if model is None else model
        if weights.model.name != self.model.name:
            theirs = weights.model
            raise ControllerModelError(
                f"the weights hold an actor for the {theirs.title} ({theirs.n_joints} "
                f"joints), not the {self.model.title}: drive a {theirs.title} with it "
                f"(reach-driver --arm {theirs.name}) or train one for the {self.model.title} "
                f"(tools/train.py --arm {self.model.name})"
            )
        self.weights = weights
        n = self.model.n_joints
        limits = weights.current_limits_mA if current_limits_mA is None else current_limits_mA
        self.current_limits_mA = np.asarray(limits, dtype=np.float64)
        if self.current_limits_mA.shape != (n,) or np.any(self.current_limits_mA < 0):
            raise ValueError(f"current_limits_mA needs {n} values >= 0, got {limits!r}")
        self.control_hz = weights.control_hz
        self.memory = InputMemory(
            weights.observation, 1.0 / self.control_hz, Workspace.of(self.model)
        )

    def reset(self) -> None:
        """Forget the memory channels: a run starts as an episode did in training."""
        self.memory.reset()

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q, qdot, target = checked_inputs(state.q, state.qdot, target, self.model)
        action = self.weights.forward(self.memory.observe(q, qdot, target))
        self.memory.acted(action)
        out: np.ndarray = action * self.current_limits_mA
        return out


@drives(ALPHA5, BRAVO7)
@learned(provenance_of(LEARNED_WEIGHTS, "nothing: the actor alone, with its memory channels"))
def make_controller(
    weights: str | Path | None = None,
    current_limits_mA: Any = None,
    *,
    model: ArmModel = ALPHA5,
) -> LearnedController:
    """Torque policy learned by RL from scratch: no demonstrations, no teacher, nothing around.

    Entry point `ddpg`: the actor of the shipped weights (or those at `weights`), its inputs
    built as in training, its output sent as it is. The shipped actor is an Alpha 5's; on the
    Bravo 7 (`model`) give `weights` of one trained for it (`tools/train.py --arm bravo7`)."""
    path = Path(weights or LEARNED_WEIGHTS)
    try:
        return LearnedController(ActorWeights.load(path), current_limits_mA, model)
    except ControllerModelError as exc:
        raise ControllerModelError(f"{path.name}: {exc}") from None


@learned(provenance_of(PAPER_WEIGHTS, "nothing: the actor alone"))
def make_paper_controller(
    weights: str | Path | None = None, current_limits_mA: Any = None
) -> LearnedController:
    """The paper's DDPG as stated, learned from scratch: its networks, noise, reward, steps.

    Entry point `ddpg-paper`: what the paper's configuration (`tools/train.py --config
    paper-per-joint`) learns on this arm, whatever that is (docs/training.md)."""
    return LearnedController(ActorWeights.load(weights or PAPER_WEIGHTS), current_limits_mA)
