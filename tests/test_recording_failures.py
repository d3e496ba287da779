"""A recording that fails (disk full) or is cut short (killed, truncated) never costs the run,
and what was written before is still read back."""

from __future__ import annotations

import errno
import re
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from reach_driver import recording
from reach_driver.cli import Exit, main
from reach_sim_bridge.server import SimConfig, SimServer

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def sim(tmp_path):
    server = SimServer(SimConfig(speed=4.0, link=str(tmp_path / "arm"), udp=("127.0.0.1", 0)))
    server.start()
    yield server
    server.stop()
    assert server.error is None


def _run_argv(sim: SimServer, record: Path, seconds: float = 2.0) -> list[str]:
    host, port = sim.udp_address
    target = sim.snapshot().q + np.array([0.3, -0.2, 0.2, 0.3])
    argv = ["--port", f"udp://{host}:{port}", "run", "--controller", "pid", "--target"]
    return [*argv, *map(str, target), "--seconds", str(seconds), "--record", str(record)]


class _DiskFullAfter(recording.RunRecorder):
    """A recorder whose sink fails (ENOSPC) from the 10th step on, every time."""

    steps = 0

    def log_step(self, s: recording.StepSample) -> None:
        type(self).steps += 1
        if type(self).steps > 10:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path))
        super().log_step(s)


# -- 2: a recording failure never stops control --------------------------------------------


def test_a_recording_that_fails_mid_run_does_not_stop_control(
    sim, tmp_path, monkeypatch, capsys
) -> None:
    monkeypatch.setattr(recording, "RunRecorder", _DiskFullAfter)
    record = tmp_path / "run.rrd"
    code = main(_run_argv(sim, record))
    out, err = capsys.readouterr()
    assert code == Exit.RECORDING_INCOMPLETE, out + err
    # The run went on to its end (2 s at 20 Hz) and printed its summary.
    steps = int(re.search(r"run:\s+(\d+)\s+steps", out).group(1))  # type: ignore[union-attr]
    assert steps >= 30
    assert "metrics" in out and "arm left in zero_velocity" in out
    assert "stopped by time" in out or "stopped by end" in out or "stopped by" in out
    # One warning, naming the file and the error; the end of the run says it again.
    assert err.count("recording failed") == 1, err
    assert str(record) in err and "No space left on device" in err
    assert "recording incomplete" in out
    assert "Traceback" not in out + err


@pytest.mark.slow
def test_a_full_disk_mid_run_is_survived(sim, tmp_path) -> None:
    """The real thing: the file may not grow past 160 kB (RLIMIT_FSIZE), so rerun's file sink
    fails mid-run as it does on a full disk."""
    record = tmp_path / "run.rrd"

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (160_000, resource.RLIM_INFINITY))

    cmd = [sys.executable, "-m", "reach_driver.cli", *_run_argv(sim, record, seconds=6.0)]
    proc = subprocess.run(
        cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, preexec_fn=limit
    )
    out, err = proc.stdout, proc.stderr
    assert proc.returncode == Exit.RECORDING_INCOMPLETE, out + err
    assert "Traceback" not in out + err
    steps = int(re.search(r"run:\s+(\d+)\s+steps", out).group(1))  # type: ignore[union-attr]
    assert steps >= 100  # 6 s at 20 Hz, less states a busy host skipped
    assert "metrics" in out and "arm left in zero_velocity" in out
    assert "recording failed" in err and str(record) in err
