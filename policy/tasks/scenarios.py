"""The paper's four scenarios (Carlucho et al., OCEANS 2020), in the arm's own angles, and
Table I's metrics.

The paper gives joint angles signed around a centred zero (joint 1 = base ... joint 4 =
wrist); the arm reports its own absolute angles. The mapping is explicit and per joint:

    q_arm = q_paper + CENTRE      CENTRE (E D C B) = (pi, 1.71045, pi, pi) rad

E, C and B put the paper's zero at the middle of a 0..2pi-style range (pi); D puts it at the
middle of its factory range 0.0175..3.4034 (pi would push scenario 1's D target to 3.4016,
2 mrad from the end stop). Every scenario target lands inside the arm's limits (checked at
import). Each scenario starts at the paper's zero pose, i.e. q_arm = CENTRE.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from policy.tasks.episodes import Episode
from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINTS
from reach_driver.metrics import metric_label

ARM_LIMITS = np.array([FACTORY_POSITION_LIMITS[d] for d in JOINTS])
"""(4, 2) factory [min, max] per joint, rad, E D C B."""
CENTRE = np.array([math.pi, float(ARM_LIMITS[1].mean()), math.pi, math.pi])
"""Arm angle (rad, E D C B) of the paper's zero for each joint."""
START_PAPER = np.zeros(4)

#: Table I's metrics in its column order (all: lower is better), and their headings.
TABLE_KEYS = ("energy_j", "rmse", "mie", "msse", "overshoot_pct", "settling_time_s")
TABLE_HEADS = tuple(metric_label(k) for k in TABLE_KEYS)  # the names `run` and `inspect` use


def paper_to_arm(q_paper: Sequence[float] | np.ndarray) -> np.ndarray:
    return np.asarray(q_paper, dtype=float) + CENTRE


def arm_to_paper(q_arm: np.ndarray) -> np.ndarray:
    return np.asarray(q_arm, dtype=float) - CENTRE


@dataclass(frozen=True)
class Scenario:
    number: int
    title: str
    paper_target: tuple[float, float, float, float]
    torque_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)

    def episode(self) -> Episode:
        return Episode(
            paper_to_arm(START_PAPER),
            paper_to_arm(self.paper_target),
            np.array(self.torque_scale),
            name=f"scenario {self.number}",
        )


SCENARIOS = (
    Scenario(1, "normal operation", (2.64, 0.26, -1.47, 0.82)),
    Scenario(2, "a different target", (-1.78, 0.11, -2.14, -2.26)),
    Scenario(3, "joint 1 at 25 % torque", (2.0, -1.0, -1.75, 1.5), (0.25, 1.0, 1.0, 1.0)),
    Scenario(4, "RL vs MPC", (2.13, -0.74, -1.03, 2.51)),
)


def check_mapping() -> None:
    """Every scenario's start and target must lie inside the arm's limits."""
    for sc in SCENARIOS:
        for what, q in (
            ("start", paper_to_arm(START_PAPER)),
            ("target", paper_to_arm(sc.paper_target)),
        ):
            if np.any(q < ARM_LIMITS[:, 0]) or np.any(q > ARM_LIMITS[:, 1]):
                raise ValueError(f"scenario {sc.number} {what} {q} is outside the arm's limits")


check_mapping()


def wins(a: dict[str, float], b: dict[str, float]) -> dict[str, bool]:
    """Per Table I metric: is summary `a` strictly better (lower) than `b`?"""
    return {k: a[k] < b[k] for k in TABLE_KEYS}
