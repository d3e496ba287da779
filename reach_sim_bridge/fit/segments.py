"""The logged excitation the fit works on: `Segment` (one joint's motion on the loop's tick
grid), the link's delays measured from the driver's timestamps (`link_delays`), and the
.npz log that keeps segments (`save_segments`, `load_segments`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocol.alpha5 import N_JOINTS

FloatArray = NDArray[np.float64]

MAX_DELAY_S = 0.1


@dataclass(frozen=True)
class Segment:
    """One logged excitation: the loop's tick grid, one row per tick.

    ``command_mA[i]`` is the current the host held over the period ending at sample i (row 0
    is before the first command), as `reach_driver.records.LoopTrace.command_mA`."""

    name: str
    joint: int  # index in E D C B of the joint being excited
    role: str  # "fit" or "validate"
    period: float  # s between ticks
    q: FloatArray  # (n + 1, 4) rad
    qdot: FloatArray  # (n + 1, 4) rad/s
    command_mA: FloatArray  # (n + 1, 4)
    current_mA: FloatArray | None = None  # measured, NaN where not reported
    meta: dict[str, Any] = field(default_factory=dict)
    # Measured part of the transport delay of each command row (arm s; row 0 unused), from
    # the driver's timestamps (`link_delays`); NaN: no command was sent at that tick (the
    # loop was late and skipped it), the row holds the previous one; None: the delay is one
    # constant.
    link_delay_s: FloatArray | None = None
    # The constant added to this segment's delays (s), found by `tune_offsets`: the part of
    # the delay the timestamps cannot see (the least transit, the arm's own step).
    offset_s: float = 0.0
    # The excited joint's angle (rad) and speed (rad/s) at the start of each replay window,
    # added to the readings there: nuisances fitted beside the arm (`fit_joint`'s
    # `fit_starts`), one row per window of the replay that fitted them; None: each window
    # starts from the readings as they are.
    start_fix: FloatArray | None = None
    # A known load the arm held in its jaws for this segment (`ArmParams.payload_kg`,
    # `payload_volume_l`): the replay puts it on the twin. A joint excited with and without
    # one has its torque scale weighed against the load's inertia (docs/identification.md).
    payload_kg: float = 0.0
    payload_volume_l: float = 0.0

    def __post_init__(self) -> None:
        for name in ("q", "qdot", "command_mA"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.ndim != 2 or arr.shape[1] != N_JOINTS or arr.shape[0] < 2:
                raise ValueError(f"segment {self.name}: {name} must be (n+1, 4), got {arr.shape}")
            object.__setattr__(self, name, arr)
        if not self.q.shape == self.qdot.shape == self.command_mA.shape:
            raise ValueError(f"segment {self.name}: q, qdot and command_mA differ in length")
        if not 0 <= self.joint < N_JOINTS:
            raise ValueError(f"segment {self.name}: joint index {self.joint} not in 0..3")
        if self.role not in ("fit", "validate"):
            raise ValueError(f"segment {self.name}: role must be fit or validate")
        if self.link_delay_s is not None:
            d = np.asarray(self.link_delay_s, dtype=float)
            if d.shape != (self.q.shape[0],) or not np.any(np.isfinite(d[1:])):
                raise ValueError(
                    f"segment {self.name}: link_delay_s must be ({self.q.shape[0]},) with a "
                    "finite delay for at least one command"
                )
            object.__setattr__(self, "link_delay_s", d)
        for name in ("payload_kg", "payload_volume_l"):
            value = float(getattr(self, name))
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"segment {self.name}: {name} must be >= 0, got {value}")
            object.__setattr__(self, name, value)
        if self.start_fix is not None:
            fix = np.asarray(self.start_fix, dtype=float)
            if fix.ndim != 2 or fix.shape[1] != 2:
                raise ValueError(f"segment {self.name}: start_fix must be (windows, 2)")
            object.__setattr__(self, "start_fix", fix)

    @property
    def ticks(self) -> int:
        return int(self.q.shape[0] - 1)

    @property
    def seconds(self) -> float:
        return self.ticks * self.period


@dataclass(frozen=True)
class LinkTiming:
    """What the driver's timestamps say about one run's link (`link_delays`)."""

    delays_s: FloatArray  # (n + 1,) arm s from tick i-1 to command row i landing; row 0 NaN
    arm_speed: float  # arm seconds per host second (the lower envelope's slope)
    p50_s: float
    p99_s: float


DELAY_ENVELOPE_S = 0.5
"""Half-width (arm s) of the running minimum that tracks the clock offset (`link_delays`)."""


def _lower_hull_line(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    """(intercept, slope) of the line under every point (x, y) that is closest to them on
    average: the lower convex hull's edge above mean(x) (a two-variable linear program)."""
    hull: list[int] = []
    for i in np.argsort(x, kind="stable"):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            cross = (x[b] - x[a]) * (y[i] - y[a]) - (y[b] - y[a]) * (x[i] - x[a])
            if cross <= 0:
                hull.pop()
            else:
                break
        hull.append(int(i))
    if len(hull) < 2:
        return float(y[hull[0]]), 0.0
    xm = float(np.mean(x))
    for a, b in zip(hull[:-1], hull[1:], strict=True):
        if x[b] >= xm or b == hull[-1]:
            slope = float((y[b] - y[a]) / (x[b] - x[a]))
            return float(y[a] - slope * x[a]), slope
    raise AssertionError("unreachable")


def link_delays(
    t: FloatArray,
    received: FloatArray,
    written: FloatArray,
    envelope_s: float = DELAY_ENVELOPE_S,
) -> LinkTiming:
    """The measured part of each command's transport delay, in arm time, from what the host
    knows: tick k's arm time ``t[k]`` (the heartbeat count), the host time its state was
    complete ``received[k]`` and the host time the command made from it was written
    ``written[k]`` (k = 0 .. n-1; the command is row k + 1 of the segment).

    Why: a fitted constant delay trades off against the armature (both delay the response to a
    current step by a fraction of a tick), and on a loaded host the real delay is not one
    number. The arm's clock is mapped to the host's by the lower envelope of ``received -
    t / speed`` (the least transit seen): its slope gives the arm speed (1 on a real arm,
    `reach-sim --speed` on a virtual one), a running minimum over +-`envelope_s` follows
    offset steps (a simulator that fell behind re-anchors its clock; the minimum looks ahead
    over 2 `envelope_s`). A command written at
    host time w then lands at arm time ``(w - offset) * speed`` plus the least transit and
    whatever the arm itself adds, which is the same for every command: that constant is left
    to the fit. Returns per command row the delay after its tick (row 0 NaN)."""
    t = np.asarray(t, dtype=float)
    received = np.asarray(received, dtype=float)
    written = np.asarray(written, dtype=float)
    if not t.shape == received.shape == written.shape or t.ndim != 1 or t.size < 2:
        raise ValueError("link_delays needs three equal 1-D arrays of at least 2 ticks")
    if not (np.all(np.isfinite(received)) and np.all(np.isfinite(written))):
        raise ValueError("link_delays: timestamps must be finite")
    # received = offset + t / speed + transit: the envelope's slope is 1 / speed.
    _, inv_speed = _lower_hull_line(t, received)
    if not inv_speed > 0:
        raise ValueError("link_delays: the arm's clock does not advance against the host's")
    speed = 1.0 / inv_speed
    offset = received - t * inv_speed
    period = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    half = max(int(round(envelope_s / max(period, 1e-9))), 1)
    # The minimum over the ticks ahead (the last ones share the final window): the offset
    # only ever steps up (a simulator re-anchors later, never earlier), so looking ahead
    # never reaches across a step to the lower offset before it.
    span = min(2 * half + 1, offset.size)
    ahead = np.lib.stride_tricks.sliding_window_view(offset, span).min(axis=1)
    floor = np.concatenate([ahead, np.full(offset.size - ahead.size, ahead[-1])])
    delay = np.maximum((written - floor) * speed - t, 0.0)
    out = np.concatenate([[np.nan], delay])
    return LinkTiming(
        delays_s=out,
        arm_speed=speed,
        p50_s=float(np.percentile(delay, 50)),
        p99_s=float(np.percentile(delay, 99)),
    )


def segment_delays(seg: Segment, extra_s: float = 0.0) -> FloatArray:
    """The delay of each command row the replay uses (s; rows 1..n)."""
    d = np.full(seg.ticks, seg.offset_s + extra_s)
    if seg.link_delay_s is not None:
        d += seg.link_delay_s[1:]
    d = d[np.isfinite(d)]
    return np.clip(d, 0.0, MAX_DELAY_S)


def segment_from_index(
    meta: dict[str, Any],
    q: FloatArray,
    qdot: FloatArray,
    command_mA: FloatArray,
    current_mA: FloatArray | None,
    link_delay_s: FloatArray | None,
) -> Segment:
    """A segment from its index entry (name, joint, role, period, meta: as `save_segments`
    and tools/identify.py's recording write it) and its arrays."""
    return Segment(
        name=meta["name"],
        joint=int(meta["joint"]),
        role=meta["role"],
        period=float(meta["period"]),
        q=q,
        qdot=qdot,
        command_mA=command_mA,
        current_mA=current_mA,
        meta=dict(meta.get("meta", {})),
        link_delay_s=link_delay_s,
        payload_kg=float(meta.get("payload_kg", 0.0)),
        payload_volume_l=float(meta.get("payload_volume_l", 0.0)),
    )


def segment_suffix(payload_kg: float) -> str:
    """What a segment's name adds for the load held in the jaws: "" or "+1kg", so that the
    same wave with and without a load keeps two names."""
    return f"+{payload_kg:g}kg" if payload_kg else ""


def index_entry(seg: Segment) -> dict[str, Any]:
    """A segment's index entry in a log or recording (`segment_from_index` reads it back)."""
    entry: dict[str, Any] = {
        "name": seg.name,
        "joint": seg.joint,
        "role": seg.role,
        "period": seg.period,
        "meta": seg.meta,
    }
    if seg.payload_kg or seg.payload_volume_l:
        entry["payload_kg"] = seg.payload_kg
        entry["payload_volume_l"] = seg.payload_volume_l
    return entry


def load_segments(path: Any) -> list[Segment]:
    """Segments from an `.npz` log written by `save_segments` (tools/identify.py)."""
    import json

    with np.load(path, allow_pickle=False) as data:
        index = json.loads(str(data["index"]))
        out = []
        for i, meta in enumerate(index):
            cur = data[f"s{i}_current_mA"] if f"s{i}_current_mA" in data else None
            link = data[f"s{i}_link_delay_s"] if f"s{i}_link_delay_s" in data else None
            out.append(
                segment_from_index(
                    meta, data[f"s{i}_q"], data[f"s{i}_qdot"], data[f"s{i}_command_mA"], cur, link
                )
            )
    return out


def save_segments(segments: Sequence[Segment], path: Any, header: dict[str, Any]) -> None:
    """One `.npz`: per segment q, qdot, command_mA, current_mA, and a JSON index (name,
    joint, role, period, meta) plus `header` (how the log was made)."""
    import json

    arrays: dict[str, Any] = {}
    index = []
    for i, seg in enumerate(segments):
        arrays[f"s{i}_q"] = seg.q
        arrays[f"s{i}_qdot"] = seg.qdot
        arrays[f"s{i}_command_mA"] = seg.command_mA
        if seg.current_mA is not None:
            arrays[f"s{i}_current_mA"] = np.asarray(seg.current_mA, dtype=float)
        if seg.link_delay_s is not None:
            arrays[f"s{i}_link_delay_s"] = seg.link_delay_s
        index.append(index_entry(seg))
    np.savez_compressed(
        path, index=np.array(json.dumps(index)), header=np.array(json.dumps(header)), **arrays
    )
