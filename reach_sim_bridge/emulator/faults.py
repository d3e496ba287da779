"""Faults the virtual arm can be asked to show: weak actuators, noisy sensors, a bad link.

The physical faults (torque scale, parameter randomisation) are applied to the arm model;
sensor noise (`reach_sim_bridge.model.sensors`) and stuck readings (`StuckReading`) are
applied to what the firmware reports; link faults (drop, corrupt, latency) are applied to the
outgoing byte stream by the server; a leak (`Leak`) to a housing's climate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from protocol.alpha5 import JOINT_LETTERS as JOINTS
from reach_sim_bridge.model.sensors import (
    SensorNoise,
)


@dataclass(frozen=True)
class FaultConfig:
    """All faults at once; the defaults are a healthy arm on a perfect link."""

    torque_scale: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)  # E D C B
    sensor_noise: SensorNoise | None = None
    randomize_seed: int | None = None
    corrupt_rate: float = 0.0  # probability that each outgoing byte is flipped
    drop_rate: float = 0.0  # probability that each outgoing frame is dropped
    latency_ms: float = 0.0  # added to every outgoing frame (wall clock)

    def __post_init__(self) -> None:
        if len(self.torque_scale) != 4:
            raise ValueError(f"torque_scale needs 4 values (E D C B), got {self.torque_scale}")
        for joint, scale in zip(JOINTS, self.torque_scale, strict=True):
            if not (math.isfinite(scale) and 0.0 <= scale <= 1.0):
                raise ValueError(f"torque scale of joint {joint} must be in [0, 1], got {scale}")
        for name in ("corrupt_rate", "drop_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"{name} is a probability in [0, 1], got {value}")
        if not (math.isfinite(self.latency_ms) and self.latency_ms >= 0.0):
            raise ValueError(f"latency_ms must be a finite number >= 0, got {self.latency_ms}")

    @property
    def link_faults(self) -> bool:
        return self.corrupt_rate > 0.0 or self.drop_rate > 0.0 or self.latency_ms > 0.0


def parse_torque_scale(text: str) -> tuple[int, float]:
    """'D=0.25' -> (index of D in E D C B, 0.25); ValueError says what was wrong."""
    joint, sep, value = text.partition("=")
    joint = joint.strip().upper()
    if not sep or joint not in JOINTS:
        raise ValueError(f"expected JOINT=SCALE with JOINT one of {' '.join(JOINTS)}, got {text!r}")
    try:
        scale = float(value)
    except ValueError:
        raise ValueError(f"torque scale for {joint} is not a number: {value!r}") from None
    if not (math.isfinite(scale) and 0.0 <= scale <= 1.0):
        raise ValueError(f"torque scale for {joint} must be in [0, 1], got {scale}")
    return JOINTS.index(joint), scale


def torque_scales(items: list[str]) -> tuple[float, float, float, float]:
    """Fold repeated JOINT=S options into an E D C B tuple (later options win)."""
    scales = [1.0, 1.0, 1.0, 1.0]
    for item in items:
        index, scale = parse_torque_scale(item)
        scales[index] = scale
    return (scales[0], scales[1], scales[2], scales[3])


class LinkFaults:
    """Drops and corrupts outgoing frames with its own seeded generator (reproducible runs)."""

    def __init__(self, config: FaultConfig, seed: int | None = None) -> None:
        self._drop = config.drop_rate
        self._corrupt = config.corrupt_rate
        self._rng = np.random.default_rng(seed)
        self.dropped_frames = 0
        self.corrupted_bytes = 0

    def apply(self, frame: bytes) -> bytes | None:
        """The frame as it leaves the arm, or None when the link loses it."""
        if self._drop > 0.0 and self._rng.random() < self._drop:
            self.dropped_frames += 1
            return None
        if self._corrupt <= 0.0 or not frame:
            return frame
        hits = np.flatnonzero(self._rng.random(len(frame)) < self._corrupt)
        if hits.size == 0:
            return frame
        damaged = bytearray(frame)
        # XOR with a non-zero mask so every hit really changes the byte.
        masks = self._rng.integers(1, 256, size=hits.size)
        for index, mask in zip(hits.tolist(), masks.tolist(), strict=True):
            damaged[index] ^= mask
        self.corrupted_bytes += int(hits.size)
        return bytes(damaged)


#: Pressure of sea water per metre of depth (bar/m): rho g = 1025 kg/m^3 x 9.81 m/s^2.
BAR_PER_METRE = 0.1006
ATMOSPHERE_BAR = 1.01325


@dataclass(frozen=True)
class Leak:
    """Water getting into one device's housing (the monitor's leak fault).

    Inside the housing, humidity rises towards 100 % and the gas pressure towards the water
    pressure outside, each as a first-order lag with `time_constant_s`: the smaller, the
    bigger the leak. A leak is physical: a RESET does not stop it.
    """

    device_id: int
    time_constant_s: float = 600.0
    depth_m: float = 10.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.time_constant_s) and self.time_constant_s > 0.0):
            raise ValueError(f"leak time constant must be > 0 s, got {self.time_constant_s}")
        if not (math.isfinite(self.depth_m) and self.depth_m >= 0.0):
            raise ValueError(f"leak depth must be a finite number >= 0 m, got {self.depth_m}")

    @property
    def outside_pressure_bar(self) -> float:
        """Absolute water pressure at the housing (bar)."""
        return ATMOSPHERE_BAR + BAR_PER_METRE * self.depth_m


@dataclass(frozen=True)
class StuckReading:
    """A sensor, or the firmware reading it, stuck: from arm time `from_s` on, device
    `device_id` reports `packet_id` (a REQUEST's answer and its heartbeat alike) with the
    very value it reported then, whatever the arm does. The packets keep coming, well formed
    and on time; only their value no longer changes (a velocity estimate that froze while
    the joint moves on, say). Injected with `Firmware.inject_stuck`, or from the start in
    `FirmwareConfig.stuck`."""

    device_id: int
    packet_id: int
    from_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.from_s) and self.from_s >= 0.0):
            raise ValueError(f"a stuck reading starts at an arm time >= 0 s, got {self.from_s}")
