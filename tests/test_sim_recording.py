"""`reach-sim --record`: the true state of the virtual arm, readable as a run recording."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import serial

from protocol import DeviceID, commands
from reach_driver.rrd_summary import read_recording
from reach_sim_bridge.recording import SimRecorder
from reach_sim_bridge.server import SimConfig, SimServer

SPEED = 5.0


def test_recorder_follows_a_position_move(tmp_path: Path) -> None:
    path = tmp_path / "sim.rrd"
    start = (3.0, 1.5, 1.5, 1.5)
    with SimServer(SimConfig(speed=SPEED, start=start)) as srv:
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
        time.sleep(1.5)
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "recording" in out
    run = read_recording(path)
    assert len(run.step) >= 10
    assert run.closed_cleanly
