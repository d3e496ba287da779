"""`run --record` / `--viewer`: the control loop's steps and summary into a Rerun recording,
a live viewer, or both.

Recording never holds up control: `run`'s steps are handed to a thread of their own
(`WRITER_THREAD`) through a bounded queue and logged there, so the loop's thread goes back to
waiting for the arm's next state as soon as its command is out; a step that finds the queue
full is counted and left out, never waited for (the recording then says it is incomplete).
Measured on a busy 2-core host: with the logging on the loop's thread, the loop thread was
preempted inside it and the next command waited (tools/loop_timing.py, docs/reliability.md).

Recording never stops control: the first write error (a full disk, a removed drive, rerun's
file sink gone) is reported once, recording stops there, and the run goes on as planned; what
was written before the error stays readable (`reach-driver inspect`). `failed` says why, so
the run can end with its own exit status (`Exit.RECORDING_INCOMPLETE`). A viewer that cannot
be started or reached, or goes away, is named once and dropped; the file and the run go on
and the exit status does not change.
"""

from __future__ import annotations

import argparse
import os
import queue
import stat
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console
from rich.markup import escape

from protocol.models import ALPHA5, ArmModel
from reach_driver.cli.exits import UsageError
from reach_driver.cli.report import summary_dict
from reach_driver.errors import DriverError
from reach_driver.records import ControlSummary, StepRecord
from reach_driver.state import JointState

if TYPE_CHECKING:
    from reach_driver.recording import RunRecorder, ViewerSpec


def output_path_problem(option: str, path: str, port: str | None, *, devices: bool) -> str | None:
    """Why `path` may not take a command's output (None if it may): the arm's own port (the
    same file, through any link or name), or, with `devices`, any device: bytes written there
    would go down a serial line, not into a file."""
    try:
        st = os.stat(path)
    except OSError:
        return None  # a file to be made (a bad directory is the writer's to report)
    if port and "://" not in port:
        try:
            arm = os.stat(port)
        except OSError:
            arm = None
        same = arm is not None and (st.st_dev, st.st_ino) == (arm.st_dev, arm.st_ino)
        if same or os.path.realpath(path) == os.path.realpath(port):
            return (
                f"{option} {path} is the arm's port (--port {port}, {os.path.realpath(port)}): "
                "what it wrote would go down the arm's line; give a file"
            )
    if devices and (stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)):
        return (
            f"{option} {path} is a device ({os.path.realpath(path)}), not a file: a recording "
            "is written to a file"
        )
    return None


#: The thread that logs `run`'s steps (never the control loop's).
WRITER_THREAD = "reach-driver recorder"
#: Steps that may wait for the writer (50 s at 20 Hz) before one is left out.
QUEUE_STEPS = 1000
#: How long the end of a run waits for the writer to log what is queued.
DRAIN_WAIT_S = 30.0


def _free_space(path: Path) -> str:
    try:
        st = os.statvfs(path.parent if str(path.parent) else ".")
    except OSError:
        return ""
    return f"; {st.f_bavail * st.f_frsize / 1e6:.1f} MB free on its filesystem"


class CliRecorder:
    """The hooks `run` gives the control loop (`on_step`) and calls at its end (`finish`)."""

    def __init__(
        self,
        path: str | None,
        meta: dict[str, object],
        warn: Console | None = None,
        viewer: ViewerSpec | None = None,
        diagnostics: Callable[[], Mapping[int, JointState]] | None = None,
        keep_into: list[RunRecorder] | None = None,
        model: ArmModel = ALPHA5,
    ) -> None:
        """Opens the recording (and the viewer); fails (DriverError) before anything moves if
        the file cannot be written. A viewer that cannot be had only warns. `diagnostics`
        gives what the driver knows of each device (`ArmClient.state.joints`): its Monitor
        readings and status flags are logged at each step or refresh that has newer ones.
        `keep_into` (`--viewer-keep`): closing ends the file but leaves a live viewer serving,
        the recorder put in this list for the command line to close when it is done. `model`:
        the arm recorded (its joints, its drawing)."""
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
        self.dropped = 0  # steps left out: the writer had QUEUE_STEPS waiting
        self._diagnostics = diagnostics
        self._keep_into = keep_into
        self._queue: queue.Queue[StepRecord | None] | None = None
        self._writer: threading.Thread | None = None
        try:
            self._rec: RunRecorder | None = recording.RunRecorder(
                path,
                metadata=meta,
                viewer=viewer,
                warn=lambda msg: self._warn.print(
                    f"[yellow]warning[/]: {escape(msg)}", soft_wrap=True
                ),
                announce=lambda msg: self._warn.print(escape(msg), soft_wrap=True),
                model=model,
            )
            self._rec.log_event("start")
        except Exception as exc:  # rerun raises RuntimeError for sink errors, Python OSError
            where = f"{exc}{_free_space(Path(path))}" if path is not None else str(exc)
            raise DriverError(f"cannot record to {path or 'the viewer'}: {where}") from None

    @property
    def viewer_failed(self) -> str | None:
        rec = self._rec
        return rec.viewer_failed if rec is not None else None

    def _fail(self, exc: Exception, where: str) -> None:
        """The first write error: say so once, stop recording, keep the run going."""
        rec, self._rec = self._rec, None
        if self.path is None:  # stream only: the viewer's own errors never get here
            self.failed = None
            self._warn.print(
                f"[yellow]warning[/]: live view failed {escape(where)}: "
                f"{escape(type(exc).__name__)}: {escape(str(exc))}; the run goes on",
                soft_wrap=True,
            )
            if rec is not None:
                try:
                    rec.abandon()
                except Exception:
                    pass
            return
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
        """The control loop's hook: hands the step to the writer thread and returns."""
        if self._rec is None:
            return
        if self._queue is None:
            self._queue = queue.Queue(maxsize=QUEUE_STEPS)
            self._writer = threading.Thread(target=self._write_steps, name=WRITER_THREAD)
            self._writer.daemon = True  # never keeps a dying process alive
            self._writer.start()
        try:
            self._queue.put_nowait(r)
        except queue.Full:
            self.dropped += 1

    def _write_steps(self) -> None:
        assert self._queue is not None
        while (r := self._queue.get()) is not None:
            self._log_step(r)

    def _drain(self) -> None:
        """Let the writer log what is queued, and stop it (before the summary is logged)."""
        writer, self._writer = self._writer, None
        if writer is None or self._queue is None:
            return
        self._queue.put(None)
        writer.join(DRAIN_WAIT_S)
        if writer.is_alive():  # a sink that hangs: give up on the rest, keep what is there
            self._fail(
                TimeoutError(f"the recorder did not finish within {DRAIN_WAIT_S:g} s"),
                f"at the end ({self.steps} steps recorded)",
            )

    def _log_step(self, r: StepRecord) -> None:
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
            rec.log_link(
                r.t,
                r.step,
                r.good_frames,
                r.bad_frames,
                r.state_age_s,
                r.latency_s,
                r.loop_period_s,
            )
            self._log_diagnostics(rec, r.t, r.step)
            self.steps += 1
        except Exception as exc:
            self._fail(exc, f"at step {r.step} (t = {r.t:.2f} s; {self.steps} steps recorded)")

    def on_state(
        self,
        t: float,
        step: int,
        q: np.ndarray,
        qdot: np.ndarray,
        current_mA: np.ndarray,
        target: np.ndarray | None = None,
    ) -> None:
        """`monitor` and `move`: what the arm reports at one refresh (no controller)."""
        rec = self._rec
        if rec is None:
            return
        try:
            rec.log_state(t, step, q, qdot, current_mA, target)
            self._log_diagnostics(rec, t, step)
            self.steps += 1
        except Exception as exc:
            self._fail(exc, f"at refresh {step} (t = {t:.2f} s)")

    def _log_diagnostics(self, rec: RunRecorder, t: float, step: int) -> None:
        if self._diagnostics is not None:
            rec.log_diagnostics(t, step, self._diagnostics())

    def _close(self, rec: RunRecorder) -> None:
        """End the file; the viewer too, unless it is to be kept serving."""
        keep = self._keep_into is not None and rec.viewing
        rec.close(keep_viewer=keep)
        self._rec = None
        if keep and self._keep_into is not None:
            self._keep_into.append(rec)

    def close(self, text: str = "stop") -> None:
        """End a `monitor` or `move` stream (no summary)."""
        self._drain()
        rec = self._rec
        if rec is None:
            return
        try:
            rec.log_event(text)
            self._close(rec)
        except Exception as exc:
            self._fail(exc, "while closing")

    def finish(
        self,
        summary: ControlSummary | None,
        error: str | None,
        controller_report: dict[str, Any] | None = None,
    ) -> None:
        self._drain()
        rec = self._rec
        if rec is None:
            return
        recording = self._recording
        if self.dropped:
            lost = (
                f"{self.dropped} step(s) were left out of {self.path or 'the live view'}: the "
                f"recorder fell {QUEUE_STEPS} steps behind the loop (a host too busy to write)"
            )
            self._warn.print(f"[yellow]warning[/]: {escape(lost)}", soft_wrap=True)
            if self.path is not None:
                self.failed = lost
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
                        current_cmd_mA=np.zeros(len(summary.target)),
                        current_meas_mA=tr.current_mA[-1],
                        torque_Nm=tr.torque_Nm[-1],
                    )
                )
                self._log_diagnostics(rec, float(tr.t[-1]), summary.steps)  # read after the run
            if error:
                rec.log_event(error, level="ERROR")
            if summary is not None:
                if summary.left_in:
                    rec.log_event(f"arm left in {summary.left_in}")
                recorded = summary_dict(summary)
                if controller_report:
                    recorded["controller_report"] = controller_report
                    said = controller_report.get("summary")
                    if isinstance(said, str):
                        rec.log_event(said)
                rec.log_summary(recorded)
            rec.log_event("stop")
            self._close(rec)
        except Exception as exc:
            self._fail(exc, "while closing")


def kept_viewers(args: argparse.Namespace) -> list[RunRecorder] | None:
    """With --viewer-keep: where a command's recorder leaves its live viewer serving for
    `main` to wait on once the command is done (None: close it with the command)."""
    if not getattr(args, "viewer_keep", False):
        return None
    kept: list[RunRecorder] = args.kept_viewers
    return kept


def check_record(args: argparse.Namespace) -> None:
    """Before the port is opened: `--record` must name a file, never the arm's port."""
    if args.record:
        problem = output_path_problem("--record", args.record, args.port, devices=True)
        if problem:
            raise UsageError(f"{problem}; nothing was sent")
