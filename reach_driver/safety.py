"""Safety limits, on by default: what the driver refuses to send and what it softens.

Limits come from the arm (POSITION/VELOCITY/CURRENT_LIMITS) and can only be tightened by
configuration, never widened. A command outside them raises `LimitError` naming the joint,
the limit and where it came from, and is not sent. Near a position bound a soft barrier
scales down currents and velocities that push further out (to zero at the bound), because a
current-mode controller overshooting into a hard stop is how arms get damaged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum

from protocol import Mode, PacketID
from protocol.alpha5 import (
    FACTORY_CURRENT_LIMITS,
    FACTORY_POSITION_LIMITS,
    FACTORY_VELOCITY_LIMITS,
    JAW,
    JOINTS,
    Range,
)
from reach_driver.chatter import ChatterConfig
from reach_driver.errors import LimitError
from reach_driver.state import joint_name


class LimitKind(str, Enum):
    POSITION = "position"
    VELOCITY = "velocity"
    CURRENT = "current"

    @property
    def packet_id(self) -> PacketID:
        return {
            LimitKind.POSITION: PacketID.POSITION_LIMITS,
            LimitKind.VELOCITY: PacketID.VELOCITY_LIMITS,
            LimitKind.CURRENT: PacketID.CURRENT_LIMITS,
        }[self]

    def unit(self, device: int) -> str:
        jaw = device == JAW
        return {
            LimitKind.POSITION: "mm" if jaw else "rad",
            LimitKind.VELOCITY: "mm/s" if jaw else "rad/s",
            LimitKind.CURRENT: "mA",
        }[self]


#: Used only when the arm does not report a limit (reach_sim_bridge/model/README.md).
DEFAULT_LIMITS: dict[LimitKind, Mapping[int, Range]] = {
    kind: {int(d): r for d, r in table.items()}
    for kind, table in (
        (LimitKind.POSITION, FACTORY_POSITION_LIMITS),
        (LimitKind.VELOCITY, FACTORY_VELOCITY_LIMITS),
        (LimitKind.CURRENT, FACTORY_CURRENT_LIMITS),
    )
}


@dataclass(frozen=True)
class SafetyConfig:
    """Tightening of the arm's limits, the barrier, the watchdog and the chatter guard.

    `position_bounds` maps a device to (min, max); `velocity_limits` and `current_limits_mA`
    to a magnitude. `watchdog_s=None` disables the watchdog; `enabled=False` disables the
    limit checks and the barrier (for bench work on a disconnected joint, never a default).
    `chatter` is the control loop's chatter guard (`reach_driver.chatter`, docs/chatter.md):
    a joint bang-banging around its goal ends the run with the arm held; `chatter=None`
    turns it off (identification's relay swings, say). `safe_wait_s` bounds how long the
    end of a command (`ArmClient.make_safe`) keeps sending `safe_mode` and reading the modes
    back until every joint confirms it, a lost link's return included (wall seconds).
    """

    enabled: bool = True
    position_bounds: Mapping[int, Range] = field(default_factory=dict)
    velocity_limits: Mapping[int, float] = field(default_factory=dict)
    current_limits_mA: Mapping[int, float] = field(default_factory=dict)
    position_margin: float = 0.0
    barrier_width: float = 0.1
    watchdog_s: float | None = 0.2
    safe_mode: Mode = Mode.ZERO_VELOCITY
    #: INDEXED_POSITION's reference is not documented, so its target cannot be checked;
    #: only with this set does the gate let it out (finite, to a known joint).
    allow_indexed_position: bool = False
    chatter: ChatterConfig | None = field(default_factory=ChatterConfig)
    safe_wait_s: float = 5.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.safe_wait_s) and self.safe_wait_s >= 0):
            raise ValueError(f"safe_wait_s must be finite and >= 0, got {self.safe_wait_s}")
        if self.barrier_width < 0 or self.position_margin < 0:
            raise ValueError("barrier_width and position_margin must not be negative")
        if self.watchdog_s is not None and self.watchdog_s <= 0:
            raise ValueError(f"watchdog_s must be positive (or None), got {self.watchdog_s}")
        for dev, (lo, hi) in self.position_bounds.items():
            if not lo < hi:
                raise ValueError(f"position bounds for {joint_name(dev)}: min {lo} >= max {hi}")
        for table in (self.velocity_limits, self.current_limits_mA):
            for dev, mag in table.items():
                if not mag > 0:
                    raise ValueError(f"limit for {joint_name(dev)} must be positive, got {mag}")


@dataclass(frozen=True)
class EffectiveLimit:
    """The range in force and the reason, for error messages and `info`."""

    low: float
    high: float
    source: str  # "arm", "default", "arm+config", ...

    def contains(self, value: float) -> bool:
        return self.low <= value <= self.high


def _slack(bound: float) -> float:
    """Float32 rounding of a bound as it crosses the wire (6.143 comes back 6.1430001)."""
    return 1e-6 * max(1.0, abs(bound))


def as_range(kind: LimitKind, values: Range) -> Range:
    """(min, max) from a limits payload in either order; a magnitude reported as [max, 0]
    (velocity, current) is symmetric."""
    lo, hi = sorted(values)
    if kind is not LimitKind.POSITION and lo >= 0:
        lo = -hi
    return (lo, hi)


def envelope_problem(device: int, kind: LimitKind, values: Range) -> str | None:
    """Why a limit cannot be real for this device (not finite, empty, outside the factory
    envelope of `protocol.alpha5`), or None when it is plausible."""
    if not all(math.isfinite(v) for v in values):
        return f"{kind.value} limits {list(values)} are not finite"
    lo, hi = as_range(kind, values)
    if not lo < hi:
        return f"{kind.value} limits [{lo:.4g}, {hi:.4g}] are empty"
    factory = DEFAULT_LIMITS[kind].get(int(device))
    if factory is None:
        return f"{joint_name(device)} has no factory {kind.value} envelope"
    flo, fhi = factory
    if lo < flo - _slack(flo) or hi > fhi + _slack(fhi):
        unit = kind.unit(device)
        return (
            f"{kind.value} limits [{lo:.4g}, {hi:.4g}] {unit} of {joint_name(device)} leave "
            f"the factory envelope [{flo:.4g}, {fhi:.4g}] {unit}"
        )
    return None


class SafetyGuard:
    """Checks commands against the effective limits; holds no connection of its own."""

    def __init__(self, config: SafetyConfig | None = None) -> None:
        self.config = config or SafetyConfig()
        self._arm: dict[tuple[LimitKind, int], Range] = {}
        self.barrier_cuts = 0

    def set_arm_limit(self, device: int, kind: LimitKind, value: Range) -> None:
        """Adopt a limit the arm reported (the caller checked it with `envelope_problem`)."""
        self._arm[(kind, int(device))] = as_range(kind, value)

    def present_limit(self, device: int, kind: LimitKind) -> Range | None:
        """The arm's limit as adopted, else the documented default; None for no device."""
        dev = int(device)
        return self._arm.get((kind, dev)) or DEFAULT_LIMITS[kind].get(dev)

    def has_arm_limit(self, device: int, kind: LimitKind) -> bool:
        return (kind, int(device)) in self._arm

    def limit(self, device: int, kind: LimitKind) -> EffectiveLimit:
        dev = int(device)
        base = self._arm.get((kind, dev))
        source = "arm"
        if base is None:
            base = DEFAULT_LIMITS[kind].get(dev)
            source = "default"
        if base is None:
            return EffectiveLimit(-math.inf, math.inf, "none")
        lo, hi = base
        cfg = self.config
        tightened = False
        if kind is LimitKind.POSITION:
            if cfg.position_margin:
                lo, hi = lo + cfg.position_margin, hi - cfg.position_margin
                tightened = True
            if dev in cfg.position_bounds:
                clo, chi = cfg.position_bounds[dev]
                lo, hi = max(lo, clo), min(hi, chi)
                tightened = True
        else:
            table = cfg.velocity_limits if kind is LimitKind.VELOCITY else cfg.current_limits_mA
            if dev in table:
                lo, hi = max(lo, -table[dev]), min(hi, table[dev])
                tightened = True
        if lo > hi:
            mid = 0.5 * (lo + hi)
            lo = hi = mid
        return EffectiveLimit(lo, hi, source + ("+config" if tightened else ""))

    def position_limits(self) -> list[tuple[float, float]]:
        """[min, max] of E D C B in force (rad): what a tool position is solved within."""
        return [(lim.low, lim.high) for lim in (self.limit(d, LimitKind.POSITION) for d in JOINTS)]

    def check(self, device: int, kind: LimitKind, value: float) -> None:
        """Raise `LimitError` if `value` is outside the effective limit (never clips)."""
        if not self.config.enabled:
            return
        if not math.isfinite(value):
            raise LimitError(
                f"refused: {kind.value} {value} for {joint_name(device)} is not finite; "
                "nothing was sent"
            )
        lim = self.limit(device, kind)
        if not lim.contains(value):
            unit = kind.unit(device)
            raise LimitError(
                f"refused: {kind.value} {value:.4g} {unit} for joint {joint_name(device)} is "
                f"outside its {kind.value} limit [{lim.low:.4g}, {lim.high:.4g}] {unit} "
                f"({lim.source}); nothing was sent"
            )

    def barrier_scale(self, device: int, position: float, direction: float) -> float:
        """Factor in [0, 1] for an output pushing in `direction` (sign) from `position`.

        1 away from the bounds or when pushing inward, falling linearly to 0 over
        `barrier_width` before the bound it pushes towards, and 0 beyond it.
        """
        cfg = self.config
        if not cfg.enabled or direction == 0 or not math.isfinite(position):
            return 1.0
        lim = self.limit(device, LimitKind.POSITION)
        room = lim.high - position if direction > 0 else position - lim.low
        if cfg.barrier_width <= 0:
            return 1.0 if room > 0 else 0.0
        return min(1.0, max(0.0, room / cfg.barrier_width))

    def soften(self, device: int, position: float | None, value: float) -> float:
        """A current or velocity after the barrier; refuses when the position is unknown."""
        if not self.config.enabled or value == 0:
            return value
        if position is None or not math.isfinite(position):
            raise LimitError(
                f"refused: position of joint {joint_name(device)} is unknown, so its position "
                "limit cannot be enforced; read or stream POSITION first; nothing was sent"
            )
        scale = self.barrier_scale(device, position, value)
        if scale < 1.0:
            self.barrier_cuts += 1
        return value * scale
