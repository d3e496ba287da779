"""The joints' sensors: Gaussian noise on what each reports.

A fact of the arm's model, not of the emulator: training, rollouts and the virtual firmware all
draw the same noise from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Default standard deviations (position rad or mm, velocity rad/s or mm/s): about a tenth of a
# degree and one degree per second, well above an encoder's quantisation so the effect on a
# controller is visible. The same values are the paper's noisy evaluation (Table I) and
# `reach-sim --sensor-noise` without a value: noise means one thing everywhere.
DEFAULT_POSITION_NOISE = 0.002
DEFAULT_VELOCITY_NOISE = 0.02


@dataclass(frozen=True)
class SensorNoise:
    """Gaussian noise on reported position and velocity, in each device's own units."""

    position_std: float = DEFAULT_POSITION_NOISE
    velocity_std: float = DEFAULT_VELOCITY_NOISE

    def __post_init__(self) -> None:
        for name in ("position_std", "velocity_std"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"sensor noise {name} must be a finite number >= 0, got {value}")

    def scaled(self, factor: float) -> SensorNoise:
        """Both standard deviations times `factor` (a run's `noise_scale`)."""
        return SensorNoise(self.position_std * factor, self.velocity_std * factor)

    def apply(
        self, q: np.ndarray, qdot: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noisy copies of `q` and `qdot` (position noise drawn first, then velocity)."""
        q = np.asarray(q, dtype=np.float64)
        qdot = np.asarray(qdot, dtype=np.float64)
        return (
            q + rng.normal(0.0, self.position_std, q.shape),
            qdot + rng.normal(0.0, self.velocity_std, qdot.shape),
        )
