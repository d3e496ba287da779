"""A recording that fails (disk full) or is cut short (killed, truncated) never costs the run,
and what was written before is still read back."""

from __future__ import annotations

import errno
import json
import re
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import LOOPBACK, WATCHDOG_S, udp_url

from reach_driver import recording
from reach_driver.cli import Exit, main
from reach_driver.rrd_summary import read_recording
from reach_sim_bridge.emulator.server import SimServer

ROOT = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.sim(speed=4.0, udp=LOOPBACK)


def _run_argv(sim: SimServer, record: Path, seconds: float = 2.0) -> list[str]:
    target = sim.snapshot().q + np.array([0.3, -0.2, 0.2, 0.3])
    # These tests are about the recording, not the watchdog.
    argv = ["--port", udp_url(sim), "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    argv.append("--target")
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
    """The real thing: the file may not grow past 260 kB (RLIMIT_FSIZE), so rerun's file sink
    fails mid-run as it does on a full disk (a recording opens at about 200 kB: its blueprint
    and the arm's scene; a run adds about 170 kB a second)."""
    record = tmp_path / "run.rrd"

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (260_000, resource.RLIM_INFINITY))

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


# -- 3: truncated and early-killed recordings read back ------------------------------------


def _recorded(path: Path, n: int = 200) -> np.ndarray:
    """n steps written by the project's RunRecorder as a run writes them: flushed every 10
    steps (a 20 Hz loop and the 0.5 s flush period); their q."""
    q = np.linspace([1.0, 1.0, 1.5, 0.5], [2.0, 1.6, 1.0, 0.9], n)
    with recording.RunRecorder(path, metadata={"controller": "synthetic"}) as rec:
        rec.log_event("start")
        for k in range(n):
            sample = recording.StepSample(
                t=k * 0.05,
                step=k,
                q=q[k],
                qdot=np.zeros(4),
                target=q[-1],
                current_cmd_mA=np.full(4, 100.0),
                current_meas_mA=np.full(4, 90.0),
                torque_Nm=np.full(4, 0.5),
            )
            rec.log_step(sample)
            rec.log_link(k * 0.05, k, good=k, bad=0, state_age_s=0.004)
            if k % 10 == 9:
                rec.flush()
        rec.log_summary({"reached": True})
    return q


@pytest.mark.parametrize("fraction", [0.999, 0.9, 0.5, 0.3])
def test_a_truncated_recording_reads_up_to_its_last_complete_message(
    tmp_path, fraction, capsys
) -> None:
    full = tmp_path / "run.rrd"
    q = _recorded(full)
    data = full.read_bytes()
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(data[: int(len(data) * fraction)])  # disk full, or killed mid-message
    run = read_recording(cut)
    n = len(run.step)
    assert n >= 10 and run.step.tolist() == list(range(n))  # the steps before the cut
    np.testing.assert_allclose(run.q, q[:n])
    assert run.truncated and not run.closed_cleanly
    if fraction > 0.99:
        assert n == 200  # only the footer was cut
    assert main(["inspect", str(cut)]) == Exit.OK
    out = capsys.readouterr().out
    assert f"{n} steps" in out and "truncated" in out


def test_cutting_a_recording_later_never_reads_fewer_steps(tmp_path) -> None:
    full = tmp_path / "run.rrd"
    _recorded(full, 120)
    data = full.read_bytes()
    counts = []
    for fraction in (0.3, 0.45, 0.6, 0.75, 0.9):
        cut = tmp_path / f"cut{fraction}.rrd"
        cut.write_bytes(data[: int(len(data) * fraction)])
        counts.append(len(read_recording(cut).step))
    assert counts == sorted(counts) and counts[-1] > counts[0], counts


def test_a_run_killed_before_its_first_step_is_still_recognised(tmp_path, capsys) -> None:
    path = tmp_path / "run.rrd"
    rec = recording.RunRecorder(path, metadata={"controller": "pid", "seconds": 20})
    killed = tmp_path / "killed.rrd"
    killed.write_bytes(path.read_bytes())  # what a kill at 0.3 s leaves on disk
    rec.close()
    run = read_recording(killed)
    assert len(run.step) == 0
    assert run.metadata["controller"] == "pid"
    assert main(["inspect", str(killed)]) == Exit.OK
    out = capsys.readouterr().out
    assert "0 steps" in out and "not a run recorded" not in out
    assert "pid" in out
    assert main(["inspect", "--json", str(killed)]) == Exit.OK
    data = json.loads(capsys.readouterr().out)
    assert data["steps"] == 0 and data["metadata"]["controller"] == "pid"
