"""Chatter: a joint caught in a sustained limit cycle around its goal (docs/chatter.md).

A controller can keep every command inside the limits and still bang-bang a joint across its
goal at full speed for as long as it is left running (the distilled actor without its settle
supervisor, `ddpg-distilled --param settle=0`, does this on a few per cent of degraded arms,
docs/results.md). Neither the limits nor the watchdog see it. The detector here does, from
the streams the control loop already has: per joint the error to the target, the speed, the
commanded current and the loop time.

Definition (per joint, one sample per control step):

- a step is *strong* when the joint is inside the band (``|target - q| < band_rad``), its
  command is at least ``current_fraction`` of its current limit and it moves at least
  ``min_speed_rad_s``;
- a *reversal* is a strong step whose command has the opposite sign of the joint's previous
  strong step;
- reversals no more than ``max_gap_s`` apart form one *cycle*; a longer gap ends it, and so
  does leaving the band (the cycle must stay near the goal) or a new target;
- the detector fires when one joint's cycle has lasted ``sustain_s`` seconds of loop time
  (from its first reversal to its latest).

An arrival that rings and then settles is a cycle too; ``sustain_s`` is set above the longest
such ring measured (docs/chatter.md).

It is pure (no I/O, no clock of its own, no driver state), so `reach_driver.control` runs it
on line and `tools/screen_chatter.py` runs the same code over recorded traces.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import InitVar, dataclass
from enum import Enum

import numpy as np

from protocol.models import ALPHA5

__all__ = ["ChatterConfig", "ChatterDetector", "HoldMode", "Verdict"]


class HoldMode(str, Enum):
    """How the driver holds the arm once the guard fires."""

    POSITION = "position"  # the arm's own position loop, at the angles it had when it fired
    ZERO_VELOCITY = "zero_velocity"  # the arm's ZERO_VELOCITY mode (holds where it stops)


@dataclass(frozen=True)
class ChatterConfig:
    """The guard's thresholds (the data behind them: docs/chatter.md)."""

    band_rad: float = 0.05
    """Only errors smaller than this count: the cycle is near the goal."""
    current_fraction: float = 0.3
    """Only commands of at least this fraction of the joint's current limit count."""
    min_speed_rad_s: float = 0.3
    """Only steps moving at least this fast count (a quarter of the no-load speed)."""
    max_gap_s: float = 0.25
    """Reversals further apart than this (loop time) are not one cycle."""
    sustain_s: float = 5.0
    """Fire once a cycle has lasted this long."""
    hold: HoldMode = HoldMode.POSITION
    """What the driver does when it fires."""

    def __post_init__(self) -> None:
        for name in ("band_rad", "min_speed_rad_s", "max_gap_s", "sustain_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"chatter {name} must be positive, got {value}")
        if not 0 < self.current_fraction <= 1:
            raise ValueError(
                f"chatter current_fraction must be in (0, 1], got {self.current_fraction}"
            )
        object.__setattr__(self, "hold", HoldMode(self.hold))


@dataclass(frozen=True)
class Verdict:
    """Why the detector fired: one joint's limit cycle, as measured over its reversals.
    `letters` names the arm's joints (the Alpha 5's by default); not a field, so a verdict
    reads as it always has."""

    joint: int  # index in the arm's joint order (E D C B on the Alpha 5)
    t: float  # loop time of the reversal that fired it (s)
    reversals: int
    span_s: float  # from the first counted reversal to the last
    max_error_rad: float  # largest |error| at the counted reversals
    mean_speed_rad_s: float  # mean |qdot| at them
    mean_current_mA: float  # mean |command| at them
    letters: InitVar[tuple[str, ...]] = ALPHA5.joint_letters

    def __post_init__(self, letters: tuple[str, ...]) -> None:
        object.__setattr__(self, "_letters", tuple(letters))

    @property
    def letter(self) -> str:
        letters: tuple[str, ...] = getattr(self, "_letters", ALPHA5.joint_letters)
        return letters[self.joint]

    def describe(self) -> str:
        return (
            f"joint {self.letter} reversed {self.reversals} times in {self.span_s:.2f} s at "
            f"+-{1000 * self.max_error_rad:.0f} mrad from its goal "
            f"({self.mean_speed_rad_s:.2f} rad/s, +-{self.mean_current_mA:.0f} mA)"
        )


@dataclass
class _Joint:
    sign: float = 0.0  # sign of the last strong command, 0 for none
    start: float = math.nan  # loop time of the cycle's first reversal (NaN: no cycle)
    last: float = math.nan  # ... and of its latest
    reversals: int = 0
    max_error: float = 0.0
    speed_sum: float = 0.0
    current_sum: float = 0.0

    def forget(self) -> None:
        self.sign = 0.0
        self.start = self.last = math.nan

    def reversal(self, t: float, err: float, speed: float, current: float, gap: float) -> None:
        if not t - self.last <= gap:  # the first reversal, or a gap too long: a new cycle
            self.start, self.reversals = t, 0
            self.max_error = self.speed_sum = self.current_sum = 0.0
        self.last = t
        self.reversals += 1
        self.max_error = max(self.max_error, err)
        self.speed_sum += speed
        self.current_sum += current

    @property
    def span(self) -> float:
        return 0.0 if math.isnan(self.start) else self.last - self.start


class ChatterDetector:
    """`update` once per control step; returns the `Verdict` from the step it fires on (and
    the same verdict on every later step, until `reset`)."""

    def __init__(
        self,
        config: ChatterConfig,
        current_limits_mA: Sequence[float] | np.ndarray,
        letters: Sequence[str] = ALPHA5.joint_letters,
    ) -> None:
        self.letters = tuple(letters)  # the arm's joints, in its order
        n = len(self.letters)
        limits = np.abs(np.asarray(current_limits_mA, dtype=float).reshape(-1))
        if limits.shape != (n,) or not np.all(np.isfinite(limits) & (limits > 0)):
            raise ValueError(
                f"need {n} positive current limits ({' '.join(self.letters)}), got "
                f"{current_limits_mA}"
            )
        self.config = config
        self.threshold_mA = config.current_fraction * limits
        self._joints = [_Joint() for _ in range(n)]
        self._target: np.ndarray | None = None
        self.verdict: Verdict | None = None
        self.longest_s = 0.0
        """The longest cycle of any joint so far, in seconds (the margin to `sustain_s`,
        for screens)."""
        self.reset()

    def reset(self) -> None:
        for j in self._joints:
            j.forget()
        self._target = None
        self.verdict = None
        self.longest_s = 0.0

    def update(
        self,
        t: float,
        q: Sequence[float] | np.ndarray,
        qdot: Sequence[float] | np.ndarray,
        command_mA: Sequence[float] | np.ndarray,
        target: Sequence[float] | np.ndarray,
    ) -> Verdict | None:
        if self.verdict is not None:
            return self.verdict
        goal = np.asarray(target, dtype=float).reshape(-1)
        if self._target is None or not np.array_equal(goal, self._target):
            for j in self._joints:
                j.forget()
            self._target = goal.copy()
        err = np.abs(goal - np.asarray(q, dtype=float).reshape(-1))
        speed = np.abs(np.asarray(qdot, dtype=float).reshape(-1))
        u = np.asarray(command_mA, dtype=float).reshape(-1)
        cfg = self.config
        for i, joint in enumerate(self._joints):
            if not err[i] < cfg.band_rad:  # outside the band, or NaN
                joint.forget()
                continue
            if not (abs(u[i]) >= self.threshold_mA[i] and speed[i] >= cfg.min_speed_rad_s):
                continue
            sign = math.copysign(1.0, u[i])
            reversed_ = joint.sign != 0.0 and sign != joint.sign
            joint.sign = sign
            if not reversed_:
                continue
            joint.reversal(
                float(t), float(err[i]), float(speed[i]), abs(float(u[i])), cfg.max_gap_s
            )
            self.longest_s = max(self.longest_s, joint.span)
            if joint.span >= cfg.sustain_s - 1e-9:
                self.verdict = Verdict(
                    joint=i,
                    t=float(t),
                    reversals=joint.reversals,
                    span_s=joint.span,
                    max_error_rad=joint.max_error,
                    mean_speed_rad_s=joint.speed_sum / joint.reversals,
                    mean_current_mA=joint.current_sum / joint.reversals,
                    letters=self.letters,
                )
                return self.verdict
        return None
