"""`reach-sim --record`: the true state of the virtual arm, readable as a run recording."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import serial
from conftest import recorded_steps, wait_until

from protocol import DeviceID, commands
from reach_driver.rrd_summary import read_recording
from reach_sim_bridge.emulator.recording import SimRecorder
from reach_sim_bridge.emulator.server import SimConfig, SimServer

SPEED = 5.0


def test_recorder_follows_a_position_move(tmp_path: Path, arm_pauses_with_host: None) -> None:
    path = tmp_path / "sim.rrd"
    start = (3.0, 1.5, 1.5, 1.5)
    # 2x: a sample every 10 ms of wall time (the recorder's thread, run late, misses some)
    with SimServer(SimConfig(speed=2.0, start=start)) as srv:
        recorder = SimRecorder(srv, path, rate_hz=50.0)
        recorder.start()
        assert srv.pty_path is not None
        with serial.Serial(srv.pty_path, 115200, timeout=0.05) as port:
            port.write(commands.position(DeviceID.D, 1.8).encode())
            assert srv.wait_sim_time(srv.sim_time + 1.5, timeout=30)
        truth = srv.snapshot()
        recorder.stop()
    run = read_recording(path)
    assert recorder.samples >= 40 and len(run.step) >= 40
    assert np.all(np.diff(run.t) > 0)
    # D moved towards its setpoint; the recorded setpoint is the commanded one.
    assert abs(run.q[0, 1] - 1.5) < 0.01
    assert abs(run.q[-1, 1] - truth.q[1]) < 0.05
    assert run.q[-1, 1] > 1.7
    assert abs(np.nanmax(run.target[:, 1]) - 1.8) < 1e-6
    assert any("D=position" in text for _, _, text in run.events)
    assert run.metadata["source"] == "reach-sim"


def test_cli_writes_a_recording_that_survives_sigint(tmp_path: Path) -> None:
    path = tmp_path / "cli.rrd"
    cli = [
        sys.executable,
        "-m",
        "reach_sim_bridge.cli",
        "--speed",
        "5",
        "--record",
        str(path),
        "--stats-interval",
        "0",
    ]
    proc = subprocess.Popen(cli, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("pty ")
        assert wait_until(lambda: len(recorded_steps(path)) >= 10, timeout=30.0, poll_s=0.1)
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "recording" in out
    run = read_recording(path)
    assert len(run.step) >= 10
    assert run.closed_cleanly


def _hold(port: serial.Serial, q: tuple[float, ...]) -> None:
    for dev, angle in zip((DeviceID.E, DeviceID.D, DeviceID.C, DeviceID.B), q, strict=True):
        port.write(commands.position(dev, angle).encode())


def test_an_idle_arm_is_recorded_at_the_idle_rate_and_a_move_at_full_rate(
    tmp_path: Path, arm_pauses_with_host: None
) -> None:
    path = tmp_path / "sim.rrd"
    start = (3.0, 1.5, 1.5, 1.5)
    # 2x, not 5x: the recorder's thread takes a sample every 10 ms of wall time, not every 4 ms
    # (a thread a loaded host runs late takes the next one and misses those between)
    with SimServer(SimConfig(speed=2.0, start=start)) as srv:
        recorder = SimRecorder(srv, path, rate_hz=50.0, idle_rate_hz=2.0, max_bytes=None)
        recorder.start()
        assert srv.pty_path is not None
        with serial.Serial(srv.pty_path, 115200, timeout=0.05) as port:
            _hold(port, start)
            assert srv.wait_sim_time(srv.sim_time + 8.0, timeout=60)  # settle, then idle
            t_move = srv.sim_time
            port.write(commands.position(DeviceID.D, 1.8).encode())
            assert srv.wait_sim_time(t_move + 2.0, timeout=30)
        recorder.stop()
    run = read_recording(path)
    assert recorder.looked > 3 * recorder.samples / 2  # most idle samples were left out
    idle = (run.t > 3.0) & (run.t < t_move - 0.1)
    idle_rate = idle.sum() / (t_move - 0.1 - 3.0)
    assert 1.0 <= idle_rate <= 3.5, idle_rate
    moving = (run.t > t_move + 0.1) & (run.t < t_move + 0.6)
    # 50 Hz while D moves (25 samples; the idle rate would give 1): the recorder's thread
    # samples sim time as it finds it, and a loaded host can make it miss a few
    assert moving.sum() >= 15
    # The quiet state just before the move is there, so the plot does not ramp over the gap.
    before = run.t[run.t < t_move + 0.05]
    after = run.t[run.t >= t_move + 0.05]
    assert after[0] - before[-1] <= 0.1
    assert run.q[-1, 1] > 1.7


def test_a_capped_recording_rotates_into_parts_that_each_read(tmp_path: Path) -> None:
    path = tmp_path / "sim.rrd"
    cap, parts = 1_500_000, 3
    with SimServer(SimConfig(speed=SPEED, start=(3.0, 1.5, 1.5, 1.5))) as srv:
        recorder = SimRecorder(srv, path, flush_period_s=0.2, max_bytes=cap, parts=parts)
        recorder.start()
        assert srv.pty_path is not None
        with serial.Serial(srv.pty_path, 115200, timeout=0.05) as port:
            k = 0
            while recorder.rotations < parts + 1 and srv.sim_time < 120.0:
                port.write(commands.position(DeviceID.D, 1.2 if k % 2 else 1.9).encode())
                assert srv.wait_sim_time(srv.sim_time + 1.0, timeout=30)
                k += 1
            # The newest part may have just been opened: let it take a few samples too (a
            # loaded host can leave the recorder's thread behind the arm).
            seen = recorder.samples
            assert wait_until(lambda: recorder.samples >= seen + 3, timeout=30)
        recorder.stop()
    assert recorder.rotations >= parts + 1
    files = [path.with_name(f"sim.{n}.rrd") for n in range(parts - 1, 0, -1)] + [path]
    assert all(f.exists() for f in files)
    assert not path.with_name(f"sim.{parts}.rrd").exists()  # the oldest was deleted
    total = sum(f.stat().st_size for f in files)
    assert total <= cap * 1.1, total  # the cap, give or take a flush
    runs = [read_recording(f) for f in files]  # oldest first
    numbers = [int(r.metadata["part"]) for r in runs]  # type: ignore[call-overload]
    assert numbers == sorted(numbers) and numbers[-1] == recorder.rotations
    first = [int(r.metadata["first_sample"]) for r in runs]  # type: ignore[call-overload]
    for older, newer, start, after in zip(runs, runs[1:], first, first[1:], strict=False):
        assert len(older.step) and older.t[-1] <= newer.t[0]
        # Nothing lost at a rotation: every sample logged before it is in the older part.
        # (Counted, not timed: how far apart in arm time two samples land depends on how
        # promptly the host schedules the recorder's thread beside an arm at 5x.)
        assert start + len(older.step) == after, (start, len(older.step), after)
    assert first[-1] + len(runs[-1].step) == recorder.samples
    # Every part states the modes it starts with.
    assert all(any(text.startswith("modes:") for _, _, text in r.events) for r in runs)


def test_inspect_summarises_a_simulator_recording_as_one(tmp_path: Path) -> None:
    from protocol import HardwareStatus
    from reach_driver.rrd_summary import summarize_recording

    path = tmp_path / "sim.rrd"
    with SimServer(SimConfig(speed=SPEED, start=(3.0, 1.5, 1.5, 1.5))) as srv:
        recorder = SimRecorder(srv, path)
        recorder.start()
        assert srv.pty_path is not None
        with serial.Serial(srv.pty_path, 115200, timeout=0.05) as port:
            port.write(commands.position(DeviceID.D, 1.8).encode())
            assert srv.wait_sim_time(srv.sim_time + 1.0, timeout=30)
            srv.inject_fault(DeviceID.C, HardwareStatus.OVER_TEMPERATURE)
            assert srv.wait_sim_time(srv.sim_time + 0.5, timeout=30)
        truth = srv.snapshot()
        recorder.stop()
    s = summarize_recording(path)
    assert s["kind"] == "simulator"
    assert "final_target" not in s and "final_error" not in s and "metrics" not in s
    final = s["final_position"]
    assert isinstance(final, list) and abs(final[1] - truth.q[1]) < 0.05
    setpoint = s["final_setpoint"]
    assert isinstance(setpoint, list) and abs(setpoint[1] - 1.8) < 1e-6
    modes = s["final_modes"]
    assert isinstance(modes, list) and modes[1] == "position"
    assert "C=OVER_TEMPERATURE" in str(s["final_faults"])
    assert any("OVER_TEMPERATURE" in line for line in s["faults"])  # type: ignore[attr-defined]
    assert s["part"] == 0 and float(s["duration_s"]) > 1.0  # type: ignore[arg-type]
