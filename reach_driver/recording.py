"""Rerun recordings (.rrd) of closed-loop runs.

A recording is the durable record of a run: joint positions against targets, errors,
velocities, commanded and measured currents, torques, mode changes, link statistics and a 3D
arm drawn from the MJCF's link geoms (`reach_driver.arm_geometry`) posed by the driver's
kinematics, with the target pose as a translucent ghost. It is written incrementally and
flushed on a short period, so what was logged before Ctrl-C or a crash stays readable
(`reach-driver inspect FILE.rrd`, `rerun FILE.rrd`).

Timelines: `arm_time` (a duration: the arm's clock in seconds, the one the viewer opens on)
and `step` (the control step index).

Entity layout (read back by `reach_driver.rrd_summary`):

    joints/<J>/position   Scalars [q, target]   rad
    joints/<J>/current    Scalars [commanded, measured]   mA
    errors                Scalars [e_E, e_D, e_C, e_B]   rad (target - q)
    velocities            Scalars [qdot x4]   rad/s
    torques               Scalars [tau x4]   N m
    link/frames           Scalars [good frames, bad frames]   counts since the run started
    link/state_age        Scalars [age of the oldest reading in the state]   ms
    link/latency          Scalars [state complete -> command written]   ms
    link/loop_period      Scalars [time since the previous command]   ms (wall clock: what the
                          watchdog judges; a stall of the host shows here)
    diagnostics/<key>     Scalars [E, D, C, B, A], one entity per Monitor reading, named with
                          its unit (`reach_driver.state.MONITOR_READINGS`: voltage_v,
                          temperature_c, humidity_pct, internal_pressure_bar (0x67),
                          pressure_0x6e_bar); NaN where a device has not reported it. Logged
                          when the driver has a newer reading, not every step.
    diagnostics/status    Scalars [E, D, C, B, A]   each device's HARDWARE_STATUS as one 32-bit
                          value (byte A highest; NaN until reported); a change of a device's
                          flags is also an `events` line naming them
    arm                   the base's geoms (static)
    arm/<link>/...        Transform3D per step (nested: each composes with its parent) and the
                          link's Cylinders3D / Boxes3D (static, in the link's frame)
    target/<link>/...     the same links, translucent, posed at the target (the ghost)
    events                TextLog (mode changes, faults, start/stop)
    run/*                 static: metadata, summary; run/target Scalars when the target changes

Live viewing (`reach-driver run/move/monitor --viewer`): the same entities go to a second
stream with the same recording id whose sink is a Rerun viewer (`protocol.viewer`, shared with
`reach-sim`, says how and why), with the same blueprint but a time panel that follows the
newest data. The viewer stream is never flushed on the control loop's thread; its first error
is reported once and it is dropped, the file goes on. `close(keep_viewer=True)` ends the file
and leaves the viewer serving (`--viewer-keep`) until `close_viewer`.

The default blueprint (`default_blueprint`; `protocol.viewer_layout` for what the simulator's
shows alike): the 3D eye frames the arm's whole reach (`arm_bodies`, `arm_eye`), every plot
spans the whole recording with its legend hidden (the titles name the colours).
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from protocol import HardwareStatus
from protocol.alpha5 import ALL_DEVICES, JOINT_LETTERS
from protocol.viewer import (
    ViewerError,
    ViewerSpec,
    ViewerTee,
    live_view_off,
    open_viewer,
    viewer_failure,
)
from protocol.viewer_layout import (
    ARM_COLOR,
    JAW_COLOR,
    JOINT_COLORS,
    JOINT_KEY,
    TARGET_COLOR,
    ArmBody,
    Ball,
    EyePose,
    arm_view,
    framing_eye,
    reach,
    series_view,
    time_panel,
)
from reach_driver.arm_geometry import GEOMS, LinkGeom
from reach_driver.kinematics import CHAIN, TCP_OFFSET_M, joint_transform, link_poses
from reach_driver.state import MONITOR_READINGS, JointState, Reading, joint_name

TIMELINE_TIME = "arm_time"
TIMELINE_STEP = "step"
BASE_LINK = "m3_inline"

_BASE_COLOR = (90, 90, 90, 255)
_GHOST_COLOR = (*TARGET_COLOR[:3], 70)
_MEASURED_COLOR = (120, 120, 120, 255)
_TCP_RADIUS_M = 0.006

#: (entity, view title) of every time-series view of the default blueprint; titles carry units.
LINK_VIEWS = (
    ("link/frames", "link: frames received (count)"),
    ("link/state_age", "link: state age (ms)"),
    ("link/latency", "link: latency, state to command (ms)"),
    ("link/loop_period", "link: loop period, command to command (ms)"),
)

#: The devices of the diagnostics entities, in their order: the four joints, then the jaw.
DIAGNOSTIC_LETTERS = tuple(d.name for d in ALL_DEVICES)
STATUS_ENTITY = "diagnostics/status"
#: (entity, view title) of the diagnostics' views: one per Monitor reading, then the flags.
DIAGNOSTIC_VIEWS = (
    *((f"diagnostics/{m.key}", m.title) for m in MONITOR_READINGS),
    (STATUS_ENTITY, "HARDWARE_STATUS as one 32-bit value, byte A highest (flags)"),
)


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


def _quat_rotate(quat_xyzw: Sequence[float], v: Sequence[float]) -> np.ndarray:
    x, y, z, w = quat_xyzw
    u, vec = np.array([x, y, z]), np.asarray(v, dtype=float)
    return vec + 2.0 * np.cross(u, np.cross(u, vec) + w * vec)


def _geom_balls(g: LinkGeom) -> list[tuple[np.ndarray, float]]:
    """Balls (link frame) enclosing a geom: a cylinder's end discs (their hull is within the
    hull of the two balls), a box's corners."""
    center = np.asarray(g.center, dtype=float)
    if g.shape == "cylinder":
        radius, length = g.size
        half = _quat_rotate(g.quat_xyzw, (0.0, 0.0, length / 2.0))
        return [(center - half, radius), (center + half, radius)]
    return [(center, float(np.linalg.norm(g.size)))]


def arm_bodies() -> list[ArmBody]:
    """The drawn arm (the MJCF's geoms on the kinematic chain, the tool centre point's dot) as
    `protocol.viewer_layout` bodies, posed at zero angles: the base, then each joint's link."""
    poses = [(np.zeros(3), np.eye(3)), *link_poses(np.zeros(len(CHAIN)))]
    names = [BASE_LINK, *(frame.child_link for frame in CHAIN)]
    bodies = []
    for i, (name, (pos, rot)) in enumerate(zip(names, poses, strict=True)):
        local = [b for g in GEOMS if g.link == name for b in _geom_balls(g)]
        if i == len(names) - 1:
            local.append((np.array([0.0, 0.0, TCP_OFFSET_M]), _TCP_RADIUS_M))
        balls = tuple(
            Ball(tuple(float(v) for v in pos + rot @ c), float(r))  # type: ignore[arg-type]
            for c, r in local
        )
        if i == 0:
            bodies.append(ArmBody(None, None, None, balls))
            continue
        axis = rot @ np.asarray(CHAIN[i - 1].axis, dtype=float)
        pivot = tuple(float(v) for v in pos)
        direction = tuple(float(v) for v in axis)
        bodies.append(ArmBody(i - 1, pivot, direction, balls))  # type: ignore[arg-type]
    return bodies


def arm_eye() -> EyePose:
    """The 3D view's eye: every pose of the arm (and of its ghost) in view."""
    return framing_eye(reach(arm_bodies()))


def default_blueprint(live: bool = False) -> rrb.Blueprint:
    """Opens on the arm-time timeline (seconds): the 3D arm and its ghost, errors and events;
    per joint its position vs target (rad) beside its currents (mA); torques, velocities and
    the link's counts, state age and latency, each on its own scale; the devices' Monitor
    readings and status flags. The eye frames the arm's whole reach; every plot spans the
    whole run, its legend hidden (colours: `protocol.viewer_layout`, the titles say them).
    `live`: for a viewer watching the run as it goes, which follows the newest data."""
    joint_rows = [
        rrb.Horizontal(
            series_view(f"/joints/{j}/position", f"{j}: position, q orange vs target blue (rad)"),
            series_view(
                f"/joints/{j}/current", f"{j}: current, commanded orange vs measured grey (mA)"
            ),
        )
        for j in JOINT_LETTERS
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                arm_view("arm (m), target pose as a ghost", ["/arm/**", "/target/**"], arm_eye()),
                series_view("/errors", f"errors: target - q (rad); {JOINT_KEY}"),
                rrb.TextLogView(origin="/events", name="events"),
                row_shares=[4, 2, 1],
            ),
            rrb.Vertical(*joint_rows),
            rrb.Vertical(
                series_view("/torques", "torques (N m)"),
                series_view("/velocities", "velocities (rad/s)"),
                *(series_view(f"/{entity}", name) for entity, name in LINK_VIEWS),
            ),
            rrb.Vertical(
                *(series_view(f"/{entity}", name) for entity, name in DIAGNOSTIC_VIEWS),
            ),
            column_shares=[4, 4, 2, 2],
        ),
        time_panel(TIMELINE_TIME, live),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def log_link_geoms(
    rec: rr.RecordingStream | ViewerTee,
    path: str,
    geoms: Sequence[LinkGeom],
    color: tuple[int, int, int, int],
) -> None:
    """A link's geoms (static, in the entity's own frame): MJCF cylinders and boxes."""
    cylinders = [g for g in geoms if g.shape == "cylinder"]
    boxes = [g for g in geoms if g.shape == "box"]
    if cylinders:
        rec.log(
            path,
            rr.Cylinders3D(
                centers=[g.center for g in cylinders],
                quaternions=[g.quat_xyzw for g in cylinders],
                radii=[g.size[0] for g in cylinders],
                lengths=[g.size[1] for g in cylinders],
                colors=[color] * len(cylinders),
                fill_mode="solid",
            ),
            static=True,
        )
    if boxes:
        rec.log(
            path,
            rr.Boxes3D(
                centers=[g.center for g in boxes],
                quaternions=[g.quat_xyzw for g in boxes],
                half_sizes=[g.size for g in boxes],
                colors=[color] * len(boxes),
                fill_mode="solid",
            ),
            static=True,
        )


class RunRecorder:
    """Writes one run to a .rrd file and/or streams it live to a viewer; use as a context
    manager so it is always closed.

    `path` None with a `viewer`: stream only. A viewer that cannot be started or reached, or
    that fails later, is reported once through `warn` and dropped; it never raises here and
    never stops the file (`viewer_failed` says why). File errors raise, as before."""

    def __init__(
        self,
        path: str | Path | None,
        *,
        app_id: str = "reach-stack",
        metadata: Mapping[str, object] | None = None,
        flush_period_s: float = 0.5,
        viewer: ViewerSpec | None = None,
        warn: Callable[[str], None] | None = None,
        announce: Callable[[str], None] | None = None,
    ) -> None:
        if path is None and viewer is None:
            raise ValueError("RunRecorder needs a path, a viewer or both")
        self.path = None if path is None else Path(path)
        self.viewer = viewer
        self.viewer_failed: str | None = None
        self._warn = warn or (lambda msg: print(f"warning: {msg}", file=sys.stderr))
        recording_id = f"{app_id}-{time.time_ns()}"
        file_rec: rr.RecordingStream | None = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            file_rec = rr.RecordingStream(app_id, recording_id=recording_id)
            file_rec.save(str(self.path), default_blueprint=default_blueprint())
        view_rec: rr.RecordingStream | None = None
        if viewer is not None:
            try:
                live = default_blueprint(live=True)
                view_rec = open_viewer(viewer, app_id, recording_id, live, announce)
            except ViewerError as exc:
                self._viewer_error(exc, opening=True)
        self._rec = ViewerTee(file_rec, view_rec, self._viewer_error)
        self._rec.watch()
        self._flush_period_s = flush_period_s
        self._last_flush = time.monotonic()
        self._last_target: np.ndarray | None = None
        self._arm_links = _link_paths("arm")
        self._ghost_links = _link_paths("target")
        self._closed = False
        self._t, self._step = 0.0, 0
        # Diagnostics: the arrival times last logged per reading, the flags last named.
        self._diag_logged: dict[str, list[float | None]] = {}
        self._flags_named: dict[int, HardwareStatus] = {}
        self._log_static_scene(metadata or {})
        # On disk at once: a run killed before its first step is still recognised as a run.
        self.flush()

    @property
    def viewing(self) -> bool:
        """A viewer is attached and has not failed."""
        return self._rec.viewer is not None

    def _viewer_error(self, exc: Exception, opening: bool = False) -> None:
        if self.viewer_failed is not None:
            return
        self.viewer_failed = viewer_failure(self.viewer, exc, opening)
        self._warn(
            live_view_off(self.viewer_failed, self.path is not None, "control is unaffected")
        )

    # -- static scene -------------------------------------------------------------------
    def _log_static_scene(self, metadata: Mapping[str, object]) -> None:
        rec = self._rec
        rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        log_link_geoms(rec, "arm", [g for g in GEOMS if g.link == BASE_LINK], _BASE_COLOR)
        tcp = [[0.0, 0.0, TCP_OFFSET_M]]
        for links, color in ((self._arm_links, ARM_COLOR), (self._ghost_links, _GHOST_COLOR)):
            for path, frame in zip(links, CHAIN, strict=True):
                log_link_geoms(rec, path, [g for g in GEOMS if g.link == frame.child_link], color)
            rec.log(
                f"{links[-1]}/tcp",
                rr.Points3D(tcp, radii=_TCP_RADIUS_M, colors=[color]),
                static=True,
            )
        for j in JOINT_LETTERS:
            rec.log(
                f"joints/{j}/position",
                rr.SeriesLines(names=["q", "target"], colors=[ARM_COLOR, TARGET_COLOR]),
                static=True,
            )
            rec.log(
                f"joints/{j}/current",
                rr.SeriesLines(
                    names=["commanded", "measured"], colors=[ARM_COLOR, _MEASURED_COLOR]
                ),
                static=True,
            )
        names = [f"{j}" for j in JOINT_LETTERS]
        for entity in ("errors", "velocities", "torques"):
            rec.log(entity, rr.SeriesLines(names=names, colors=list(JOINT_COLORS)), static=True)
        rec.log("link/frames", rr.SeriesLines(names=["good frames", "bad frames"]), static=True)
        rec.log("link/state_age", rr.SeriesLines(names=["state age ms"]), static=True)
        rec.log("link/latency", rr.SeriesLines(names=["latency ms"]), static=True)
        rec.log("link/loop_period", rr.SeriesLines(names=["loop period ms"]), static=True)
        for entity, _ in DIAGNOSTIC_VIEWS:
            rec.log(
                entity,
                rr.SeriesLines(names=list(DIAGNOSTIC_LETTERS), colors=[*JOINT_COLORS, JAW_COLOR]),
                static=True,
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

    def log_state(
        self,
        t: float,
        step: int,
        q: np.ndarray,
        qdot: np.ndarray,
        current_mA: np.ndarray,
        target: np.ndarray | None = None,
    ) -> None:
        """What the arm reports, without a controller (`monitor`, `move`): positions (against
        the target when there is one, the ghost posed at it), velocities, measured currents
        and the 3D arm. Joints with no reading yet are left out of the pose."""
        self._set_time(t, step)
        rec = self._rec
        q = np.asarray(q, dtype=float)
        tgt = np.full(4, np.nan) if target is None else np.asarray(target, dtype=float)
        if target is not None and (
            self._last_target is None or not np.array_equal(tgt, self._last_target)
        ):
            self._log_pose(self._ghost_links, tgt)
            rec.log("run/target", rr.Scalars(tgt))
            self._last_target = tgt.copy()
        meas = np.asarray(current_mA, dtype=float)
        for i, j in enumerate(JOINT_LETTERS):
            rec.log(f"joints/{j}/position", rr.Scalars([q[i], tgt[i]]))
            rec.log(f"joints/{j}/current", rr.Scalars([np.nan, meas[i]]))
        if target is not None:
            rec.log("errors", rr.Scalars(tgt - q))
        rec.log("velocities", rr.Scalars(np.asarray(qdot, dtype=float)))
        if np.all(np.isfinite(q)):
            self._log_pose(self._arm_links, q)
        self._maybe_flush()

    def log_link(
        self,
        t: float,
        step: int,
        good: int,
        bad: int,
        state_age_s: float,
        latency_s: float | None = None,
        loop_period_s: float | None = None,
    ) -> None:
        """The link's health at one step: frame counts, state age and (if known) the latency
        from the state being complete to the command being written and the wall time since the
        previous command, each its own entity."""
        self._set_time(t, step)
        rec = self._rec
        rec.log("link/frames", rr.Scalars([float(good), float(bad)]))
        rec.log("link/state_age", rr.Scalars(state_age_s * 1e3))
        if latency_s is not None:
            rec.log("link/latency", rr.Scalars(latency_s * 1e3))
        if loop_period_s is not None and np.isfinite(loop_period_s):
            rec.log("link/loop_period", rr.Scalars(loop_period_s * 1e3))

    def log_diagnostics(self, t: float, step: int, joints: Mapping[int, JointState]) -> bool:
        """The devices' Monitor readings and HARDWARE_STATUS flags, those the driver has a
        newer reading of than last logged (so this can be called every step); an `events`
        line when a device's flags change. True if anything was logged."""
        fields = [(f"diagnostics/{m.key}", m.field) for m in MONITOR_READINGS]
        logged = False
        for entity, name in (*fields, (STATUS_ENTITY, "status")):
            readings: list[Reading[Any] | None] = [
                getattr(joints.get(int(d)) or JointState(int(d)), name) for d in ALL_DEVICES
            ]
            stamps = [None if r is None else r.t for r in readings]
            if all(v is None for v in stamps) or stamps == self._diag_logged.get(entity):
                continue
            if not logged:
                self._set_time(t, step)
                logged = True
            self._diag_logged[entity] = stamps
            values = [np.nan if r is None else float(r.value) for r in readings]
            self._rec.log(entity, rr.Scalars(values))
            if entity == STATUS_ENTITY:
                self._name_flag_changes(readings)
        if logged:
            self._maybe_flush()
        return logged

    def _name_flag_changes(self, readings: Sequence[Reading[Any] | None]) -> None:
        for dev, reading in zip(ALL_DEVICES, readings, strict=True):
            if reading is None:
                continue
            flags = HardwareStatus(reading.value)
            if flags == self._flags_named.get(int(dev), HardwareStatus.NONE):
                continue
            self._flags_named[int(dev)] = flags
            names = ", ".join(flags.flag_names()) or "cleared"
            level = "WARNING" if flags else "INFO"
            self._rec.log("events", rr.TextLog(f"status {joint_name(dev)}: {names}", level=level))

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
        """The file only: the viewer stream sends on its own (rerun's batcher) and is never
        waited for on the control loop's thread."""
        if self._rec.file is not None:
            self._rec.file.flush(timeout_sec=2.0)
        self._last_flush = time.monotonic()

    def close(self, keep_viewer: bool = False) -> None:
        """End the file; and the viewer stream, unless `keep_viewer`: then it goes on serving
        what it was sent until `close_viewer` (`--viewer-keep`)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._rec.file is not None:
                self._rec.file.flush(timeout_sec=5.0)
                self._rec.file.disconnect()
        finally:
            if not keep_viewer:
                self._rec.close_viewer()

    def close_viewer(self) -> None:
        """Drop the viewer stream (a kept one: its server and web viewer stop)."""
        self._rec.close_viewer()

    def abandon(self) -> None:
        """Stop writing without flushing: after a write error, when a flush would only wait for
        a sink that is gone. What reached the file before stays readable."""
        if self._closed:
            return
        self._closed = True
        file, self._rec.file = self._rec.file, None
        try:
            if file is not None:
                file.disconnect()
        finally:
            self._rec.close_viewer()

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
