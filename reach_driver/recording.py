"""Rerun recordings (.rrd) of closed-loop runs.

A recording is the durable record of a run: joint positions against targets, errors,
velocities, commanded and measured currents, torques, mode changes, link statistics and a 3D
arm whose links follow the joint angles, with the target pose as a ghost. It is written
incrementally and flushed on a short period, so what was logged before Ctrl-C or a crash stays
readable (`reach-driver inspect FILE.rrd`, `rerun FILE.rrd`).

Entity layout (read back by `reach_driver.rrd_summary`):

    joints/<J>/position   Scalars [q, target]   rad
    joints/<J>/current    Scalars [commanded, measured]   mA
    errors                Scalars [e_E, e_D, e_C, e_B]   rad (target - q)
    velocities            Scalars [qdot x4]   rad/s
    torques               Scalars [tau x4]   N m
    link                  Scalars [good frames, bad frames, state age ms]
    arm/...               Transform3D per link; target/... the ghost
    events                TextLog (mode changes, faults, start/stop)
    run/*                 static: targets, joint names, metrics, metadata
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from protocol.alpha5 import JOINT_LETTERS
from reach_driver.kinematics import CHAIN, TCP_OFFSET_M, joint_transform

TIMELINE_TIME = "arm_time"
TIMELINE_STEP = "step"

_ARM_COLOR = (230, 150, 40, 255)
_GHOST_COLOR = (80, 170, 255, 90)
# Link geometry drawn in each link's own frame: from its origin to the next joint's origin.
_LINK_SEGMENTS: dict[str, list[list[float]]] = {
    "m2_1_1": [[0.0, 0.0, 0.0], [-0.02, 0.0, 0.033]],
    "m2": [[0.0, 0.0, 0.0], [-0.04, 0.0, -0.1453]],
    "m2_1_3": [[0.0, 0.0, 0.0], [0.02, 0.0, 0.033]],
    "m1": [[0.0, 0.0, 0.0], [0.0, 0.0, TCP_OFFSET_M]],
}


@dataclass(frozen=True)
class StepSample:
    """What the loop knew and did at one control step (arrays in E D C B order)."""

    t: float
    step: int
    q: np.ndarray
    qdot: np.ndarray
    target: np.ndarray
    current_cmd_mA: np.ndarray
    current_meas_mA: np.ndarray | None = None
    torque_Nm: np.ndarray | None = None


def _link_paths(root: str) -> list[str]:
    """Entity paths of the moving links, nested so each Transform3D composes with its parent."""
    paths, path = [], root
    for frame in CHAIN:
        path = f"{path}/{frame.child_link}"
        paths.append(path)
    return paths


def default_blueprint() -> rrb.Blueprint:
    """Opens on the 3D arm, position-vs-target per joint, torques and errors."""
    position_views = [
        rrb.TimeSeriesView(origin=f"/joints/{j}/position", name=f"{j}: position vs target")
        for j in JOINT_LETTERS
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="/", contents=["/arm/**", "/target/**"], name="arm"),
                rrb.TimeSeriesView(origin="/errors", name="errors (rad)"),
                row_shares=[3, 2],
            ),
            rrb.Vertical(*position_views),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/torques", name="torques (N m)"),
                rrb.TimeSeriesView(origin="/velocities", name="velocities (rad/s)"),
                rrb.TimeSeriesView(origin="/link", name="link"),
            ),
            column_shares=[3, 3, 2],
        ),
        collapse_panels=True,
    )


class RunRecorder:
    """Writes one run to a .rrd file; use as a context manager so it is always closed."""

    def __init__(
        self,
        path: str | Path,
        *,
        app_id: str = "reach-stack",
        metadata: Mapping[str, object] | None = None,
        flush_period_s: float = 0.5,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._rec = rr.RecordingStream(app_id, recording_id=f"{app_id}-{time.time_ns()}")
        self._rec.save(str(self.path), default_blueprint=default_blueprint())
        self._flush_period_s = flush_period_s
        self._last_flush = time.monotonic()
        self._last_target: np.ndarray | None = None
        self._arm_links = _link_paths("arm")
        self._ghost_links = _link_paths("target")
        self._closed = False
        self._t, self._step = 0.0, 0
        self._log_static_scene(metadata or {})
        # On disk at once: a run killed before its first step is still recognised as a run.
        self.flush()

    # -- static scene -------------------------------------------------------------------
    def _log_static_scene(self, metadata: Mapping[str, object]) -> None:
        rec = self._rec
        rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        base = [[-0.12, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.014]]
        rec.log("arm", rr.LineStrips3D([base], radii=0.012, colors=[_ARM_COLOR]), static=True)
        for links, color, radius in (
            (self._arm_links, _ARM_COLOR, 0.01),
            (self._ghost_links, _GHOST_COLOR, 0.008),
        ):
            for path, frame in zip(links, CHAIN, strict=True):
                segment = _LINK_SEGMENTS[frame.child_link]
                rec.log(path, rr.LineStrips3D([segment], radii=radius, colors=[color]), static=True)
        for j in JOINT_LETTERS:
            rec.log(f"joints/{j}/position", rr.SeriesLines(names=["q", "target"]), static=True)
            rec.log(
                f"joints/{j}/current", rr.SeriesLines(names=["commanded", "measured"]), static=True
            )
        names = [f"{j}" for j in JOINT_LETTERS]
        for entity in ("errors", "velocities", "torques"):
            rec.log(entity, rr.SeriesLines(names=names), static=True)
        rec.log(
            "link", rr.SeriesLines(names=["good frames", "bad frames", "state age ms"]), static=True
        )
        meta = {"joint_names": list(JOINT_LETTERS), **dict(metadata)}
        rec.log("run/metadata", rr.TextDocument(json.dumps(meta, default=str)), static=True)

    def _set_time(self, t: float, step: int) -> None:
        self._t, self._step = float(t), int(step)
        self._rec.set_time(TIMELINE_TIME, duration=float(t))
        self._rec.set_time(TIMELINE_STEP, sequence=int(step))

    def _log_pose(self, links: Sequence[str], q: np.ndarray) -> None:
        for path, frame, angle in zip(links, CHAIN, q, strict=True):
            translation, rotation = joint_transform(frame, float(angle))
            self._rec.log(path, rr.Transform3D(translation=translation, mat3x3=rotation))

    # -- per step ---------------------------------------------------------------------------
    def log_step(self, s: StepSample) -> None:
        """Log one control step; the ghost pose is re-logged only when the target changes."""
        self._set_time(s.t, s.step)
        rec = self._rec
        q = np.asarray(s.q, dtype=float)
        target = np.asarray(s.target, dtype=float)
        if self._last_target is None or not np.array_equal(target, self._last_target):
            self._log_pose(self._ghost_links, target)
            rec.log("run/target", rr.Scalars(target))
            self._last_target = target.copy()
        cmd = np.asarray(s.current_cmd_mA, dtype=float)
        meas = np.full(4, np.nan) if s.current_meas_mA is None else np.asarray(s.current_meas_mA)
        for i, j in enumerate(JOINT_LETTERS):
            rec.log(f"joints/{j}/position", rr.Scalars([q[i], target[i]]))
            rec.log(f"joints/{j}/current", rr.Scalars([cmd[i], meas[i]]))
        rec.log("errors", rr.Scalars(target - q))
        rec.log("velocities", rr.Scalars(np.asarray(s.qdot, dtype=float)))
        if s.torque_Nm is not None:
            rec.log("torques", rr.Scalars(np.asarray(s.torque_Nm, dtype=float)))
        self._log_pose(self._arm_links, q)
        self._maybe_flush()

    def log_link(self, t: float, step: int, good: int, bad: int, state_age_s: float) -> None:
        self._set_time(t, step)
        self._rec.log("link", rr.Scalars([float(good), float(bad), state_age_s * 1e3]))

    def log_event(
        self, text: str, level: str = "INFO", t: float | None = None, step: int | None = None
    ) -> None:
        """Mode changes, faults, start and stop (at the last step's time unless given); flushed
        at once because they explain how a run ended."""
        self._set_time(self._t if t is None else t, self._step if step is None else step)
        self._rec.log("events", rr.TextLog(text, level=level))
        self.flush()

    def log_summary(self, summary: Mapping[str, object]) -> None:
        """The run's metrics and outcome, static so a viewer shows them at any time."""
        self._rec.log(
            "run/summary", rr.TextDocument(json.dumps(dict(summary), default=float)), static=True
        )
        self.flush()

    # -- lifetime ---------------------------------------------------------------------------
    def _maybe_flush(self) -> None:
        now = time.monotonic()
        if now - self._last_flush >= self._flush_period_s:
            self.flush()

    def flush(self) -> None:
        self._rec.flush(timeout_sec=2.0)
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._rec.flush(timeout_sec=5.0)
        self._rec.disconnect()

    def abandon(self) -> None:
        """Stop writing without flushing: after a write error, when a flush would only wait for
        a sink that is gone. What reached the file before stays readable."""
        if self._closed:
            return
        self._closed = True
        self._rec.disconnect()

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is not None:
            name = exc_type.__name__ if exc_type else "error"
            self.log_event(f"run ended by {name}: {exc}", level="ERROR")
        self.close()
