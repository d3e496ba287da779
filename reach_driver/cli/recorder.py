"""`run --record`: the control loop's steps and summary into a Rerun recording.

Recording never stops control: the first write error (a full disk, a removed drive, rerun's
file sink gone) is reported once, recording stops there, and the run goes on as planned; what
was written before the error stays readable (`reach-driver inspect`). `failed` says why, so
the run can end with its own exit status (`Exit.RECORDING_INCOMPLETE`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console
from rich.markup import escape

from reach_driver.cli.report import summary_dict
from reach_driver.errors import DriverError
from reach_driver.records import ControlSummary, StepRecord

if TYPE_CHECKING:
    from reach_driver.recording import RunRecorder


def _free_space(path: Path) -> str:
    try:
        st = os.statvfs(path.parent if str(path.parent) else ".")
    except OSError:
        return ""
    return f"; {st.f_bavail * st.f_frsize / 1e6:.1f} MB free on its filesystem"


class CliRecorder:
    """The hooks `run` gives the control loop (`on_step`) and calls at its end (`finish`)."""

    def __init__(self, path: str, meta: dict[str, object], warn: Console | None = None) -> None:
        """Opens the recording; fails (DriverError) before anything moves if it cannot."""
        try:
            from reach_driver import recording
        except ImportError as exc:
            raise DriverError(
                f"--record needs reach_driver.recording, which failed to import: {exc}"
            ) from None
        self._recording = recording
        self.path = path
        self._warn = warn or Console(stderr=True, highlight=False)
        self.failed: str | None = None
        self.steps = 0
        try:
            self._rec: RunRecorder | None = recording.RunRecorder(path, metadata=meta)
            self._rec.log_event("start")
        except Exception as exc:  # rerun raises RuntimeError for sink errors, Python OSError
            raise DriverError(f"cannot record to {path}: {exc}{_free_space(Path(path))}") from None

    def _fail(self, exc: Exception, where: str) -> None:
        """The first write error: say so once, stop recording, keep the run going."""
        rec, self._rec = self._rec, None
        self.failed = (
            f"writing {self.path} failed {where}: {type(exc).__name__}: {exc}"
            f"{_free_space(Path(self.path))}"
        )
        self._warn.print(
            f"[yellow]warning[/]: recording failed, recording stopped, the run goes on: "
            f"{escape(self.failed)}",
            soft_wrap=True,
        )
        if rec is not None:
            try:
                rec.abandon()
            except Exception:  # the sink is broken already; nothing more to save
                pass

    def on_step(self, r: StepRecord) -> None:
        rec = self._rec
        if rec is None:
            return
        recording = self._recording
        try:
            rec.log_step(
                recording.StepSample(
                    t=r.t,
                    step=r.step,
                    q=r.q,
                    qdot=r.qdot,
                    target=r.target,
                    current_cmd_mA=r.command_mA,
                    current_meas_mA=r.current_mA,
                    torque_Nm=r.torque_Nm,
                )
            )
            rec.log_link(r.t, r.step, r.good_frames, r.bad_frames, r.state_age_s)
            self.steps += 1
        except Exception as exc:
            self._fail(exc, f"at step {r.step} (t = {r.t:.2f} s; {self.steps} steps recorded)")

    def finish(self, summary: ControlSummary | None, error: str | None) -> None:
        rec = self._rec
        if rec is None:
            return
        recording = self._recording
        try:
            if summary is not None and summary.trace is not None and summary.steps:
                # The state that ended the run, so the recording scores like the printed metrics.
                tr = summary.trace
                rec.log_step(
                    recording.StepSample(
                        t=float(tr.t[-1]),
                        step=summary.steps,
                        q=tr.q[-1],
                        qdot=tr.qdot[-1],
                        target=summary.target,
                        current_cmd_mA=np.zeros(4),
                        current_meas_mA=tr.current_mA[-1],
                        torque_Nm=tr.torque_Nm[-1],
                    )
                )
            if error:
                rec.log_event(error, level="ERROR")
            if summary is not None:
                if summary.left_in:
                    rec.log_event(f"arm left in {summary.left_in}")
                rec.log_summary(summary_dict(summary))
            rec.log_event("stop")
            rec.close()
            self._rec = None
        except Exception as exc:
            self._fail(exc, "while closing")
