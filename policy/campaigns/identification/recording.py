"""The records of an excitation run beside its .npz log: the driver's timestamps of each step
(`StepStamps`, from which the link's delays are measured) and the Rerun recording
(`ExcitationRecorder`, read back by `load_recording`)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from protocol.alpha5 import N_JOINTS
from reach_driver import DriverError
from reach_driver.records import StepRecord
from reach_sim_bridge.fit.segments import (
    LinkTiming,
    Segment,
    index_entry,
    link_delays,
    segment_from_index,
)


@dataclass
class StepStamps:
    """The driver's timestamps of each step of one run (`ControlLoop`'s `on_step`): the arm
    time of the tick, the host time its state was complete and the host time the command
    was written (the hook runs right after the write)."""

    t: list[float] = field(default_factory=list)
    received: list[float] = field(default_factory=list)
    written: list[float] = field(default_factory=list)
    latency: list[float] = field(default_factory=list)
    state_age: list[float] = field(default_factory=list)
    good: list[int] = field(default_factory=list)
    bad: list[int] = field(default_factory=list)

    def on_step(self, r: StepRecord) -> None:
        now = time.monotonic()
        self.t.append(r.t)
        self.written.append(now)
        self.received.append(now - r.latency_s)
        self.latency.append(r.latency_s)
        self.state_age.append(r.state_age_s)
        self.good.append(r.good_frames)
        self.bad.append(r.bad_frames)

    def timing(self, trace_t: np.ndarray, dt: float) -> LinkTiming | None:
        """The measured delays per command row of a trace on the tick grid `dt` (None with
        fewer than two steps: the delay is then left to the fit alone). A tick the loop
        skipped (it was late and took the newer state) sent no command: its row holds the
        previous command and is NaN (the replay lands it with the one before)."""
        if len(self.t) < 2:
            return None
        t = np.asarray(self.t)
        measured = link_delays(t, np.asarray(self.received), np.asarray(self.written))
        n = len(trace_t) - 1
        rows = np.rint(t / dt).astype(int) + 1  # the command sent at tick k is row k + 1
        delays = np.full(n + 1, np.nan)
        keep = (rows >= 1) & (rows <= n)
        delays[rows[keep]] = measured.delays_s[1:][keep]
        return replace(measured, delays_s=delays)  # NaN: a skipped tick, no command sent


class ExcitationRecorder:
    """The excitation as a Rerun recording (.rrd), written with `reach_driver.recording` (the
    entities `reach-driver run --record` writes, so `reach-driver inspect` and the viewer
    read it): every tick of every segment on one arm-time timeline, an event where each
    segment starts, the link's latency and state age per step, and at the end a summary whose
    `segments` index (name, joint, role, first step, rows, measured link delays) lets
    `load_recording` rebuild the segments exactly. The file is opened before the arm moves
    (an unwritable path fails first) and the segments, from their traces (the rows the fit
    uses), are logged when the excitation ends or stops (Ctrl-C, an error): encoding them
    while the control loop runs took CPU from it on a loaded 2-core host. A write error is
    reported once and stops the recording; the identification goes on (the .npz log is the
    fit's own copy)."""

    def __init__(self, path: Path, metadata: dict[str, Any], console: Console) -> None:
        from reach_driver import recording

        self._recording = recording
        self.path = path
        self.console = console
        self.failed: str | None = None
        self.index: list[dict[str, Any]] = []
        self.step = 0
        self._pending: list[tuple[Segment, np.ndarray, float, StepStamps]] = []
        try:
            self._rec: Any = recording.RunRecorder(
                path,
                metadata={"source": "tools/identify.py", **metadata},
                warn=lambda msg: console.print(f"[yellow]warning[/]: {msg}"),
            )
            self._rec.log_event("start")
        except Exception as exc:  # rerun raises RuntimeError for sink errors, Python OSError
            raise DriverError(f"cannot record to {path}: {exc}") from None

    def _fail(self, exc: Exception) -> None:
        rec, self._rec = self._rec, None
        self.failed = f"writing {self.path} failed: {type(exc).__name__}: {exc}"
        self.console.print(
            f"[yellow]warning[/]: {self.failed}; recording stopped, the identification goes on"
        )
        if rec is not None:
            try:
                rec.abandon()
            except Exception:
                pass

    def add(self, seg: Segment, center: np.ndarray, t0: float, stamps: StepStamps) -> None:
        """Keep one finished segment (from arm time `t0` on) for `close` to log."""
        self._pending.append((seg, center, t0, stamps))

    def _log(self, seg: Segment, center: np.ndarray, t0: float, stamps: StepStamps) -> None:
        """Log one segment (its ticks are rows 0..n)."""
        rec = self._rec
        if rec is None:
            return
        recording = self._recording
        n = seg.ticks
        current = seg.current_mA if seg.current_mA is not None else np.full_like(seg.q, np.nan)
        try:
            rec.log_event(
                f"segment {seg.name} ({seg.role}): {seg.meta.get('wave', '')}", t=t0, step=self.step
            )
            for k in range(n + 1):
                t = t0 + k * seg.period
                rec.log_step(
                    recording.StepSample(
                        t=t,
                        step=self.step + k,
                        q=seg.q[k],
                        qdot=seg.qdot[k],
                        target=center,
                        current_cmd_mA=seg.command_mA[k + 1] if k < n else np.zeros(N_JOINTS),
                        current_meas_mA=current[k],
                    )
                )
                if k < len(stamps.t):
                    rec.log_link(
                        t,
                        self.step + k,
                        stamps.good[k],
                        stamps.bad[k],
                        stamps.state_age[k],
                        stamps.latency[k],
                    )
        except Exception as exc:
            self._fail(exc)
            return
        self.index.append(
            {
                **index_entry(seg),
                "first_step": self.step,
                "rows": n + 1,
                "t0": t0,
                "command_row0": seg.command_mA[0].tolist(),
                "link_delay_s": None
                if seg.link_delay_s is None
                else [None if not math.isfinite(v) else v for v in seg.link_delay_s.tolist()],
            }
        )
        self.step += n + 1

    def close(self, header: dict[str, Any]) -> None:
        """Log the segments kept, the index and the end; close the file."""
        for item in self._pending:
            self._log(*item)
        self._pending.clear()
        rec = self._rec
        if rec is None:
            return
        try:
            rec.log_summary({"identification": header, "segments": self.index})
            rec.log_event("stop")
            rec.close()
            self._rec = None
        except Exception as exc:
            self._fail(exc)


def load_recording(path: Path) -> list[Segment]:
    """The segments of an excitation recorded by `ExcitationRecorder` (ValueError saying what
    is missing: a recording cut before its end has its steps but no index)."""
    from reach_driver.rrd_summary import read_recording

    run = read_recording(path)
    index = run.summary.get("segments") if isinstance(run.summary, dict) else None
    if not isinstance(index, list) or not index:
        raise ValueError(
            f"{path}: no identification index (not written by identify.py, or cut before the "
            f"excitation ended; its .npz log has the finished segments)"
        )
    rows_at = {int(s): i for i, s in enumerate(run.step)}
    out = []
    for meta in index:
        first, rows = int(meta["first_step"]), int(meta["rows"])
        try:
            sel = np.array([rows_at[first + k] for k in range(rows)])
        except KeyError as exc:
            raise ValueError(f"{path}: segment {meta['name']} lacks step {exc}") from None
        if run.qdot is None:
            raise ValueError(f"{path}: no velocities recorded")
        command = np.empty((rows, N_JOINTS))
        command[0] = meta["command_row0"]
        command[1:] = run.current_cmd[sel[:-1]]
        delays = meta.get("link_delay_s")
        out.append(
            segment_from_index(
                meta,
                run.q[sel],
                run.qdot[sel],
                command,
                run.current_meas[sel],
                None
                if delays is None
                else np.array([np.nan if v is None else v for v in delays], dtype=float),
            )
        )
    return out
