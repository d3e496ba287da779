"""Live viewing of a Rerun recording (`--viewer spawn | connect | serve`), one copy for the
driver's recorder and the simulator's.

None of this is the codec. It lives in `protocol` for the reason `protocol.alpha5` does: that
is the one package the driver and the simulator share (neither may import the other), and both
must read `--viewer` alike and open, watch and drop a viewer the same way. `protocol/__init__`
does not import it, and rerun is imported only when a viewer is opened, so both command lines
read `--viewer` without loading rerun.

A recorder sends its entities to two streams with the same recording id: its file, and one
whose sink is the viewer (`open_viewer`): one spawned here (`spawn`), one already running
(`connect URL`, a `GrpcSink`), or a gRPC server plus the web viewer (`serve`, a
`GrpcServerSink` here and the web viewer in a child `rerun --serve-web --bind ADDR`) for a
machine without a display. Both listen on loopback unless `--viewer-bind` says otherwise: a
robot's telemetry is not served to the network unasked. (rerun 0.41's `rr.serve_web_viewer`
takes no bind address and listens on every interface, so it is not used.) They
are separate streams on purpose: in rerun 0.41 a stream's `flush()` waits for every sink and
raises if any fails, so with one stream of two sinks a viewer that went away would block the
logging thread at each flush and end the file. `ViewerTee` logs to both; the viewer stream is
flushed only on a thread of its own, and its first error is reported once and it is dropped,
the file goes on.

The viewer stream sends every LIVE_FLUSH_S (fewer, larger messages than rerun's default, which
a slowly drawing viewer could not keep up with), and `serve` replays what a viewer that joins
late missed newest first, so it shows the present at once. `--viewer-keep` (`add_viewer_option`
with `keep`) is the command line's: its recorder leaves the stream open when the command is
done, and `reach-driver` closes it on Ctrl-C.
"""

from __future__ import annotations

import argparse
import importlib.util
import ipaddress
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

#: where `--viewer connect` looks without a URL: a viewer started with plain `rerun`
DEFAULT_VIEWER_PORT = 9876
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_VIEWER_PORT}/proxy"
#: `--viewer serve`: the gRPC port and the web viewer's HTTP port
DEFAULT_WEB_PORT = 9090
#: `--viewer serve` listens here unless `--viewer-bind` says otherwise: this machine only
DEFAULT_BIND = "127.0.0.1"
_WEB_START_S = 20.0  # the longest the web viewer's process may take to listen (a loaded host)
VIEWER_MODES = ("spawn", "connect", "serve")
VIEWER_USAGE = (
    "spawn [PORT] | connect [URL|PORT] | serve [GRPC_PORT [WEB_PORT]] "
    f"(defaults: port {DEFAULT_VIEWER_PORT}, {DEFAULT_VIEWER_URL}, web port {DEFAULT_WEB_PORT})"
)
_PROBE_TIMEOUT_S = 1.0
_VIEWER_CLOSE_S = 1.0  # the longest closing waits for a viewer that stopped answering
_VIEWER_WATCH_S = 1.0  # how often the viewer stream is flushed, off the logging thread
#: How often the viewer stream sends what was logged (a chunk per entity, every entity). A
#: viewer takes in messages for about 10 ms a frame (rerun 0.41); one that draws a frame a
#: second or less (a browser on software WebGL) fell ever further behind rerun's default
#: 0.2 s chunks. Twice a second keeps a live arm moving and sends 2.5 times fewer messages.
LIVE_FLUSH_S = 0.5


@dataclass(frozen=True)
class ViewerSpec:
    """Where a live copy of a recording goes (`--viewer`)."""

    mode: str  # "spawn" | "connect" | "serve"
    url: str = DEFAULT_VIEWER_URL  # connect: the viewer; spawn/serve: the gRPC address made
    port: int = DEFAULT_VIEWER_PORT  # spawn and serve: the gRPC port
    web_port: int = DEFAULT_WEB_PORT  # serve: the web viewer's HTTP port
    bind: str = DEFAULT_BIND  # serve: where both listen (loopback: reach it over `ssh -L`)

    @property
    def host(self) -> str:
        """serve: the address this machine reaches both servers at."""
        return _connect_host(self.bind)

    @property
    def web_url(self) -> str:
        """serve: the address to open in a browser (the web viewer, told where the data is)."""
        host = _url_host(self.host)
        return f"http://{host}:{self.web_port}/?url=rerun%2Bhttp://{host}:{self.port}/proxy"

    @property
    def loopback(self) -> bool:
        return ipaddress.ip_address(self.bind).is_loopback

    def describe(self) -> str:
        if self.mode == "serve":
            return f"serve (gRPC {self.bind}:{self.port}, web viewer {self.bind}:{self.web_port})"
        return f"{self.mode} {self.url}"


def _connect_host(bind: str) -> str:
    """Where to reach a server bound to `bind`: itself, or loopback for 'every interface'."""
    address = ipaddress.ip_address(bind)
    if address.is_unspecified:
        return "127.0.0.1" if address.version == 4 else "::1"
    return bind


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def with_bind(spec: ViewerSpec, bind: str) -> ViewerSpec:
    """`spec` (serve) listening on `bind` (ValueError if it is no IP address or not serve)."""
    try:
        ipaddress.ip_address(bind)
    except ValueError:
        raise ValueError(f"--viewer-bind takes an IP address, got {bind!r}") from None
    if spec.mode != "serve":
        raise ValueError(f"--viewer-bind is for --viewer serve, not {spec.mode}")
    bound = replace(spec, bind=bind)
    return replace(bound, url=f"rerun+http://{_url_host(bound.host)}:{spec.port}/proxy")


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


class ViewerAction(argparse.Action):
    """`--viewer MODE [VALUE...]` into a `ViewerSpec` (usage error if the words are wrong)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        try:
            spec = parse_viewer(list(values))
            bind = getattr(namespace, "viewer_bind", None)
            if bind is not None:
                spec = with_bind(spec, bind)
        except ValueError as exc:
            raise argparse.ArgumentError(self, str(exc)) from None
        setattr(namespace, self.dest, spec)


class ViewerBindAction(argparse.Action):
    """`--viewer-bind ADDR`: where `--viewer serve` listens (before or after `--viewer`)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        spec = getattr(namespace, "viewer", None)
        try:
            bound = with_bind(spec if spec is not None else ViewerSpec("serve"), str(values))
        except ValueError as exc:
            raise argparse.ArgumentError(self, str(exc)) from None
        setattr(namespace, self.dest, str(values))
        if spec is not None:
            namespace.viewer = bound


BIND_HELP = (
    "with --viewer serve: the address the gRPC server and the web viewer listen on (default "
    f"{DEFAULT_BIND}, this machine only; watch from elsewhere through ssh -L). 0.0.0.0 (or a "
    "LAN address) serves the arm's telemetry to anyone who can reach this machine: only on a "
    "network you trust"
)


KEEP_HELP = (
    "with --viewer serve: when the command is done (the arm left safe, the summary printed, "
    "the recording closed, the port released), go on serving what it streamed until Ctrl-C, "
    "so a viewer can still open or reread it; the exit status is the command's own"
)


def add_viewer_option(
    parser: argparse._ActionsContainer, help_text: str, keep: bool = False
) -> None:
    """`--viewer MODE [VALUE...]` on a parser or an argument group (None when not given), and
    `--viewer-bind ADDR` beside it; with `keep`, `--viewer-keep` too (a command that ends by
    itself: serving on after it is worth asking for)."""
    parser.add_argument(
        "--viewer",
        nargs="+",
        action=ViewerAction,
        metavar=("MODE", "VALUE"),
        default=None,
        help=help_text,
    )
    parser.add_argument(
        "--viewer-bind", action=ViewerBindAction, metavar="ADDR", default=None, help=BIND_HELP
    )
    if keep:
        parser.add_argument("--viewer-keep", action="store_true", help=KEEP_HELP)


def viewer_options_problem(args: argparse.Namespace) -> str | None:
    """A `--viewer-bind` or `--viewer-keep` given without `--viewer serve` (for the parser's
    error), or None."""
    viewer = getattr(args, "viewer", None)
    if getattr(args, "viewer_bind", None) is not None and viewer is None:
        return "--viewer-bind is for --viewer serve, which was not given"
    if getattr(args, "viewer_keep", False) and (viewer is None or viewer.mode != "serve"):
        given = "was not given" if viewer is None else f"not --viewer {viewer.mode}"
        return (
            f"--viewer-keep is for --viewer serve, {given} (a spawned or connected viewer "
            "outlives the command anyway)"
        )
    return None


def _answers(host: str, port: int, timeout: float = _PROBE_TIMEOUT_S) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def _free(host: str, port: int) -> bool:
    """Whether a server could listen on `port`: nothing listens there. Closed connections
    lingering in TIME_WAIT (a browser that watched the last run) do not count: the servers
    bind with SO_REUSEADDR, as this probe does."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def _rerun_cli() -> str | None:
    """The `rerun` binary itself (rerun_cli's), so the web viewer's process is the one this
    process stops; else the venv's or PATH's `rerun` script."""
    found = importlib.util.find_spec("rerun_cli")
    if found is not None and found.origin:
        binary = os.path.join(os.path.dirname(found.origin), "rerun")
        if os.access(binary, os.X_OK):
            return binary
    return _rerun_executable() or shutil.which("rerun")


def _die_with_parent() -> None:
    """In the web viewer's child, before exec: it gets SIGTERM if this process dies (Linux)."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except Exception:
        pass


def _start_web_viewer(spec: ViewerSpec) -> subprocess.Popen[bytes]:
    """The web viewer on `spec.bind`:`spec.web_port`, pointed at the gRPC server, in a child
    `rerun` (which, unlike `rr.serve_web_viewer`, takes a bind address); it is listening when
    this returns (ViewerError if it cannot be started)."""
    exe = _rerun_cli()
    if exe is None:
        raise ViewerError("--viewer serve needs the `rerun` viewer (rerun-sdk), not found")
    cmd = [exe, "--serve-web", "--bind", spec.bind, "--web-viewer-port", str(spec.web_port)]
    proc = subprocess.Popen(
        [*cmd, spec.url],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # Ctrl-C is this process's to handle; it stops the child
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
    )
    end = time.monotonic() + _WEB_START_S
    while not _answers(spec.host, spec.web_port, timeout=0.2):
        if proc.poll() is not None or time.monotonic() > end:
            _stop_process(proc)
            raise ViewerError(
                f"the web viewer did not start on {spec.bind}:{spec.web_port} "
                f"(`rerun --serve-web` exit status {proc.returncode})"
            )
        time.sleep(0.05)
    return proc


def _stop_process(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=2.0)


#: The attribute of a served stream that stops its web viewer (`drop_viewer` calls it).
_STOP_WEB = "_reach_stop_web_viewer"


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
    import rerun as rr

    rec = rr.RecordingStream(
        app_id,
        recording_id=recording_id,
        batcher_config=rr.ChunkBatcherConfig(flush_tick=LIVE_FLUSH_S),
    )
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
                if not _free(spec.bind, port):
                    raise ViewerError(
                        f"port {port} ({what}) is in use, by another run serving or a viewer: "
                        "pick others (--viewer serve GRPC_PORT WEB_PORT) or --viewer connect"
                    )
            rec.set_sinks(
                # a viewer that joins late is sent the newest data first: the present at once,
                # the run's start after it
                rr.GrpcServerSink(bind_ip=spec.bind, port=spec.port, newest_first=True),
                default_blueprint=blueprint,
            )
            web = _start_web_viewer(spec)
            setattr(rec, _STOP_WEB, weakref.finalize(rec, _stop_process, web))
            if spec.loopback:
                reach = (
                    f"from another machine forward both ports first: ssh -L {spec.web_port}:"
                    f"localhost:{spec.web_port} -L {spec.port}:localhost:{spec.port} HOST"
                )
            else:
                reach = (
                    f"listening on {spec.bind} (--viewer-bind): anyone who can reach ports "
                    f"{spec.port} and {spec.web_port} of this machine can watch"
                )
            native = f"`rerun --connect {spec.url}` (native)"
            say(f"viewer: open {spec.web_url} (web), or {native}; {reach}")
        return rec
    except ViewerError:
        drop_viewer(rec)
        raise
    except Exception as exc:  # rerun raises RuntimeError (no executable, a port it cannot bind)
        drop_viewer(rec)
        raise ViewerError(f"{type(exc).__name__}: {exc}") from None


def drop_viewer(rec: rr.RecordingStream, wait_s: float = _VIEWER_CLOSE_S) -> None:
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
    stop_web = getattr(rec, _STOP_WEB, None)
    if stop_web is not None:
        stop_web()  # `serve`'s web viewer process (at most a few seconds, usually at once)


def viewer_failure(spec: ViewerSpec | None, exc: Exception, opening: bool) -> str:
    """What a recorder keeps as its `viewer_failed`: which viewer, and what went wrong."""
    what = spec.describe() if spec is not None else "viewer"
    when = "could not be started" if opening else "failed"
    return f"--viewer {what} {when}: {exc}"


def live_view_off(failure: str, recording: bool, goes_on: str) -> str:
    """The one warning a recorder gives when its viewer is dropped: the failure, whether a
    file is still written, and what else carries on (`goes_on`)."""
    where = "the recording goes on" if recording else "nothing is recorded"
    return f"{failure}; live view off, {where}, {goes_on}"


class ViewerTee:
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
        drop_viewer(viewer, wait_s=0.1)

    def watch(self, period_s: float = _VIEWER_WATCH_S) -> None:
        """Flush the viewer stream every `period_s` on a thread of its own: a viewer that went
        away (rerun reports it only on a flush) is noticed, named and dropped without the
        logging thread ever waiting for it. A flush that merely times out (a slow viewer) is
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

    def close_viewer(self) -> None:
        """Stop watching and drop the viewer stream (the file is the caller's to close)."""
        self.unwatch()
        viewer, self.viewer = self.viewer, None
        if viewer is not None:
            drop_viewer(viewer)

    def log(self, path: str, entity: Any, static: bool = False) -> None:
        if self.file is not None:
            self.file.log(path, entity, static=static)
        self._to_viewer(lambda v: v.log(path, entity, static=static))

    def set_time(self, timeline: str, **kw: Any) -> None:
        if self.file is not None:
            self.file.set_time(timeline, **kw)
        self._to_viewer(lambda v: v.set_time(timeline, **kw))
