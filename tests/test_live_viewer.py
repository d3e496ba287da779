"""`--viewer spawn | connect | serve`: a run streamed live to Rerun beside its file.

No display here, so the viewer is played by rerun's own CLI in headless mode: `rerun --bind
127.0.0.1 --port P --save FILE` hosts the gRPC endpoint a viewer would and writes what it
receives to FILE (rerun 0.41 has no in-process receiver in its Python API), and
`rerun URL --save FILE` is a client pulling from a server a run hosts (`serve`). Everything is
on loopback, on ports picked free, and bounded in time.
"""

from __future__ import annotations

import ipaddress
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun_cli
from conftest import WATCHDOG_S, recorded_steps, wait_until

from protocol import Mode
from protocol.viewer import ViewerSpec, parse_viewer
from reach_driver.cli import Exit, main
from reach_driver.recording import RunRecorder, StepSample
from reach_driver.rrd_summary import read_recording
from reach_sim_bridge.emulator.server import SimConfig, SimServer

RERUN = os.path.join(os.path.dirname(rerun_cli.__file__), "rerun")  # the binary, not a wrapper
DT = 0.05


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


def _settle(path: Path, quiet_s: float = 0.5, timeout: float = 5.0) -> None:
    """Give the receiver time to write what reached it: until its file stops growing (a
    loaded host delivers the last messages late), at most `timeout` seconds."""
    end, last, since = time.monotonic() + timeout, -1, time.monotonic()
    while time.monotonic() < end:
        size = path.stat().st_size if path.exists() else -1
        if size != last:
            last, since = size, time.monotonic()
        elif size >= 0 and time.monotonic() - since >= quiet_s:
            return
        time.sleep(0.05)


def _holds_steps(path: Path, steps: list[int]) -> bool:
    """Whether the receiver's file already holds exactly these steps."""
    return recorded_steps(path) == steps


def _stop(
    proc: subprocess.Popen[bytes], received: Path | None = None, steps: list[int] | None = None
) -> None:
    """Stop the receiver once it has written what reached it: the `steps` sent, when known
    (up to 30 s: a loaded host delivers late, never not at all), else until its file stops
    growing."""
    if received is not None and steps is not None:
        wait_until(lambda: _holds_steps(received, steps), timeout=30.0, poll_s=0.1)
    elif received is not None:
        _settle(received)
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)


@pytest.fixture
def receiver(tmp_path: Path) -> Iterator[tuple[int, Path, subprocess.Popen[bytes]]]:
    """A headless stand-in for a viewer on a free loopback port, saving what reaches it."""
    port, out = _free_port(), tmp_path / "received.rrd"
    proc = subprocess.Popen(
        [RERUN, "--bind", "127.0.0.1", "--port", str(port), "--save", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        assert wait_until(lambda: _listening(port), timeout=20), "rerun --save did not listen"
        yield port, out, proc
    finally:
        _stop(proc)


def _log_run(rec: RunRecorder, n: int) -> np.ndarray:
    target = np.array([2.0, 1.6, 1.0, 0.9])
    rec.log_event("start")
    for k in range(n):
        q = target - 0.5 * np.exp(-k * DT)
        rec.log_step(
            StepSample(
                t=k * DT,
                step=k,
                q=q,
                qdot=np.zeros(4),
                target=target,
                current_cmd_mA=np.full(4, 10.0 + k),
                current_meas_mA=np.full(4, 9.0),
                torque_Nm=np.full(4, 0.1),
            )
        )
        rec.log_link(k * DT, k, good=k, bad=0, state_age_s=0.004, latency_s=0.001)
    rec.log_summary({"reached": True})
    return target


# -- the words of --viewer -------------------------------------------------------------------


def test_viewer_words_parse_with_their_defaults() -> None:
    assert parse_viewer(["connect"]) == ViewerSpec("connect")
    assert parse_viewer(["connect"]).url == "rerun+http://127.0.0.1:9876/proxy"
    assert parse_viewer(["connect", "9000"]).url == "rerun+http://127.0.0.1:9000/proxy"
    far = parse_viewer(["connect", "rerun+http://10.0.0.5:9877/proxy"])
    assert (far.url, far.port) == ("rerun+http://10.0.0.5:9877/proxy", 9877)
    assert parse_viewer(["spawn"]).port == 9876
    serve = parse_viewer(["serve", "9100", "9101"])
    assert (serve.port, serve.web_port, serve.bind) == (9100, 9101, "127.0.0.1")
    assert serve.web_url == "http://127.0.0.1:9101/?url=rerun%2Bhttp://127.0.0.1:9100/proxy"
    for bad in (["watch"], ["connect", "http://x"], ["serve", "1", "2", "3"], ["serve", "0"]):
        with pytest.raises(ValueError):
            parse_viewer(bad)
    with pytest.raises(ValueError, match="after positional"):
        parse_viewer(["spawn", "3", "1"])


def test_bad_viewer_words_are_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(
            ["--port", "loop://", "run", "--controller", "pid", "--target", "1", "1", "1", "1"]
            + ["--seconds", "1", "--viewer", "watch"]
        )
    assert exc.value.code == 2
    assert "--viewer" in capsys.readouterr().err


# -- connect -------------------------------------------------------------------------------------


def test_connect_streams_the_run_and_the_file_is_still_complete(tmp_path, receiver) -> None:
    port, received, proc = receiver
    path = tmp_path / "run.rrd"
    warnings: list[str] = []
    with RunRecorder(
        path, viewer=parse_viewer(["connect", str(port)]), warn=warnings.append
    ) as rec:
        assert rec.viewing
        target = _log_run(rec, 60)
    assert warnings == []
    _stop(proc, received, list(range(60)))  # the receiver closes its file
    local, live = read_recording(path), read_recording(received)
    assert local.step.tolist() == list(range(60)) and local.closed_cleanly
    assert live.step.tolist() == local.step.tolist()  # every step reached the viewer
    np.testing.assert_allclose(live.q, local.q)
    np.testing.assert_allclose(live.target, np.tile(target, (60, 1)))
    assert live.summary == {"reached": True} and [e[2] for e in live.events] == ["start"]


def test_streaming_only_writes_no_file(tmp_path, receiver) -> None:
    port, received, proc = receiver
    with RunRecorder(None, viewer=parse_viewer(["connect", str(port)])) as rec:
        _log_run(rec, 10)
    _stop(proc, received, list(range(10)))
    assert read_recording(received).step.tolist() == list(range(10))
    assert list(tmp_path.glob("*.rrd")) == [received]


def test_no_viewer_at_the_address_warns_once_and_the_file_is_complete(tmp_path) -> None:
    path = tmp_path / "run.rrd"
    warnings: list[str] = []
    t0 = time.monotonic()
    with RunRecorder(
        path, viewer=parse_viewer(["connect", str(_free_port())]), warn=warnings.append
    ) as rec:
        assert not rec.viewing
        _log_run(rec, 40)
    assert time.monotonic() - t0 < 5.0  # nothing waited for the missing viewer
    assert len(warnings) == 1 and "no Rerun viewer answers" in warnings[0], warnings
    assert "control is unaffected" in warnings[0]
    run = read_recording(path)
    assert run.step.tolist() == list(range(40)) and run.closed_cleanly


def test_a_viewer_that_goes_away_mid_run_never_stops_the_file_or_blocks(tmp_path, receiver) -> None:
    port, _received, proc = receiver
    path = tmp_path / "run.rrd"
    warnings: list[str] = []
    rec = RunRecorder(path, viewer=parse_viewer(["connect", str(port)]), warn=warnings.append)
    _log_run(rec, 20)
    proc.kill()  # the viewer window closed
    proc.wait(timeout=5)
    t0 = time.monotonic()
    for k in range(20, 200):
        rec.log_step(StepSample(k * DT, k, np.ones(4), np.zeros(4), np.full(4, 2.0), np.zeros(4)))
        rec.flush()  # the control loop's flushes: the file only
    assert time.monotonic() - t0 < 5.0
    # rerun reports the lost viewer on a flush: the watcher's, off the control thread
    assert wait_until(lambda: warnings and not rec.viewing, timeout=20), "the lost viewer"
    assert len(warnings) == 1 and "failed" in warnings[0] and "recording goes on" in warnings[0]
    for k in range(200, 220):
        rec.log_step(StepSample(k * DT, k, np.ones(4), np.zeros(4), np.full(4, 2.0), np.zeros(4)))
    t0 = time.monotonic()
    rec.close()
    assert time.monotonic() - t0 < 3.0
    run = read_recording(path)
    assert run.step.tolist() == list(range(220)) and run.closed_cleanly


# -- spawn ---------------------------------------------------------------------------------------


def test_spawn_without_a_display_warns_at_once_and_records(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    warnings: list[str] = []
    path = tmp_path / "run.rrd"
    with RunRecorder(path, viewer=parse_viewer(["spawn"]), warn=warnings.append) as rec:
        _log_run(rec, 5)
    assert len(warnings) == 1 and "needs a display" in warnings[0] and "serve" in warnings[0]
    assert read_recording(path).step.tolist() == list(range(5))


# -- serve ---------------------------------------------------------------------------------------


def test_serve_hosts_grpc_and_the_web_viewer_and_prints_the_address(tmp_path) -> None:
    grpc, web = _free_port(), _free_port()
    said: list[str] = []
    warnings: list[str] = []
    spec = parse_viewer(["serve", str(grpc), str(web)])
    path = tmp_path / "run.rrd"
    pulled = tmp_path / "pulled.rrd"
    rec = RunRecorder(path, viewer=spec, warn=warnings.append, announce=said.append)
    client: subprocess.Popen[bytes] | None = None
    try:
        assert warnings == [] and rec.viewing
        assert len(said) == 1 and spec.web_url in said[0] and f"ssh -L {web}:" in said[0]
        assert wait_until(lambda: _listening(grpc), timeout=10)
        assert not _listening_beyond_loopback(grpc)
        # Both servers on loopback only: a robot's telemetry is not served to the network.
        assert _listen_addresses(grpc) == {"127.0.0.1"}
        assert _listen_addresses(web) == {"127.0.0.1"}
        page = urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10).read()
        assert b"<html" in page.lower()
        _log_run(rec, 30)
        # a viewer connecting late gets the run from the start (the server buffers it)
        client = subprocess.Popen(
            [RERUN, spec.url, "--save", str(pulled)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        assert wait_until(lambda: _holds_steps(pulled, list(range(30))), 30, poll_s=0.1)
    finally:
        if client is not None:
            _stop(client)
        rec.close()
    assert read_recording(pulled).step.tolist() == list(range(30))
    assert read_recording(path).step.tolist() == list(range(30))
    assert _listen_addresses(web) == set()  # the web viewer went with the recorder


def _listen_addresses(port: int) -> set[str]:
    """The local addresses TCP sockets listen on at `port`, from /proc/net/tcp{,6}."""
    found: set[str] = set()
    for table, width in (("/proc/net/tcp", 8), ("/proc/net/tcp6", 32)):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            hexaddr, hexport = local.split(":")
            if state != "0A" or int(hexport, 16) != port:  # 0A: LISTEN
                continue
            raw = bytes.fromhex(hexaddr)
            # /proc prints each 32-bit word of the address in host (little-endian) order
            words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
            found.add(
                str(ipaddress.ip_address(words))
                if width == 8
                else str(ipaddress.IPv6Address(words))
            )
    return found


def test_viewer_bind_listens_where_asked_and_only_with_serve() -> None:
    from reach_driver.cli.parser import build_parser as driver_parser
    from reach_sim_bridge.cli import build_parser as sim_parser

    spec = (
        driver_parser()
        .parse_args(
            [
                "run",
                "--controller",
                "pid",
                "--target",
                "1",
                "1",
                "1",
                "1",
                "--seconds",
                "1",
                "--viewer",
                "serve",
                "9100",
                "9101",
                "--viewer-bind",
                "0.0.0.0",
            ]
        )
        .viewer
    )
    assert (spec.bind, spec.host, spec.port, spec.web_port) == ("0.0.0.0", "127.0.0.1", 9100, 9101)
    assert (
        sim_parser().parse_args(["--viewer-bind", "::1", "--viewer", "serve"]).viewer.bind == "::1"
    )
    for bad in (
        ["--viewer", "connect", "--viewer-bind", "0.0.0.0"],
        ["--viewer", "serve", "--viewer-bind", "localhost:9"],
    ):
        with pytest.raises(SystemExit):
            sim_parser().parse_args(bad)


def test_viewer_bind_without_serve_is_a_usage_error(capsys) -> None:
    from reach_sim_bridge.cli import main as sim_main

    with pytest.raises(SystemExit) as exc:
        sim_main(["--no-pty", "--viewer-bind", "0.0.0.0"])
    assert exc.value.code == 2 and "--viewer serve" in capsys.readouterr().err


def _listening_beyond_loopback(port: int) -> bool:
    """True if the port answers on this machine's other addresses (it should not)."""
    try:
        host = socket.gethostbyname(socket.gethostname())
    except OSError:
        return False
    if host.startswith("127."):
        return False
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def test_serve_on_a_port_in_use_warns_and_records(tmp_path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        warnings: list[str] = []
        path = tmp_path / "run.rrd"
        with RunRecorder(
            path, viewer=parse_viewer(["serve", str(port), str(_free_port())]), warn=warnings.append
        ) as rec:
            _log_run(rec, 5)
    assert len(warnings) == 1 and f"port {port}" in warnings[0] and "in use" in warnings[0]
    assert read_recording(path).step.tolist() == list(range(5))


# -- the CLI -------------------------------------------------------------------------------------


def test_run_with_viewer_and_record_writes_both(sim, tmp_path, receiver, capsys) -> None:
    port, received, proc = receiver
    record = tmp_path / "run.rrd"
    target = sim.snapshot().q + np.array([0.2, -0.1, 0.1, 0.2])
    argv = ["--port", str(sim.link), "-q", "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "pid", "--target"]
    argv += [*map(str, target), "--seconds", "1.5", "--record", str(record)]
    argv += ["--viewer", "connect", f"rerun+http://127.0.0.1:{port}/proxy"]
    assert main(argv) == Exit.OK
    assert "warning" not in capsys.readouterr().err
    local = read_recording(record)
    _stop(proc, received, local.step.tolist())
    live = read_recording(received)
    # every step the loop took (and the state that ended it), each of the 30 ticks stepped on
    # or counted as skipped by a loop a loaded host ran late
    steps = int(local.summary["steps"])  # type: ignore[call-overload]
    skipped = int(local.summary["skipped_states"])  # type: ignore[call-overload]
    assert len(local.step) == steps + 1 and steps + skipped >= 30
    assert live.step.tolist() == local.step.tolist() and live.summary == local.summary


def test_run_with_an_absent_viewer_warns_and_exits_ok(sim, tmp_path, capsys) -> None:
    target = sim.snapshot().q + np.array([0.1, 0.0, 0.0, 0.0])
    argv = ["--port", str(sim.link), "-q", "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "pid", "--target"]
    argv += [*map(str, target), "--seconds", "0.5", "--viewer", "connect", str(_free_port())]
    assert main(argv) == Exit.OK
    err = capsys.readouterr().err
    assert err.count("no Rerun viewer answers") == 1, err


def test_monitor_streams_the_arm_to_a_viewer(sim, tmp_path, receiver, capsys) -> None:
    port, received, proc = receiver
    record = tmp_path / "monitor.rrd"
    argv = ["--port", str(sim.link), "-q", "monitor", "--seconds", "1", "--record", str(record)]
    assert main([*argv, "--viewer", "connect", str(port)]) == 0
    assert "warning" not in capsys.readouterr().err
    local = read_recording(record)
    _stop(proc, received, local.step.tolist())
    live = read_recording(received)
    # the whole second watched (up to the state it ended on), and all of it reached the viewer
    assert len(local.step) >= 2 and local.t[-1] >= 1.0
    assert live.step.tolist() == local.step.tolist()
    assert np.all(np.isfinite(live.q)) and np.all(np.isnan(live.target))


def test_monitor_seconds_count_from_when_it_watches(sim, tmp_path, monkeypatch) -> None:
    """Opening the recording and viewer (loading rerun) took seconds on a loaded host, all of
    `--seconds 1`: the monitor recorded nothing. Its seconds start once it is watching."""
    from reach_driver.cli import monitor

    opened = monitor.CliRecorder

    def slow_open(*args: Any, **kwargs: Any) -> Any:
        time.sleep(1.5)  # a host too busy to load rerun within the monitor's second
        return opened(*args, **kwargs)

    monkeypatch.setattr(monitor, "CliRecorder", slow_open)
    record = tmp_path / "monitor.rrd"
    argv = ["--port", str(sim.link), "-q", "monitor", "--seconds", "1", "--record", str(record)]
    assert main(argv) == 0
    local = read_recording(record)
    assert len(local.step) >= 2 and local.t[-1] >= 1.0, local.t


def test_move_streams_the_arm_and_its_target_to_a_viewer(sim, receiver, capsys) -> None:
    port, received, proc = receiver
    q = sim.snapshot().q + np.array([0.1, 0.0, 0.0, 0.0])
    tolerance = 0.02
    argv = ["--port", str(sim.link), "-q", "move", *map(str, q), "--tolerance", str(tolerance)]
    assert main([*argv, "--viewer", "connect", str(port)]) == 0
    assert "warning" not in capsys.readouterr().err
    _stop(proc, received)
    live = read_recording(received)
    assert len(live.step) >= 3 and np.all(np.isfinite(live.q))
    np.testing.assert_allclose(live.target[-1], q)
    assert np.max(np.abs(live.q[-1] - q)) <= tolerance  # the state the move ended on


def test_move_streams_the_state_it_ended_on_whenever_the_last_tick_was(
    sim, tmp_path, receiver, monkeypatch
) -> None:
    """The viewer's last frame of a move is the state that was judged reached, not the 20 Hz
    tick before it (a loaded host's last tick came early and showed the arm short of its
    tolerance). Here the stream ticks once only: the start, then the end."""
    from reach_driver.cli import monitor

    monkeypatch.setattr(monitor.StateStream, "PERIOD_S", 1e9)
    port, received, proc = receiver
    q = sim.snapshot().q + np.array([0.1, 0.0, 0.0, 0.0])
    tolerance = 0.02
    argv = ["--port", str(sim.link), "-q", "move", *map(str, q), "--tolerance", str(tolerance)]
    assert main([*argv, "--viewer", "connect", str(port)]) == 0
    _stop(proc, received, [0, 1])
    live = read_recording(received)
    assert live.step.tolist() == [0, 1]
    assert np.max(np.abs(live.q[-1] - q)) <= tolerance


# -- reach-sim --viewer --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "words", [["spawn"], ["connect"], ["connect", "9000"], ["serve", "9100", "9101"]]
)
def test_both_command_lines_read_viewer_words_into_the_same_spec(words: list[str]) -> None:
    from reach_driver.cli.parser import build_parser as driver_parser
    from reach_sim_bridge.cli import build_parser as sim_parser

    driver_argv = ["--port", "loop://", "run", "--controller", "pid", "--target", "1", "1"]
    driver_argv += ["1", "1", "--seconds", "1", "--viewer", *words]
    expected = parse_viewer(words)
    assert driver_parser().parse_args(driver_argv).viewer == expected
    assert sim_parser().parse_args(["--viewer", *words]).viewer == expected


def test_reach_sim_rejects_bad_viewer_words_as_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from reach_sim_bridge.cli import build_parser as sim_parser

    with pytest.raises(SystemExit) as exc:
        sim_parser().parse_args(["--viewer", "serve", "9100", "9100"])
    assert exc.value.code == 2
    assert "must differ" in capsys.readouterr().err


def test_sim_recorder_streams_its_samples_and_still_writes_the_file(tmp_path, receiver) -> None:
    from reach_sim_bridge.emulator.recording import SimRecorder

    port, received, proc = receiver
    path = tmp_path / "sim.rrd"
    warnings: list[str] = []
    with SimServer(SimConfig(speed=5.0, pty=False, udp=("127.0.0.1", 0))) as srv:
        recorder = SimRecorder(
            srv, path, viewer=parse_viewer(["connect", str(port)]), warn=warnings.append
        )
        assert recorder.viewing
        recorder.start()
        assert srv.wait_sim_time(srv.sim_time + 1.0, timeout=30)
        recorder.stop()
    assert warnings == []
    local = read_recording(path)
    _stop(proc, received, local.step.tolist())
    live = read_recording(received)
    assert len(local.step) >= 2 and local.metadata["source"] == "reach-sim"
    assert live.step.tolist() == local.step.tolist()
    np.testing.assert_allclose(live.q, local.q)


def test_sim_recorder_without_a_viewer_warns_once_and_the_simulator_runs_on(tmp_path) -> None:
    from reach_sim_bridge.emulator.recording import SimRecorder

    path = tmp_path / "sim.rrd"
    warnings: list[str] = []
    with SimServer(SimConfig(speed=5.0, pty=False, udp=("127.0.0.1", 0))) as srv:
        recorder = SimRecorder(
            srv, path, viewer=parse_viewer(["connect", str(_free_port())]), warn=warnings.append
        )
        assert not recorder.viewing
        recorder.start()
        assert srv.wait_sim_time(srv.sim_time + 0.5, timeout=30)
        recorder.stop()
    assert len(warnings) == 1 and "no Rerun viewer answers" in warnings[0], warnings
    assert "the recording goes on" in warnings[0] and "the simulator runs on" in warnings[0]
    assert recorder.viewer_failed is not None and recorder.viewer_failed in warnings[0]
    assert len(read_recording(path).step) >= 2


def test_reading_viewer_words_does_not_load_rerun() -> None:
    """`import protocol` and both command lines' parsers stay light: rerun loads only when a
    viewer is opened (or a recorder is made)."""
    code = (
        "import sys, protocol, protocol.viewer, reach_driver.cli, reach_sim_bridge.cli\n"
        "protocol.viewer.parse_viewer(['serve'])\n"
        "print('rerun' in sys.modules)"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_reach_sim_viewer_serve_prints_the_address_and_streams_only(tmp_path) -> None:
    grpc, web = _free_port(), _free_port()
    cli = [sys.executable, "-m", "reach_sim_bridge.cli", "--no-pty", "--udp", "127.0.0.1:0"]
    cli += ["--viewer", "serve", str(grpc), str(web)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen(
        cli, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=env
    )
    try:
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline().startswith("udp ")
        line = proc.stderr.readline()
        assert f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy" in line, line
        assert wait_until(lambda: _listening(grpc), timeout=10)
        page = urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10).read()
        assert b"<html" in page.lower()
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "recording" not in out and list(tmp_path.glob("*.rrd")) == []


def test_a_viewer_joining_late_is_sent_the_present_first(tmp_path) -> None:
    """--viewer serve replays what a late viewer missed newest first (after the static scene
    and the blueprint): it shows the arm as it is now at once, and the run's start after."""
    import rerun as rr

    from protocol.viewer import open_viewer
    from reach_driver.recording import default_blueprint

    grpc, web = _free_port(), _free_port()
    spec = parse_viewer(["serve", str(grpc), str(web)])
    rec = open_viewer(spec, "reach-stack", "late-joiner", default_blueprint(live=True))
    pulled = tmp_path / "pulled.rrd"
    client: subprocess.Popen[bytes] | None = None
    try:
        rec.log("run/metadata", rr.TextDocument("{}"), static=True)
        for batch in range(4):  # four sends, as four half seconds of a run
            for k in range(batch * 10, batch * 10 + 10):
                rec.set_time("step", sequence=k)
                rec.log("joints/E/position", rr.Scalars([float(k), 0.0]))
            rec.flush(timeout_sec=10.0)
        client = subprocess.Popen(
            [RERUN, spec.url, "--save", str(pulled)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        assert wait_until(
            lambda: (
                _steps_in_order(pulled, "/joints/E/position")
                and sorted(_steps_in_order(pulled, "/joints/E/position")) == list(range(40))
            ),
            30,
            poll_s=0.1,
        )
    finally:
        if client is not None:
            _stop(client)
        from protocol.viewer import drop_viewer

        drop_viewer(rec)
    order = _steps_in_order(pulled, "/joints/E/position")
    assert order[:10] == list(range(30, 40)), order  # the newest send first
    assert sorted(order) == list(range(40))  # and all of it


def _steps_in_order(path: Path, entity: str) -> list[int]:
    """The steps of `entity`'s rows in the order they reached the file."""
    import warnings

    from rerun.chunk import RrdReader

    if not path.exists():
        return []
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            chunks = RrdReader(path).stream().to_chunks()
    except Exception:  # still being written
        return []
    steps: list[int] = []
    for c in chunks:
        if str(c.entity_path) == entity and not c.is_static:
            steps.extend(int(s) for s in c.to_record_batch().column("step").to_pylist())
    return steps


def _lingering(port: int) -> bool:
    """Whether a TCP connection on local `port` is in TIME_WAIT (/proc/net/tcp state 06)."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            if state == "06" and int(local.split(":")[1], 16) == port:
                return True
    return False


def test_serve_on_ports_a_finished_viewer_lingers_on_starts(tmp_path) -> None:
    """A browser that watched the last run leaves its closed connection in TIME_WAIT on the
    web viewer's port for a minute: that port is free to serve again (it was called 'in
    use', and the next run watched nothing)."""
    web = _free_port()
    with socket.socket() as server:
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", web))
        server.listen()
        client = socket.create_connection(("127.0.0.1", web))
        conn, _ = server.accept()
        conn.close()  # the server closes first, as a web server does: its end lingers
        client.close()
    assert wait_until(lambda: _lingering(web), timeout=10), "no TIME_WAIT to test against"
    warnings: list[str] = []
    spec = parse_viewer(["serve", str(_free_port()), str(web)])
    with RunRecorder(tmp_path / "run.rrd", viewer=spec, warn=warnings.append) as rec:
        assert warnings == [] and rec.viewing
        _log_run(rec, 3)
    assert read_recording(tmp_path / "run.rrd").step.tolist() == [0, 1, 2]


# -- --viewer-keep -------------------------------------------------------------------------------


def test_viewer_keep_serves_the_finished_run_until_ctrl_c(sim, tmp_path) -> None:
    """With --viewer-keep the run ends as ever (arm safe, summary out, the file closed, the
    port released), then its viewer goes on serving the whole run until Ctrl-C; the exit
    status is the run's own."""
    from policy.campaigns.attacks import driver_process

    grpc, web = _free_port(), _free_port()
    record, pulled = tmp_path / "run.rrd", tmp_path / "pulled.rrd"
    target = sim.snapshot().q + np.array([0.1, 0.0, 0.0, 0.0])
    proc = driver_process(
        *["--port", str(sim.link), "-q", "--watchdog", str(WATCHDOG_S), "run"],
        *["--controller", "pid", "--target", *map(str, target), "--seconds", "1"],
        *["--record", str(record), "--viewer", "serve", str(grpc), str(web), "--viewer-keep"],
    )
    client: subprocess.Popen[bytes] | None = None
    try:
        assert proc.stderr is not None and proc.stdout is not None
        said = [proc.stderr.readline() for _ in range(2)]  # the address, then the keeping
        assert spec_line(said[0], grpc, web) and "still serving" in said[1], said
        assert f"http://127.0.0.1:{web}/" in said[1] and "Ctrl-C" in said[1]
        assert proc.poll() is None  # waiting
        assert all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in (5, 4, 3, 2))
        run = read_recording(record)  # closed, as any run's
        assert run.closed_cleanly and run.summary["steps"]
        assert _listening(grpc) and _listening(web)
        client = subprocess.Popen(
            [RERUN, f"rerun+http://127.0.0.1:{grpc}/proxy", "--save", str(pulled)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        steps = run.step.tolist()
        assert wait_until(lambda: _holds_steps(pulled, steps), 30, poll_s=0.1), "not all served"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if client is not None:
            _stop(client)
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == Exit.OK, err  # not 130: Ctrl-C ended the serving, not the run
    assert "arm left in zero_velocity" in out and "interrupted" not in err
    assert _listen_addresses(grpc) == set() and _listen_addresses(web) == set()


def spec_line(line: str, grpc: int, web: int) -> bool:
    return f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy" in line


@pytest.mark.parametrize("words", [[], ["--viewer", "connect", "9000"]])
def test_viewer_keep_without_serve_is_a_usage_error(words: list[str], capsys) -> None:
    argv = ["--port", "loop://", "run", "--controller", "pid", "--target", "1", "1", "1", "1"]
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--seconds", "1", *words, "--viewer-keep"])
    assert exc.value.code == 2 and "--viewer-keep is for --viewer serve" in capsys.readouterr().err
