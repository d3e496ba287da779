"""`run --record`: the control loop's steps and summary into a Rerun recording."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from reach_driver.cli.report import summary_dict
from reach_driver.errors import DriverError
from reach_driver.records import ControlSummary, StepRecord


def recorder_hook(
    path: str, meta: dict[str, object]
) -> tuple[Callable[[StepRecord], None], Callable[[ControlSummary | None, str | None], None]]:
    """Wire `--record` to reach_driver.recording; fails before anything moves if unavailable."""
    try:
        from reach_driver import recording
    except ImportError as exc:
        raise DriverError(
            f"--record needs reach_driver.recording, which failed to import: {exc}"
        ) from None
    rec = recording.RunRecorder(path, metadata=meta)
    rec.log_event("start")

    def on_step(r: StepRecord) -> None:
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

    def finish(summary: ControlSummary | None, error: str | None) -> None:
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

    return on_step, finish
