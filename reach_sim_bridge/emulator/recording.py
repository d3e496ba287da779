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
second stream with the same recording id whose sink is a viewer, never flushed by the
recorder and not bounded (a viewer keeps what its memory limit allows); its first error is
reported once and it is dropped, the file and the simulator go on. Without `--record` the
arm is streamed only. The viewer code below is kept in step with `reach_driver.recording`
(the layering forbids a module both could import; `tests/test_live_viewer.py` checks they
read `--viewer` alike).
"""

from __future__ import annotations

import json
import math
import os
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from protocol import HardwareStatus, Mode
from protocol.alpha5 import JOINT_LETTERS as JOINTS
from reach_sim_bridge.emulator.firmware import Firmware
from reach_sim_bridge.emulator.server import SimServer
from reach_sim_bridge.model.arm import Alpha5Arm

DEVICE_IDS = (0x05, 0x04, 0x03, 0x02)
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
_CHUNKS_AT_OPEN = 60  # the blueprint's and the static scene's
_PER_SAMPLE_ENTITIES = 13  # joints x 8, torques, velocities, links, jaw, link/frames

_ARM_COLOR = (230, 150, 40, 255)
_BASE_COLOR = (90, 90, 90, 255)
_LINKS = ("m3_inline", "m2_1_1", "m2", "m2_1_3", "m1", "jaw")


#: where `--viewer connect` looks without a URL: a viewer started with plain `rerun`
DEFAULT_VIEWER_PORT = 9876
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_VIEWER_PORT}/proxy"
#: `--viewer serve`: the gRPC port (loopback only) and the web viewer's HTTP port
DEFAULT_WEB_PORT = 9090
VIEWER_MODES = ("spawn", "connect", "serve")
VIEWER_USAGE = (
    "spawn [PORT] | connect [URL|PORT] | serve [GRPC_PORT [WEB_PORT]] "
    f"(defaults: port {DEFAULT_VIEWER_PORT}, {DEFAULT_VIEWER_URL}, web port {DEFAULT_WEB_PORT})"
)
_PROBE_TIMEOUT_S = 1.0
_VIEWER_CLOSE_S = 1.0  # the longest closing waits for a viewer that stopped answering
_VIEWER_WATCH_S = 1.0  # how often the viewer stream is flushed, off the control thread


@dataclass(frozen=True)
class ViewerSpec:
    """Where a live copy of a recording goes (`--viewer`)."""

    mode: str  # "spawn" | "connect" | "serve"
    url: str = DEFAULT_VIEWER_URL  # connect: the viewer; spawn/serve: the gRPC address made
    port: int = DEFAULT_VIEWER_PORT  # spawn and serve: the gRPC port
    web_port: int = DEFAULT_WEB_PORT  # serve: the web viewer's HTTP port
    bind: str = "127.0.0.1"  # serve: loopback only; reach it over SSH (`ssh -L`)

    @property
    def web_url(self) -> str:
        """serve: the address to open in a browser (the web viewer, told where the data is)."""
        return f"http://127.0.0.1:{self.web_port}/?url=rerun%2Bhttp://127.0.0.1:{self.port}/proxy"

    def describe(self) -> str:
        if self.mode == "serve":
            return f"serve (gRPC {self.bind}:{self.port}, web viewer port {self.web_port})"
        return f"{self.mode} {self.url}"


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"not a port number: {text!r}") from None
    if not 1 <= value <= 65535:
        raise ValueError(f"a port is 1..65535, got {text}")
    return value


def _url_port(url: str) -> tuple[str, int]:
    """(host, port) of a rerun gRPC URL (`rerun+http://HOST:PORT/proxy`)."""
    rest = url.split("://", 1)[1] if "://" in url else url
    hostport = rest.split("/", 1)[0]
    host, sep, port = hostport.rpartition(":")
    if not sep:
        return hostport, 443 if url.startswith("rerun+https") else 80
    return host.strip("[]") or "127.0.0.1", _port(port)


def parse_viewer(words: Sequence[str]) -> ViewerSpec:
    """`--viewer` words: `spawn [PORT]`, `connect [URL|PORT]`, `serve [GRPC_PORT [WEB_PORT]]`
    (ValueError saying what is wrong)."""
    if not words or words[0] not in VIEWER_MODES:
        raise ValueError(f"expected {VIEWER_USAGE}; got {' '.join(words)!r}")
    mode, rest = words[0], list(words[1:])
    limit = {"spawn": 1, "connect": 1, "serve": 2}[mode]
    if len(rest) > limit:
        raise ValueError(
            f"{mode} takes at most {limit} value(s), got {' '.join(rest)!r} (put --viewer "
            "after positional arguments such as move's angles)"
        )
    if mode == "connect":
        if not rest:
            return ViewerSpec("connect")
        target = rest[0]
        if "://" not in target:
            port = _port(target)
            return ViewerSpec("connect", url=f"rerun+http://127.0.0.1:{port}/proxy", port=port)
        if not target.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise ValueError(
                f"a viewer URL starts rerun+http://, rerun+https:// or rerun://, got {target!r}"
            )
        return ViewerSpec("connect", url=target, port=_url_port(target)[1])
    port = _port(rest[0]) if rest else DEFAULT_VIEWER_PORT
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if mode == "spawn":
        return ViewerSpec("spawn", url=url, port=port)
    web = _port(rest[1]) if len(rest) > 1 else DEFAULT_WEB_PORT
    if web == port:
        raise ValueError(f"serve: the gRPC and web ports must differ, both are {port}")
    return ViewerSpec("serve", url=url, port=port, web_port=web)


def _answers(host: str, port: int, timeout: float = _PROBE_TIMEOUT_S) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def _free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def _rerun_executable() -> str | None:
    """The viewer installed beside this Python (a venv's bin/rerun), else None: rerun looks
    in PATH (which a venv that was not activated does not put first)."""
    candidate = os.path.join(os.path.dirname(sys.executable), "rerun")
    return candidate if os.access(candidate, os.X_OK) else None


class ViewerError(RuntimeError):
    """The viewer could not be started or reached (the caller warns and goes on)."""


def open_viewer(
    spec: ViewerSpec,
    app_id: str,
    recording_id: str,
    blueprint: rrb.Blueprint | None,
    announce: Callable[[str], None] | None = None,
) -> rr.RecordingStream:
    """A stream whose sink is the viewer `spec` asks for (ViewerError if it cannot be had).

    connect: the address must answer first (a GrpcSink to nothing would buffer the run in
    memory and make every flush wait); spawn: `rr.spawn(connect=False)`, then a GrpcSink to
    it; serve: a GrpcServerSink on loopback and the web viewer, their address announced."""
    rec = rr.RecordingStream(app_id, recording_id=recording_id)
    say = announce or (lambda _msg: None)
    try:
        if spec.mode == "connect":
            host, port = _url_port(spec.url)
            if not _answers(host, port):
                raise ViewerError(
                    f"no Rerun viewer answers at {spec.url} (start one with `rerun`, or watch "
                    "with --viewer serve)"
                )
            rec.set_sinks(rr.GrpcSink(spec.url), default_blueprint=blueprint)
        elif spec.mode == "spawn":
            if sys.platform.startswith("linux") and not (
                os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
            ):
                raise ViewerError(
                    "--viewer spawn needs a display (neither DISPLAY nor WAYLAND_DISPLAY is "
                    "set); on a machine without one use --viewer serve"
                )
            rr.spawn(
                port=spec.port,
                connect=False,
                recording=rec,
                hide_welcome_screen=True,
                executable_path=_rerun_executable(),
            )
            if not _answers("127.0.0.1", spec.port):
                raise ViewerError(f"the spawned viewer does not listen on port {spec.port}")
            rec.set_sinks(rr.GrpcSink(spec.url), default_blueprint=blueprint)
        else:  # serve
            for port, what in ((spec.port, "gRPC"), (spec.web_port, "web viewer")):
                if not _free(spec.bind if what == "gRPC" else "0.0.0.0", port):
                    raise ViewerError(
                        f"port {port} ({what}) is in use, by another run serving or a viewer: "
                        "pick others (--viewer serve GRPC_PORT WEB_PORT) or --viewer connect"
                    )
            rec.set_sinks(
                rr.GrpcServerSink(bind_ip=spec.bind, port=spec.port), default_blueprint=blueprint
            )
            rr.serve_web_viewer(web_port=spec.web_port, open_browser=False, connect_to=spec.url)
            say(
                f"viewer: open {spec.web_url} (web), or `rerun --connect {spec.url}` (native); "
                f"from another machine forward both ports first: ssh -L {spec.web_port}:"
                f"localhost:{spec.web_port} -L {spec.port}:localhost:{spec.port} HOST"
            )
        return rec
    except ViewerError:
        _drop(rec)
        raise
    except Exception as exc:  # rerun raises RuntimeError (no executable, a port it cannot bind)
        _drop(rec)
        raise ViewerError(f"{type(exc).__name__}: {exc}") from None


def _drop(rec: rr.RecordingStream, wait_s: float = _VIEWER_CLOSE_S) -> None:
    """Disconnect a viewer stream without waiting long: rerun's disconnect waits up to 5 s
    for a viewer that does not answer, so it runs on a daemon thread given `wait_s`."""

    def close() -> None:
        try:
            rec.flush(timeout_sec=wait_s)
        except Exception:  # a viewer that is gone: nothing more to send
            pass
        try:
            rec.disconnect()
        except Exception:
            pass

    thread = threading.Thread(target=close, name="rerun-viewer-close", daemon=True)
    thread.start()
    thread.join(timeout=2 * wait_s + 0.5)


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
    bodies = {model.body(name).id for name in _LINKS}
    base = model.body("m3_inline").id
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
        colors=[_BASE_COLOR if model.geom_bodyid[g] == base else _ARM_COLOR for g in cylinders],
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


def _sampler(geoms: _Geoms):  # type: ignore[no-untyped-def]
    def sample(arm: Alpha5Arm, firmware: Firmware) -> _Sample:
        setpoints = [firmware.setpoints(dev) for dev in DEVICE_IDS]
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
            status=tuple(firmware.status(dev) for dev in DEVICE_IDS),
            cylinder_pos=data.geom_xpos[geoms.cylinders].copy(),
            cylinder_quat=_quats_xyzw(data.geom_xmat[geoms.cylinders]),
            box_pos=data.geom_xpos[geoms.boxes].copy(),
            box_quat=_quats_xyzw(data.geom_xmat[geoms.boxes]),
        )

    return sample


def part_path(path: Path, n: int) -> Path:
    """FILE.rrd for the newest part (n = 0), FILE.<n>.rrd for the older ones."""
    return path if n == 0 else path.with_name(f"{path.stem}.{n}{path.suffix}")


def _blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="/", contents=["/arm/**"], name="arm, true state (m)"),
                rrb.TextLogView(origin="/events", name="events (modes, faults)"),
                row_shares=[4, 1],
            ),
            rrb.Vertical(
                *[
                    rrb.Horizontal(
                        rrb.TimeSeriesView(
                            origin=f"/joints/{j}/position",
                            name=f"{j}: true position vs setpoint (rad)",
                        ),
                        rrb.TimeSeriesView(
                            origin=f"/joints/{j}/current",
                            name=f"{j}: current, applied vs drawn (mA)",
                        ),
                    )
                    for j in JOINTS
                ]
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/torques", name="torques delivered (N m)"),
                rrb.TimeSeriesView(origin="/velocities", name="velocities (rad/s)"),
                rrb.TimeSeriesView(origin="/link/frames", name="link: frames (count)"),
            ),
            column_shares=[3, 4, 2],
        ),
        rrb.TimePanel(timeline=TIMELINE_TIME, state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


class _Tee:
    """Logs to the file stream (its errors propagate: the caller decides) and to the viewer
    stream (its first error is reported through `on_viewer_error` and the viewer dropped)."""

    def __init__(
        self,
        file: rr.RecordingStream | None,
        viewer: rr.RecordingStream | None,
        on_viewer_error: Callable[[Exception], None],
    ) -> None:
        self.file, self.viewer = file, viewer
        self._on_viewer_error = on_viewer_error
        self._watching = threading.Event()

    def _to_viewer(self, call: Callable[[rr.RecordingStream], None]) -> None:
        viewer = self.viewer
        if viewer is None:
            return
        try:
            call(viewer)
        except Exception as exc:
            self._fail(viewer, exc)

    def _fail(self, viewer: rr.RecordingStream, exc: Exception) -> None:
        if self.viewer is not viewer:
            return  # already dropped
        self.viewer = None
        self._on_viewer_error(exc)  # first: `viewing` is False only once it is said
        _drop(viewer, wait_s=0.1)

    def watch(self, period_s: float = _VIEWER_WATCH_S) -> None:
        """Flush the viewer stream every `period_s` on a thread of its own: a viewer that went
        away (rerun reports it only on a flush) is noticed, named and dropped without the
        control loop ever waiting for it. A flush that merely times out (a slow viewer) is
        not a failure."""
        if self.viewer is None or self._watching.is_set():
            return
        self._watching.set()

        def run() -> None:
            while self._watching.is_set():
                time.sleep(period_s)
                viewer = self.viewer
                if viewer is None or not self._watching.is_set():
                    return
                try:
                    viewer.flush(timeout_sec=period_s)
                except Exception as exc:
                    if "timed out" not in str(exc).lower():
                        self._fail(viewer, exc)
                        return

        threading.Thread(target=run, name="rerun-viewer-watch", daemon=True).start()

    def unwatch(self) -> None:
        self._watching.clear()

    def log(self, path: str, entity: Any, static: bool = False) -> None:
        if self.file is not None:
            self.file.log(path, entity, static=static)
        self._to_viewer(lambda v: v.log(path, entity, static=static))

    def set_time(self, timeline: str, **kw: Any) -> None:
        if self.file is not None:
            self.file.set_time(timeline, **kw)
        self._to_viewer(lambda v: v.set_time(timeline, **kw))


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
        self._recording_id = f"reach-sim-{time.time_ns()}"
        self._geoms = server.observe(lambda arm, _fw: _geoms(arm.model))
        self._sample = _sampler(self._geoms)
        self._lock = threading.Lock()  # the stream, across rotation and outside flushes
        self._modes: tuple[Mode, ...] | None = None
        self._status: tuple[HardwareStatus, ...] | None = None
        self._chunks = _CHUNKS_AT_OPEN
        self._out = _Tee(None, None, self._viewer_error)
        if viewer is not None:
            try:
                view = open_viewer(viewer, "reach-sim", self._recording_id, _blueprint(), announce)
            except ViewerError as exc:
                self._viewer_error(exc, opening=True)
            else:
                self._out.viewer = view
                self._log_scene(_Tee(None, view, self._viewer_error))
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
        what = self.viewer.describe() if self.viewer is not None else "viewer"
        when = "could not be started" if opening else "failed"
        self.viewer_failed = f"--viewer {what} {when}: {exc}"
        where = "the recording goes on" if self.path is not None else "nothing is recorded"
        self._warn(f"{self.viewer_failed}; live view off, {where}, the simulator runs on")

    # -- parts ------------------------------------------------------------------------------
    def _open_part(self) -> rr.RecordingStream:
        assert self.path is not None
        rec = rr.RecordingStream(
            "reach-sim",
            recording_id=self._recording_id,
            batcher_config=rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=IDLE_FLUSH_S + 5.0)),
        )
        rec.save(str(self.path), default_blueprint=_blueprint())
        self._log_scene(rec)
        # Each part states the modes and faults it starts with.
        self._modes = None
        self._status = None
        self._chunks = _CHUNKS_AT_OPEN
        return rec

    def _log_scene(self, rec: rr.RecordingStream | _Tee) -> None:
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
                    colors=[_ARM_COLOR] * len(g.boxes),
                    fill_mode="solid",
                ),
                static=True,
            )
        for j in JOINTS:
            rec.log(f"joints/{j}/position", rr.SeriesLines(names=["q", "setpoint"]), static=True)
            rec.log(f"joints/{j}/current", rr.SeriesLines(names=["applied", "drawn"]), static=True)
        for entity in ("torques", "velocities"):
            rec.log(entity, rr.SeriesLines(names=list(JOINTS)), static=True)
        rec.log(
            "link/frames",
            rr.SeriesLines(names=["frames in", "bad frames", "frames out"]),
            static=True,
        )
        meta = {
            "source": "reach-sim",
            "joint_names": list(JOINTS),
            "rate_hz": self.rate_hz,
            "idle_rate_hz": self.idle_rate_hz,
            "speed": self.server.config.speed,
            "part": self.rotations,  # 0 for the first file written, counting up
            "max_bytes": self.max_bytes,
            "parts": self.parts,
        }
        rec.log("run/metadata", rr.TextDocument(json.dumps(meta)), static=True)

    def _rotate(self) -> None:
        """Close the current part and start the next: FILE.rrd -> FILE.1.rrd -> ..."""
        assert self._rec is not None and self.path is not None
        self._rec.flush(timeout_sec=5.0)
        self._rec.disconnect()
        oldest = part_path(self.path, self.parts - 1)
        oldest.unlink(missing_ok=True)
        for n in range(self.parts - 2, -1, -1):
            src = part_path(self.path, n)
            if src.exists():
                os.replace(src, part_path(self.path, n + 1))
        self.rotations += 1
        self._rec = self._open_part()
        self._out.file = self._rec

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
            for i, j in enumerate(JOINTS):
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
                    f"{j}={m.name.lower()}" for j, m in zip(JOINTS, s.modes, strict=True)
                )
                rec.log("events", rr.TextLog(f"modes: {names}", level="INFO"))
                self._modes = s.modes
                self._urgent = self._events_since_flush = True
            if s.status != self._status:
                faults = [f"{j}={_flags(st)}" for j, st in zip(JOINTS, s.status, strict=True) if st]
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
                self._chunks += _PER_SAMPLE_ENTITIES + int(self._events_since_flush)
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
        with self._lock:
            viewer, self._out.viewer = self._out.viewer, None
            try:
                if self._rec is not None:
                    self._rec.flush(timeout_sec=5.0)
                    self._rec.disconnect()
            finally:
                if viewer is not None:
                    _drop(viewer)


def _flags(status: HardwareStatus) -> str:
    names = [f.name for f in HardwareStatus if f and f in status and f.name]
    return "|".join(names) if names else f"0x{int(status):08x}"
