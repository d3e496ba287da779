"""Recordings written by RunRecorder read back intact, also after a crash."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import recorded_steps, wait_until

from reach_driver.metrics import Trace, compute_metrics
from reach_driver.recording import RunRecorder, StepSample
from reach_driver.rrd_summary import RecordingReadError, read_recording, summarize_recording

DT = 0.05


def _synthetic_run(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A first-order approach from start to target: q, qdot, target."""
    start, target = np.array([1.0, 1.0, 1.5, 0.5]), np.array([2.0, 1.6, 1.0, 0.9])
    t = np.arange(n)[:, None] * DT
    q = target + (start - target) * np.exp(-t / 0.8)
    qdot = -(start - target) / 0.8 * np.exp(-t / 0.8)
    return q, qdot, target


def _write(path: Path, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    q, qdot, target = _synthetic_run(n)
    with RunRecorder(path, metadata={"controller": "synthetic"}) as rec:
        rec.log_event("start")
        for k in range(n):
            rec.log_step(
                StepSample(
                    t=k * DT,
                    step=k,
                    q=q[k],
                    qdot=qdot[k],
                    target=target,
                    current_cmd_mA=np.full(4, 100.0 + k),
                    current_meas_mA=np.full(4, 90.0),
                    torque_Nm=np.full(4, 0.5),
                )
            )
            rec.log_link(k * DT, k, good=k, bad=0, state_age_s=0.004)
        rec.log_summary({"reached": True})
    return q, qdot, target


def test_round_trip_series_and_metrics(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    q, qdot, target = _write(path, 200)
    run = read_recording(path)
    assert run.step.tolist() == list(range(200))
    np.testing.assert_allclose(run.t, np.arange(200) * DT, atol=1e-9)
    np.testing.assert_allclose(run.q, q)
    np.testing.assert_allclose(run.target, np.tile(target, (200, 1)))
    np.testing.assert_allclose(run.current_cmd[:, 0], 100.0 + np.arange(200))
    assert run.metadata["controller"] == "synthetic"
    assert run.summary == {"reached": True}
    assert [e[2] for e in run.events] == ["start"]
    assert run.closed_cleanly

    summary: dict[str, Any] = summarize_recording(path)
    expected = compute_metrics(
        Trace(dt=DT, q=q, qdot=qdot, tau=np.full_like(q, 0.5), target=target)
    ).as_dict()
    metrics = summary["metrics"]
    assert isinstance(metrics, dict)
    for key, value in expected.items():
        assert metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-9), key
    assert summary["duration_s"] == pytest.approx(199 * DT)
    np.testing.assert_allclose(summary["final_error"], target - q[-1])


def test_inspect_says_how_a_recorded_overshoot_came_about(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """C crosses its goal at speed and swings 0.1 rad past: an arrival, named with its size."""
    from reach_driver.cli import main

    q, qdot, target = _synthetic_run(100)
    t = np.arange(100) * DT
    swing = 0.1 * np.sin(np.pi * np.clip(t - 1.0, 0.0, 1.0))  # past C's goal over 1-2 s
    q[:, 2] = np.where(t < 1.0, q[:, 2], target[2]) - swing  # C steps down: past is below
    qdot[:, 2] = np.gradient(q[:, 2], DT)
    path = tmp_path / "swing.rrd"
    with RunRecorder(path) as rec:
        for k in range(100):
            rec.log_step(StepSample(k * DT, k, q[k], qdot[k], target, np.zeros(4)))
    assert main(["inspect", "--json", str(path)]) == 0
    over = json.loads(capsys.readouterr().out)["overshoot"]
    assert (
        over["joint"] == "C"
        and over["arrival"]
        and over["past_rad"] == pytest.approx(0.1, abs=2e-3)
    )
    assert main(["inspect", str(path)]) == 0
    assert "overshoot: C went 100.0 mrad" in capsys.readouterr().out


def test_exception_in_run_is_recorded(tmp_path: Path) -> None:
    path = tmp_path / "crash.rrd"
    q, qdot, target = _synthetic_run(5)
    with pytest.raises(RuntimeError), RunRecorder(path) as rec:
        for k in range(5):
            rec.log_step(StepSample(k * DT, k, q[k], qdot[k], target, np.zeros(4)))
        raise RuntimeError("controller exploded")
    run = read_recording(path)
    assert len(run.step) == 5
    assert run.events[-1][1] == "ERROR" and "controller exploded" in run.events[-1][2]


def test_recording_survives_sigkill(tmp_path: Path) -> None:
    """What was logged before the process died is readable (flushed on a short period)."""
    path = tmp_path / "killed.rrd"
    script = textwrap.dedent(
        f"""
        import sys, time, numpy as np
        from reach_driver.recording import RunRecorder, StepSample
        rec = RunRecorder({str(path)!r}, flush_period_s=0.05)
        k = 0
        while True:
            rec.log_step(StepSample(k * 0.05, k, np.full(4, 1.0 + 0.001 * k), np.zeros(4),
                                    np.full(4, 2.0), np.zeros(4)))
            if k == 50:
                print("ready", flush=True)
            k += 1
            time.sleep(0.002)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        # killed once the first 50 steps are on disk (flushed every 0.05 s: a loaded host may
        # take longer to get there, never forever)
        assert wait_until(lambda: len(recorded_steps(path)) >= 50, timeout=30.0, poll_s=0.05)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    run = read_recording(path)
    assert len(run.step) >= 50
    assert not run.closed_cleanly
    np.testing.assert_allclose(run.q[:, 0], 1.0 + 0.001 * run.step)
    assert "metrics" in summarize_recording(path)


@pytest.mark.skipif(
    shutil.which("rerun") is None and not (Path(sys.executable).parent / "rerun").exists(),
    reason="rerun CLI not installed",
)
def test_rerun_verify_accepts_recording(tmp_path: Path) -> None:
    path = tmp_path / "verify.rrd"
    _write(path, 20)
    rerun_cli = Path(sys.executable).parent / "rerun"
    cli = str(rerun_cli) if rerun_cli.exists() else "rerun"
    result = subprocess.run(
        [cli, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "verified without error" in result.stdout + result.stderr


def test_unreadable_inputs_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(RecordingReadError, match="no such recording"):
        read_recording(tmp_path / "missing.rrd")
    junk = tmp_path / "junk.rrd"
    junk.write_bytes(b"not a recording at all")
    with pytest.raises(RecordingReadError):
        read_recording(junk)


def test_inspect_cli_prints_the_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from reach_driver.cli import main

    path = tmp_path / "run.rrd"
    q, _, target = _write(path, 100)
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "100 steps" in out and "final state" in out and "settling_time_s" in out
    assert f"{target[0] - q[-1, 0]:+.4f}" in out
    assert "overshoot: no joint went past its goal" in out  # a first-order approach
    assert main(["inspect", "--json", str(path)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["steps"] == 100 and data["metrics"]["reached"] in (True, False)
    assert data["overshoot"] is None
    assert main(["inspect", str(tmp_path / "missing.rrd")]) != 0
    assert "no such recording" in capsys.readouterr().out
