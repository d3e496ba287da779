"""Diagnostics in recordings: the devices' Monitor readings (voltage, temperature, humidity,
pressure at 0x67 and 0x6E) and HARDWARE_STATUS flags that the driver has are logged to the
.rrd by `run --record` and `monitor --record`, and `inspect` reports them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import WATCHDOG_S

from protocol import DeviceID, HardwareStatus
from reach_driver.cli import Exit, main
from reach_driver.recording import DIAGNOSTIC_LETTERS, RunRecorder
from reach_driver.rrd_summary import STATUS_KEY, read_recording, summarize_recording
from reach_driver.state import MONITOR_READINGS, JointState, Reading
from reach_sim_bridge.emulator.faults import Leak
from reach_sim_bridge.emulator.server import SimServer

KEYS = [m.key for m in MONITOR_READINGS]


def _js(device: int, t: float, volts: float, flags: HardwareStatus) -> JointState:
    return JointState(
        int(device), voltage=Reading(volts, t), status=Reading(flags, t), pressure=Reading(1.1, t)
    )


def test_only_newer_readings_are_logged_and_flag_changes_are_named(tmp_path: Path) -> None:
    path = tmp_path / "diag.rrd"
    d = int(DeviceID.D)
    with RunRecorder(path, metadata={"controller": "synthetic"}) as rec:
        first = {d: _js(d, 1.0, 24.0, HardwareStatus.NONE)}
        assert rec.log_diagnostics(0.0, 0, first)
        assert not rec.log_diagnostics(0.1, 1, first)  # nothing new: nothing logged
        assert not rec.log_diagnostics(0.1, 1, {})  # nothing known at all
        later = {d: _js(d, 2.0, 17.5, HardwareStatus.LOW_SUPPLY_VOLTAGE)}
        assert rec.log_diagnostics(0.2, 2, later)
    run = read_recording(path)
    volts = run.diagnostics["voltage_v"]
    assert volts.t.tolist() == pytest.approx([0.0, 0.2])
    column = DIAGNOSTIC_LETTERS.index("D")
    assert volts.values[:, column].tolist() == [24.0, 17.5]
    assert np.isnan(volts.values[:, DIAGNOSTIC_LETTERS.index("E")]).all()  # never reported
    assert "temperature_c" not in run.diagnostics  # no device reported it
    assert run.diagnostics[STATUS_KEY].values[-1, column] == float(
        HardwareStatus.LOW_SUPPLY_VOLTAGE
    )
    events = [text for _, _, text in run.events]
    assert events == ["status D (0x04): LOW_SUPPLY_VOLTAGE"]  # NONE -> NONE named nothing


def test_a_recorded_run_holds_every_devices_diagnostics(sim: SimServer, tmp_path: Path) -> None:
    sim.inject_fault(int(DeviceID.B), HardwareStatus.JOINT_SERVICE_DUE)  # reported, not blocking
    record = tmp_path / "run.rrd"
    target = sim.snapshot().q + np.array([0.2, -0.1, 0.1, 0.2])
    argv = ["--port", str(sim.link), "-q", "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "pid", "--target"]
    argv += [*map(str, target), "--seconds", "1", "--record", str(record)]
    assert main(argv) == Exit.OK
    run = read_recording(record)
    assert set(run.diagnostics) == {*KEYS, STATUS_KEY}
    for key in KEYS:  # read before and after the run: two rows, every device in each
        series = run.diagnostics[key]
        assert len(series.t) >= 2 and np.isfinite(series.values).all(), key
        assert series.t[0] <= run.t[0] + 1e-6 and series.t[-1] >= run.t[-1] - 1e-6
    summary: dict[str, Any] = summarize_recording(record)
    diag = summary["diagnostics"]
    assert isinstance(diag, dict) and diag["devices"] == ["E", "D", "C", "B", "A"]
    assert all(18.0 <= v <= 24.0 for v in diag["voltage_v"]["final"])
    assert diag["temperature_c"]["final"] == pytest.approx([20.0] * 5, abs=5.0)
    assert diag["pressure_0x6e_bar"]["final"] == pytest.approx([1.0] * 5, abs=0.1)
    assert diag["internal_pressure_bar"]["max"] == pytest.approx([1.0] * 5, abs=0.1)
    assert diag["final_status"] == {
        "E": ["ok"],
        "D": ["ok"],
        "C": ["ok"],
        "B": ["JOINT_SERVICE_DUE"],
        "A": ["ok"],
    }
    assert any("status B (0x02): JOINT_SERVICE_DUE" in e for e in summary["events"])


def test_a_recorded_monitor_shows_a_leak_and_inspect_reports_it(
    sim: SimServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    device = int(DeviceID.D)
    # tau 5 s of sim time: past the 40 % level after 2 s, 0.5 s of wall time at 4x
    sim.observe(lambda _arm, fw: fw.inject_leak(Leak(device, time_constant_s=5.0)))
    record = tmp_path / "monitor.rrd"
    argv = ["--port", str(sim.link), "monitor", "--seconds", "2", "--record", str(record)]
    assert main(argv) == Exit.OK
    capsys.readouterr()
    run = read_recording(record)
    assert len(run.step) > 5  # the states, at 20 Hz
    humidity = run.diagnostics["humidity_pct"]
    d, e = DIAGNOSTIC_LETTERS.index("D"), DIAGNOSTIC_LETTERS.index("E")
    assert len(humidity.t) >= 3  # a row per refresh that read newer values
    assert np.all(np.diff(humidity.values[:, d]) > 0.0)  # rising with each reading
    assert humidity.values[-1, d] > 40.0 and humidity.values[-1, e] < 11.0
    assert main(["inspect", "--json", str(record)]) == Exit.OK
    diag = json.loads(capsys.readouterr().out)["diagnostics"]
    assert "OVER_HUMIDITY" in diag["final_status"]["D"]
    assert diag["final_status"]["E"] == ["ok"]
    assert diag["humidity_pct"]["max"][d] > 40.0 > diag["humidity_pct"]["min"][d]
    assert main(["inspect", str(record)]) == Exit.OK
    out = capsys.readouterr().out
    assert "diagnostics (last reading of each device)" in out
    assert "OVER_HUMIDITY" in out and "RH %" in out and "0x6E bar" in out
