"""`reach-sim --record FILE.rrd`: the virtual arm's true state as a Rerun recording.

The simulator sees what no client can: true joint angles, the current actually drawn, the
torque delivered. Sampling them on sim time gives a ground-truth record to lay beside the
driver's own recording of the same run. Entity names follow the driver's
(`joints/<J>/position` = [q, firmware position setpoint], `joints/<J>/current` = [applied,
drawn], `torques`, `velocities`, `link/frames`, `events`), so `reach-driver inspect` reads
either file (it says which); the 3D arm is the MJCF's own geoms (`arm/links` cylinders,
`arm/jaw` boxes) posed by MuJoCo. Timelines: `arm_time` (sim seconds, the one the viewer opens
on) and `step` (the full-rate sample index).

A simulator left running must not fill the disk, so the recording is bounded twice:

- **rate**: every full-rate sample (`rate_hz`) is looked at, but while the arm is quiet (no
  joint moving faster than `IDLE_SPEED`, currents steady, modes, setpoints and faults
  unchanged) only `idle_rate_hz` of them are logged; the first sample that is not quiet is
  logged at once, with the quiet one before it so a plot does not ramp across the gap, and
  the full rate is kept for `HOLD_S` after the arm settles. Chunks are written every
  `flush_period_s` wall seconds at the full rate and at most every `IDLE_FLUSH_S` when idle
  (rerun's per-chunk overhead, not the samples, is what made idle recordings large).
- **size**: with `max_bytes`, the recording is split into `parts` files of `max_bytes /
  parts` each, rotated like logs: FILE.rrd is the newest, FILE.1.rrd the one before, ... up
  to FILE.<parts-1>.rrd; the oldest is deleted. Every part is a complete recording (metadata,
  blueprint, the arm's geometry, the modes and faults as they stand) under the same recording
  id, so `rerun FILE.*.rrd FILE.rrd` shows them as one.

Live viewing (`reach-sim --viewer spawn | connect URL | serve`): the same samples go to a
second stream with the same recording id whose sink is a viewer (`protocol.viewer`, the one
copy the driver uses too), never flushed by the recorder and not bounded (a viewer keeps what
its memory limit allows); its first error is reported once and it is dropped, the file and
the simulator go on. Without `--record` the arm is streamed only. Its time panel follows the
newest data; a file's plays from the start. Both blueprints frame the arm's whole reach
(`arm_bodies`, from the model) and plot over the whole recording without legends
(`protocol.viewer_layout`).
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from protocol import HardwareStatus, Mode
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
    TARGET_COLOR,
    ArmBody,
    Ball,
    EyePose,
    arm_view,
    framing_eye,
    joint_colors,
    joint_key,
    reach,
    series_view,
    time_panel,
)
from reach_sim_bridge.emulator.firmware import Firmware
from reach_sim_bridge.emulator.server import SimServer
from reach_sim_bridge.model.arm import MotorArm

TIMELINE_TIME = "arm_time"
TIMELINE_STEP = "step"

#: The default size cap of a recording, all its parts together (reach-sim --record-max-mb).
DEFAULT_MAX_BYTES = 200_000_000
IDLE_SPEED = 0.005  # rad/s: slower than this on every joint is "not moving"
IDLE_CURRENT_MA = 5.0  # a drawn current this far from the last logged one is a change
HOLD_S = 0.5  # sim seconds of full rate kept after the arm settles
IDLE_FLUSH_S = 30.0  # wall seconds: the longest a sample waits in memory
_MIN_ROWS_PER_FLUSH = 50  # samples: fewer per flush and the chunk overhead dominates
# The footer rerun writes on closing a file indexes every chunk (~1.1 kB each, measured with
# rerun 0.41): a part is rotated when its size plus the footer still to come reaches its cap.
_FOOTER_BYTES_PER_CHUNK = 1200
_CHUNKS_AT_OPEN = 80  # the blueprint's and the static scene's (77, measured with rerun 0.41)
#: Entities logged per sample beside the two per joint: torques, velocities, links, jaw,
#: link/frames.
_PER_SAMPLE_ENTITIES = 5

_BASE_COLOR = (90, 90, 90, 255)
_APPLIED_COLOR = (120, 120, 120, 255)


def drawn_bodies(model: mujoco.MjModel) -> list[int]:
    """The bodies drawn, in the model's order: those with a cylinder or box geom (the links,
    the base and the jaws; not the buoyancy bodies, which have none)."""
    kinds = (int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_BOX))
    return sorted(
        {int(model.geom_bodyid[g]) for g in range(model.ngeom) if model.geom_type[g] in kinds}
    )


@dataclass(frozen=True)
class _Geoms:
    """The drawn geoms of the model: ids, and their static sizes and colours."""

    cylinders: np.ndarray
    boxes: np.ndarray
    radii: np.ndarray
    lengths: np.ndarray
    half_sizes: np.ndarray
    colors: list[tuple[int, int, int, int]]


def _geoms(model: mujoco.MjModel) -> _Geoms:
    bodies = set(drawn_bodies(model))
    base = {b for b in bodies if model.body_parentid[b] == 0}  # welded to the world
    cyl, box = int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_BOX)
    cylinders = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] in bodies and model.geom_type[g] == cyl
    ]
    boxes = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] in bodies and model.geom_type[g] == box
    ]
    return _Geoms(
        cylinders=np.array(cylinders, dtype=int),
        boxes=np.array(boxes, dtype=int),
        radii=model.geom_size[cylinders, 0].copy(),
        lengths=2.0 * model.geom_size[cylinders, 1].copy(),
        half_sizes=model.geom_size[boxes].copy(),
        colors=[_BASE_COLOR if model.geom_bodyid[g] in base else ARM_COLOR for g in cylinders],
    )


def _quats_xyzw(xmat: np.ndarray) -> np.ndarray:
    out = np.empty((len(xmat), 4))
    wxyz = np.zeros(4)
    for i, m in enumerate(xmat):
        mujoco.mju_mat2Quat(wxyz, m)
        out[i] = (wxyz[1], wxyz[2], wxyz[3], wxyz[0])
    return out


@dataclass(frozen=True)
class _Sample:
    t: float
    q: np.ndarray
    qdot: np.ndarray
    tau: np.ndarray
    drawn_mA: np.ndarray
    applied_mA: np.ndarray
    setpoint: np.ndarray
    modes: tuple[Mode, ...]
    status: tuple[HardwareStatus, ...]
    cylinder_pos: np.ndarray
    cylinder_quat: np.ndarray
    box_pos: np.ndarray
    box_quat: np.ndarray


def _sampler(geoms: _Geoms, devices: tuple[int, ...]):  # type: ignore[no-untyped-def]
    def sample(arm: MotorArm, firmware: Firmware) -> _Sample:
        setpoints = [firmware.setpoints(dev) for dev in devices]
        modes = tuple(m for m, _, _ in setpoints)
        target = np.array([p if m == Mode.POSITION else math.nan for m, p, _ in setpoints])
        arm.skeleton()  # runs the kinematics: the geoms' world poses below are current
        data = arm.data
        return _Sample(
            t=arm.time,
            q=arm.q.copy(),
            qdot=arm.qdot.copy(),
            tau=arm.tau.copy(),
            drawn_mA=arm.current_mA.copy(),
            applied_mA=np.array([a for _, _, a in setpoints]),
            setpoint=target,
            modes=modes,
            status=tuple(firmware.status(dev) for dev in devices),
            cylinder_pos=data.geom_xpos[geoms.cylinders].copy(),
            cylinder_quat=_quats_xyzw(data.geom_xmat[geoms.cylinders]),
            box_pos=data.geom_xpos[geoms.boxes].copy(),
            box_quat=_quats_xyzw(data.geom_xmat[geoms.boxes]),
        )

    return sample


def part_path(path: Path, n: int) -> Path:
    """FILE.rrd for the newest part (n = 0), FILE.<n>.rrd for the older ones."""
    return path if n == 0 else path.with_name(f"{path.stem}.{n}{path.suffix}")


def _balls(model: mujoco.MjModel, data: mujoco.MjData, body: int, grow: float) -> tuple[Ball, ...]:
    """Balls enclosing a body's drawn geoms (world, as `data` poses them): a cylinder's two
    end discs, a box's corners; each grown by `grow` (a slide's travel)."""
    cyl, box = int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_BOX)
    out: list[Ball] = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != body or model.geom_type[g] not in (cyl, box):
            continue
        center = data.geom_xpos[g]
        if model.geom_type[g] == cyl:
            radius, half = model.geom_size[g, :2]
            axis = data.geom_xmat[g].reshape(3, 3)[:, 2] * half
            ends = [(center - axis, radius), (center + axis, radius)]
        else:
            ends = [(center, float(np.linalg.norm(model.geom_size[g])))]
        out.extend(Ball(tuple(float(v) for v in c), float(r) + grow) for c, r in ends)  # type: ignore[arg-type]
    return tuple(out)


def arm_bodies(model: mujoco.MjModel) -> list[ArmBody]:
    """The drawn bodies (`drawn_bodies`) as `protocol.viewer_layout` bodies, posed at the
    model's zero angles; the jaw's slide counted as its fingers' travel."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    ids = drawn_bodies(model)
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    bodies = []
    for b in ids:
        parent = int(model.body_parentid[b])
        while parent not in ids and parent != 0:
            parent = int(model.body_parentid[parent])
        joints = range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
        pivot = axis = None
        grow = 0.0
        for j in joints:
            if model.jnt_type[j] == hinge:
                pivot = tuple(float(v) for v in data.xanchor[j])
                axis = tuple(float(v) for v in data.xaxis[j])
            else:
                grow += float(np.max(np.abs(model.jnt_range[j])))
        bodies.append(
            ArmBody(
                None if parent == 0 else ids.index(parent),
                pivot,  # type: ignore[arg-type]
                axis,  # type: ignore[arg-type]
                _balls(model, data, b, grow),
            )
        )
    return bodies


def _blueprint(joints: tuple[str, ...], eye: EyePose, live: bool = False) -> rrb.Blueprint:
    """The true arm with its eye on every pose (`eye`), per joint its position vs the
    firmware's setpoint beside its currents, torques, velocities and the link's frames; every
    plot over the whole recording, legends hidden. `live`: following the newest data."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                arm_view("arm, true state (m)", ["/arm/**"], eye),
                rrb.TextLogView(origin="/events", name="events (modes, faults)"),
                row_shares=[4, 1],
            ),
            rrb.Vertical(
                *[
                    rrb.Horizontal(
                        series_view(
                            f"/joints/{j}/position",
                            f"{j}: true position orange vs setpoint blue (rad)",
                        ),
                        series_view(
                            f"/joints/{j}/current",
                            f"{j}: current, applied grey vs drawn orange (mA)",
                        ),
                    )
                    for j in joints
                ]
            ),
            rrb.Vertical(
                series_view("/torques", f"torques delivered (N m); {joint_key(joints)}"),
                series_view("/velocities", "velocities (rad/s)"),
                series_view("/link/frames", "link: frames (count)"),
            ),
            column_shares=[4, 4, 2],
        ),
        time_panel(TIMELINE_TIME, live),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


class SimRecorder:
    """Samples a running SimServer at `rate_hz` of sim time into a .rrd, in its own thread
    (bounded in rate when the arm is idle and in size by `max_bytes`; see the module), and/or
    streams the samples live to a viewer (`viewer`; `path` None: stream only)."""

    def __init__(
        self,
        server: SimServer,
        path: str | Path | None,
        rate_hz: float = 50.0,
        flush_period_s: float = 2.0,
        *,
        idle_rate_hz: float = 2.0,
        max_bytes: int | None = DEFAULT_MAX_BYTES,
        parts: int = 4,
        viewer: ViewerSpec | None = None,
        warn: Callable[[str], None] | None = None,
        announce: Callable[[str], None] | None = None,
    ) -> None:
        if path is None and viewer is None:
            raise ValueError("SimRecorder needs a path, a viewer or both")
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"recording rate must be positive, got {rate_hz}")
        if not (math.isfinite(idle_rate_hz) and 0 < idle_rate_hz <= rate_hz):
            raise ValueError(f"idle rate must be in (0, {rate_hz}] Hz, got {idle_rate_hz}")
        if max_bytes is not None and max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive (or None: no cap), got {max_bytes}")
        if parts < 2:
            raise ValueError(f"a capped recording needs at least 2 parts, got {parts}")
        self.server = server
        #: the arm served: its joints name the entities, its MJCF is drawn
        self.model = server.config.model
        self.joints = self.model.joint_letters
        self.path = None if path is None else Path(path)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self.viewer = viewer
        self.viewer_failed: str | None = None
        self._warn = warn or (lambda msg: print(f"reach-sim: warning: {msg}", file=sys.stderr))
        self.rate_hz, self.idle_rate_hz = float(rate_hz), float(idle_rate_hz)
        self.period = 1.0 / rate_hz
        self.idle_period = 1.0 / idle_rate_hz
        self.max_bytes, self.parts = max_bytes, parts
        self.part_bytes = None if max_bytes is None else max(1, max_bytes // parts)
        self.flush_period_s = flush_period_s
        self.samples = 0  # logged
        self.looked = 0  # sampled, logged or not
        self.rotations = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closers: list[threading.Thread] = []  # finishing rotated-out parts
        self._recording_id = f"reach-sim-{time.time_ns()}"
        self._geoms = server.observe(lambda arm, _fw: _geoms(arm.model))
        self._eye = server.observe(lambda arm, _fw: framing_eye(reach(arm_bodies(arm.model))))
        self._sample = _sampler(self._geoms, tuple(int(d) for d in self.model.joints))
        self._lock = threading.Lock()  # the stream, across rotation and outside flushes
        self._modes: tuple[Mode, ...] | None = None
        self._status: tuple[HardwareStatus, ...] | None = None
        self._chunks = _CHUNKS_AT_OPEN
        self._out = ViewerTee(None, None, self._viewer_error)
        if viewer is not None:
            try:
                live = _blueprint(self.joints, self._eye, live=True)
                view = open_viewer(viewer, "reach-sim", self._recording_id, live, announce)
            except ViewerError as exc:
                self._viewer_error(exc, opening=True)
            else:
                self._out.viewer = view
                self._log_scene(ViewerTee(None, view, self._viewer_error))
        self._rec = self._open_part() if self.path is not None else None
        self._out.file = self._rec
        self._out.watch()
        self._last_flush = time.monotonic()
        self._rows_since_flush = 0
        self._urgent = False
        self._events_since_flush = False

    @property
    def viewing(self) -> bool:
        """A viewer is attached and has not failed."""
        return self._out.viewer is not None

    def _viewer_error(self, exc: Exception, opening: bool = False) -> None:
        if self.viewer_failed is not None:
            return
        self.viewer_failed = viewer_failure(self.viewer, exc, opening)
        self._warn(
            live_view_off(self.viewer_failed, self.path is not None, "the simulator runs on")
        )

    # -- parts ------------------------------------------------------------------------------
    def _open_part(self) -> rr.RecordingStream:
        assert self.path is not None
        rec = rr.RecordingStream(
            "reach-sim",
            recording_id=self._recording_id,
            batcher_config=rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=IDLE_FLUSH_S + 5.0)),
        )
        rec.save(str(self.path), default_blueprint=_blueprint(self.joints, self._eye))
        self._log_scene(rec)
        # Each part states the modes and faults it starts with.
        self._modes = None
        self._status = None
        self._chunks = _CHUNKS_AT_OPEN
        return rec

    def _log_scene(self, rec: rr.RecordingStream | ViewerTee) -> None:
        """The static scene and metadata every part (and the viewer) starts with."""
        rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        g = self._geoms
        rec.log(
            "arm/links",
            rr.Cylinders3D(radii=g.radii, lengths=g.lengths, colors=g.colors, fill_mode="solid"),
            static=True,
        )
        if len(g.boxes):
            rec.log(
                "arm/jaw",
                rr.Boxes3D(
                    half_sizes=g.half_sizes,
                    colors=[ARM_COLOR] * len(g.boxes),
                    fill_mode="solid",
                ),
                static=True,
            )
        for j in self.joints:
            rec.log(
                f"joints/{j}/position",
                rr.SeriesLines(names=["q", "setpoint"], colors=[ARM_COLOR, TARGET_COLOR]),
                static=True,
            )
            rec.log(
                f"joints/{j}/current",
                rr.SeriesLines(names=["applied", "drawn"], colors=[_APPLIED_COLOR, ARM_COLOR]),
                static=True,
            )
        for entity in ("torques", "velocities"):
            rec.log(
                entity,
                rr.SeriesLines(names=list(self.joints), colors=list(joint_colors(self.joints))),
                static=True,
            )
        rec.log(
            "link/frames",
            rr.SeriesLines(names=["frames in", "bad frames", "frames out"]),
            static=True,
        )
        meta = {
            "source": "reach-sim",
            "arm": self.model.name,
            "joint_names": list(self.joints),
            "rate_hz": self.rate_hz,
            "idle_rate_hz": self.idle_rate_hz,
            "speed": self.server.config.speed,
            "part": self.rotations,  # 0 for the first file written, counting up
            # How many samples the parts before this one hold: parts that join without a gap
            # satisfy first_sample + its own sample count == the next part's first_sample.
            "first_sample": self.samples,
            "max_bytes": self.max_bytes,
            "parts": self.parts,
        }
        rec.log("run/metadata", rr.TextDocument(json.dumps(meta)), static=True)

    def _rotate(self) -> None:
        """Close the current part and start the next: FILE.rrd -> FILE.1.rrd -> ...

        Only the renames and the new part's opening happen here, on the sampling thread; the
        old part's last flush and footer are written by a thread of their own (the open file
        follows its rename), so the arm's motion during them is sampled into the new part
        instead of being lost to a wait on the disk."""
        assert self._rec is not None and self.path is not None
        old = self._rec
        oldest = part_path(self.path, self.parts - 1)
        oldest.unlink(missing_ok=True)
        for n in range(self.parts - 2, -1, -1):
            src = part_path(self.path, n)
            if src.exists():
                os.replace(src, part_path(self.path, n + 1))
        self.rotations += 1
        self._rec = self._open_part()
        self._out.file = self._rec
        closer = threading.Thread(
            target=_close_part, args=(old,), name="reach-sim-part-closer", daemon=True
        )
        closer.start()
        self._closers = [t for t in self._closers if t.is_alive()] + [closer]

    # -- sampling ---------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="reach-sim-recorder", daemon=True)
        self._thread.start()

    def _quiet(self, s: _Sample, last: _Sample | None) -> bool:
        if last is None or s.modes != last.modes or s.status != last.status:
            return False
        if float(np.max(np.abs(s.qdot))) >= IDLE_SPEED:
            return False
        if float(np.max(np.abs(s.drawn_mA - last.drawn_mA))) >= IDLE_CURRENT_MA:
            return False
        return bool(np.array_equal(s.setpoint, last.setpoint, equal_nan=True))

    def _run(self) -> None:
        k, last_t = 0, -math.inf
        logged: _Sample | None = None  # the last sample logged
        skipped: tuple[_Sample, int] | None = None  # the last quiet one left out
        active_until = -math.inf
        while not self._stop.is_set():
            if not self.server.wait_sim_time(k * self.period, timeout=0.2):
                if not self.server.running:
                    break
                continue
            sample = self.server.observe(self._sample)
            if sample.t > last_t:  # the sim may not have stepped since the last look
                self.looked += 1
                last_t = sample.t
                if not self._quiet(sample, logged):
                    if skipped is not None and logged is not None:
                        self.log(*skipped)  # the state just before it changed
                    active_until = sample.t + HOLD_S
                if (
                    logged is None
                    or sample.t <= active_until
                    or sample.t - logged.t >= self.idle_period - 0.5 * self.period
                ):
                    self.log(sample, k)
                    logged, skipped = sample, None
                else:
                    skipped = (sample, k)
                self._maybe_flush()
            k = max(k + 1, int(sample.t / self.period) + 1)

    def log(self, s: _Sample, k: int) -> None:
        with self._lock:
            rec = self._out
            rec.set_time(TIMELINE_TIME, duration=s.t)
            rec.set_time(TIMELINE_STEP, sequence=k)
            for i, j in enumerate(self.joints):
                rec.log(f"joints/{j}/position", rr.Scalars([s.q[i], s.setpoint[i]]))
                rec.log(f"joints/{j}/current", rr.Scalars([s.applied_mA[i], s.drawn_mA[i]]))
            rec.log("torques", rr.Scalars(s.tau))
            rec.log("velocities", rr.Scalars(s.qdot))
            rec.log(
                "arm/links",
                rr.Cylinders3D.from_fields(centers=s.cylinder_pos, quaternions=s.cylinder_quat),
            )
            if len(s.box_pos):
                rec.log(
                    "arm/jaw", rr.Boxes3D.from_fields(centers=s.box_pos, quaternions=s.box_quat)
                )
            stats = self.server.stats()
            rec.log(
                "link/frames",
                rr.Scalars(
                    [float(stats.frames_in), float(stats.bad_total), float(stats.frames_out)]
                ),
            )
            if s.modes != self._modes:
                names = ", ".join(
                    f"{j}={m.name.lower()}" for j, m in zip(self.joints, s.modes, strict=True)
                )
                rec.log("events", rr.TextLog(f"modes: {names}", level="INFO"))
                self._modes = s.modes
                self._urgent = self._events_since_flush = True
            if s.status != self._status:
                faults = [
                    f"{j}={_flags(st)}" for j, st in zip(self.joints, s.status, strict=True) if st
                ]
                text = "faults: " + (", ".join(faults) if faults else "none")
                rec.log("events", rr.TextLog(text, level="WARN" if faults else "INFO"))
                self._status = s.status
                self._urgent = self._events_since_flush = True
            self.samples += 1
            self._rows_since_flush += 1

    # -- writing ----------------------------------------------------------------------------
    def _maybe_flush(self) -> None:
        waited = time.monotonic() - self._last_flush
        if waited < self.flush_period_s:
            return
        if self._rows_since_flush >= _MIN_ROWS_PER_FLUSH or self._urgent or waited >= IDLE_FLUSH_S:
            self.flush()

    def flush(self) -> None:
        """Write what is buffered; start the next part if this one is full."""
        with self._lock:
            if self._rec is not None:  # the file only: the viewer stream sends on its own
                self._rec.flush(timeout_sec=2.0)
            self._last_flush = time.monotonic()
            if self._rows_since_flush:  # a chunk per entity logged since the last flush
                per_sample = 2 * len(self.joints) + _PER_SAMPLE_ENTITIES
                self._chunks += per_sample + int(self._events_since_flush)
            self._rows_since_flush, self._urgent, self._events_since_flush = 0, False, False
            if self.part_bytes is not None and self.path is not None:
                try:
                    size = self.path.stat().st_size
                except OSError:
                    return
                if size + self._chunks * _FOOTER_BYTES_PER_CHUNK >= self.part_bytes:
                    self._rotate()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._out.unwatch()
        for closer in self._closers:
            closer.join(timeout=10.0)
        with self._lock:
            try:
                if self._rec is not None:
                    self._rec.flush(timeout_sec=5.0)
                    self._rec.disconnect()
            finally:
                self._out.close_viewer()


def _close_part(rec: rr.RecordingStream) -> None:
    """Write a rotated-out part's last samples and its footer."""
    rec.flush(timeout_sec=5.0)
    rec.disconnect()


def _flags(status: HardwareStatus) -> str:
    names = [f.name for f in HardwareStatus if f and f in status and f.name]
    return "|".join(names) if names else f"0x{int(status):08x}"
