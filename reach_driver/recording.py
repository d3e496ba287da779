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

Live viewing (`ViewerSpec`, `reach-driver run/move/monitor --viewer`): the same entities go to a
second stream with the same recording id whose sink is a Rerun viewer: one spawned here
(`spawn`), one already running (`connect URL`, a `GrpcSink`), or a gRPC server plus the web
viewer hosted by this process (`serve`, a `GrpcServerSink` and `rr.serve_web_viewer`) for a
machine without a display. The file and the viewer are separate streams on purpose: in rerun
0.41 a stream's `flush()` waits for every sink and raises if any fails, so with one stream of
two sinks a viewer that went away would block the control loop at each flush and end the file.
The viewer stream is never flushed on the loop's thread; its first error is reported once and
it is dropped, the file goes on.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import threading
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
from reach_driver.arm_geometry import GEOMS, LinkGeom
from reach_driver.kinematics import CHAIN, TCP_OFFSET_M, joint_transform
from reach_driver.state import MONITOR_READINGS, JointState, Reading, joint_name

TIMELINE_TIME = "arm_time"
TIMELINE_STEP = "step"
BASE_LINK = "m3_inline"

_ARM_COLOR = (230, 150, 40, 255)
_BASE_COLOR = (90, 90, 90, 255)
_GHOST_COLOR = (80, 170, 255, 70)
_TARGET_COLOR = (80, 170, 255, 255)
_MEASURED_COLOR = (120, 120, 120, 255)
_JOINT_COLORS = [(230, 90, 60, 255), (90, 180, 80, 255), (70, 130, 230, 255), (200, 170, 40, 255)]

#: (entity, view title) of every time-series view of the default blueprint; titles carry units.
LINK_VIEWS = (
    ("link/frames", "link: frames received (count)"),
    ("link/state_age", "link: state age (ms)"),
    ("link/latency", "link: latency, state to command (ms)"),
)

#: The devices of the diagnostics entities, in their order: the four joints, then the jaw.
DIAGNOSTIC_LETTERS = tuple(d.name for d in ALL_DEVICES)
STATUS_ENTITY = "diagnostics/status"
#: (entity, view title) of the diagnostics' views: one per Monitor reading, then the flags.
DIAGNOSTIC_VIEWS = (
    *((f"diagnostics/{m.key}", m.title) for m in MONITOR_READINGS),
    (STATUS_ENTITY, "HARDWARE_STATUS as one 32-bit value, byte A highest (flags)"),
)


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


def _series_view(origin: str, name: str) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(origin=origin, name=name)


def default_blueprint() -> rrb.Blueprint:
    """Opens on the arm-time timeline (seconds): the 3D arm and its ghost, errors and events;
    per joint its position vs target (rad) beside its currents (mA); torques, velocities and
    the link's counts, state age and latency, each on its own scale; the devices' Monitor
    readings and status flags."""
    joint_rows = [
        rrb.Horizontal(
            _series_view(f"/joints/{j}/position", f"{j}: position q vs target (rad)"),
            _series_view(f"/joints/{j}/current", f"{j}: current, commanded vs measured (mA)"),
        )
        for j in JOINT_LETTERS
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(
                    origin="/",
                    contents=["/arm/**", "/target/**"],
                    name="arm (m), target pose as a ghost",
                ),
                _series_view("/errors", "errors: target - q (rad)"),
                rrb.TextLogView(origin="/events", name="events"),
                row_shares=[4, 2, 1],
            ),
            rrb.Vertical(*joint_rows),
            rrb.Vertical(
                _series_view("/torques", "torques (N m)"),
                _series_view("/velocities", "velocities (rad/s)"),
                *(_series_view(f"/{entity}", name) for entity, name in LINK_VIEWS),
            ),
            rrb.Vertical(
                *(_series_view(f"/{entity}", name) for entity, name in DIAGNOSTIC_VIEWS),
            ),
            column_shares=[3, 4, 2, 2],
        ),
        rrb.TimePanel(timeline=TIMELINE_TIME, state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def log_link_geoms(
    rec: rr.RecordingStream | _Tee,
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
        blueprint = default_blueprint()
        file_rec: rr.RecordingStream | None = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            file_rec = rr.RecordingStream(app_id, recording_id=recording_id)
            file_rec.save(str(self.path), default_blueprint=blueprint)
        view_rec: rr.RecordingStream | None = None
        if viewer is not None:
            try:
                view_rec = open_viewer(viewer, app_id, recording_id, blueprint, announce)
            except ViewerError as exc:
                self._viewer_error(exc, opening=True)
        self._rec = _Tee(file_rec, view_rec, self._viewer_error)
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
        what = self.viewer.describe() if self.viewer is not None else "viewer"
        when = "could not be started" if opening else "failed"
        self.viewer_failed = f"--viewer {what} {when}: {exc}"
        where = "the recording goes on" if self.path is not None else "nothing is recorded"
        self._warn(f"{self.viewer_failed}; live view off, {where}, control is unaffected")

    # -- static scene -------------------------------------------------------------------
    def _log_static_scene(self, metadata: Mapping[str, object]) -> None:
        rec = self._rec
        rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        log_link_geoms(rec, "arm", [g for g in GEOMS if g.link == BASE_LINK], _BASE_COLOR)
        tcp = [[0.0, 0.0, TCP_OFFSET_M]]
        for links, color in ((self._arm_links, _ARM_COLOR), (self._ghost_links, _GHOST_COLOR)):
            for path, frame in zip(links, CHAIN, strict=True):
                log_link_geoms(rec, path, [g for g in GEOMS if g.link == frame.child_link], color)
            rec.log(f"{links[-1]}/tcp", rr.Points3D(tcp, radii=0.006, colors=[color]), static=True)
        for j in JOINT_LETTERS:
            rec.log(
                f"joints/{j}/position",
                rr.SeriesLines(names=["q", "target"], colors=[_ARM_COLOR, _TARGET_COLOR]),
                static=True,
            )
            rec.log(
                f"joints/{j}/current",
                rr.SeriesLines(
                    names=["commanded", "measured"], colors=[_ARM_COLOR, _MEASURED_COLOR]
                ),
                static=True,
            )
        names = [f"{j}" for j in JOINT_LETTERS]
        for entity in ("errors", "velocities", "torques"):
            rec.log(entity, rr.SeriesLines(names=names, colors=_JOINT_COLORS), static=True)
        rec.log("link/frames", rr.SeriesLines(names=["good frames", "bad frames"]), static=True)
        rec.log("link/state_age", rr.SeriesLines(names=["state age ms"]), static=True)
        rec.log("link/latency", rr.SeriesLines(names=["latency ms"]), static=True)
        for entity, _ in DIAGNOSTIC_VIEWS:
            rec.log(entity, rr.SeriesLines(names=list(DIAGNOSTIC_LETTERS)), static=True)
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
    ) -> None:
        """The link's health at one step: frame counts, state age and (if known) the latency
        from the state being complete to the command being written, each its own entity."""
        self._set_time(t, step)
        rec = self._rec
        rec.log("link/frames", rr.Scalars([float(good), float(bad)]))
        rec.log("link/state_age", rr.Scalars(state_age_s * 1e3))
        if latency_s is not None:
            rec.log("link/latency", rr.Scalars(latency_s * 1e3))

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

    def _close_viewer(self) -> None:
        self._rec.unwatch()
        viewer, self._rec.viewer = self._rec.viewer, None
        if viewer is not None:
            _drop(viewer)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            if self._rec.file is not None:
                self._rec.file.flush(timeout_sec=5.0)
                self._rec.file.disconnect()
        finally:
            self._close_viewer()

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
            self._close_viewer()

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
