"""One controller, simulated or real: the closed loop through reach_driver against the virtual
arm on a real pty (sped up), compared with the direct environment, under faults (weak joint,
corrupted bytes, the arm restarting, a stalled controller, a bad target) and through the
`reach-driver` CLI and `make demo`."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import WATCHDOG_S, wait_until

from policy.campaigns.evaluate_command import main as evaluate_main
from policy.campaigns.evaluation import Episode, RunConfig, run_episode
from policy.campaigns.via_driver import (
    AGREEMENT,
    DriverConfig,
    run_episode_via_driver,
    tick_origin,
)
from policy.tasks.scenarios import SCENARIOS
from protocol import HardwareStatus, Mode, Packet, PacketID
from protocol.payload import pack_floats
from reach_driver import ArmClient, ControlLoop, SafetyConfig, open_transport
from reach_driver.assembler import StateAssembler
from reach_driver.cli import Exit, main
from reach_driver.control import control_period
from reach_driver.controllers import load_controller
from reach_driver.rrd_summary import summarize_recording
from reach_sim_bridge.emulator.server import SimServer

ROOT = Path(__file__).resolve().parents[1]
JOINT_IDS = (5, 4, 3, 2)  # E D C B


SCENARIO_1 = SCENARIOS[0].episode()
SCENARIO_2 = SCENARIOS[1].episode()
SCENARIO_3 = SCENARIOS[2].episode()  # E at 25 % torque
#: where `ddpg` ends well inside the 20 mrad tolerance (about 1 mrad: docs/results.md); its D
#: swings 0.7 rad past a 0.11 rad step on the way, so the overshoot agreement is relative
DDPG_TARGET = SCENARIO_2


def modes(sim: SimServer) -> list[Mode]:
    return [sim.firmware.mode(d) for d in JOINT_IDS]


# The `sim` fixture's arm: at scenario 1's start, in real time. Every arm served in a test here
# (the fixture's and run_episode_via_driver's) pauses with the host (conftest.
# arm_pauses_with_host). What a loaded host still does is run the control loop late now and
# then, so that it skips a tick (counted): a period is 50 ms of wall time at 1x, 25 ms at 2x,
# and the ddpg-distilled and lambda runs below overshoot when ticks go missing (seen at 2x under
# a busy loop: lambda 50 % past its goal).
pytestmark = [
    pytest.mark.sim(speed=1.0, start=SCENARIO_1.start),
    pytest.mark.usefixtures("arm_pauses_with_host"),
]


# ------------------------------------------------------------------------- fast: pure logic


@pytest.mark.parametrize("name", ["ddpg", "ddpg-distilled"])
def test_learned_controllers_run_at_the_rate_they_were_trained_at(name: str) -> None:
    learned = load_controller(name)
    trained_hz = learned.weights.metadata["env"]["control_hz"]  # type: ignore[attr-defined]
    period, warning = control_period(learned, None)
    assert period == pytest.approx(1.0 / trained_hz) and warning is None
    pid = load_controller("pid", period_s=0.1)
    assert control_period(pid, None) == (0.1, None)
    period, warning = control_period(pid, 0.05)
    assert period == 0.05 and warning is not None and "0.1 s" in warning


def _heartbeat(device: int, pid: PacketID, value: float) -> Packet:
    return Packet(device, pid, pack_floats(value))


def test_lost_packets_cost_only_their_own_tick() -> None:
    """Ticks stay whole (every value from the same tick) and counted when packets are lost;
    a missing position is extrapolated from the previous tick, a missing velocity held."""
    period = 0.05
    asm = StateAssembler(period)
    order = [(d, p) for d in (2, 3, 4, 5) for p in (PacketID.POSITION, PacketID.VELOCITY)]
    lost = {3: (3, PacketID.POSITION), 5: (2, PacketID.POSITION), 7: (5, PacketID.VELOCITY)}
    t_end = time.monotonic()

    def pos(k: int, j: int) -> float:
        return 1.0 + 0.1 * j + 0.01 * k

    def vel(k: int, j: int) -> float:
        return 0.2 + 0.01 * j + 0.001 * k

    taken = []
    for k in range(10):
        t = t_end - (10 - k) * period  # arrivals one period apart, all in the past
        for dev, pid in order:
            if lost.get(k) == (dev, pid):
                continue
            j = JOINT_IDS.index(dev)
            value = pos(k, j) if pid == PacketID.POSITION else vel(k, j)
            asm(_heartbeat(dev, pid, value), t)
        got = asm.take(0.0)  # tick 7 lost its last packet: handed out after the grace
        assert got is not None, f"tick {k} was not handed out"
        taken.append(got)
    assert [g.ticks for g in taken] == list(range(10))
    assert [g.partial for g in taken] == [k in lost for k in range(10)]
    for k, g in enumerate(taken):
        q, qdot = g.values[0::2], g.values[1::2]
        want_q = np.array([pos(k, j) for j in range(4)])
        want_qdot = np.array([vel(k, j) for j in range(4)])
        if k == 3:  # C's position: previous position + previous velocity x period
            want_q[2] = pos(2, 2) + vel(2, 2) * period
        if k == 5:
            want_q[3] = pos(4, 3) + vel(4, 3) * period
        if k == 7:  # E's velocity held
            want_qdot[0] = vel(6, 0)
        np.testing.assert_allclose(q, want_q, atol=1e-6)
        np.testing.assert_allclose(qdot, want_qdot, atol=1e-6)
    assert asm.incomplete == 0 and asm.partial == 3


def test_tick_origin_is_found_from_exact_float32_matches() -> None:
    h = 0.002
    times = 10.0 + np.arange(2000) * h
    q = np.stack([np.sin(times * (j + 1)) + 2.0 for j in range(4)], axis=1)
    origin = times[137]
    loop_t = np.arange(0, 3.0, 0.05)
    idx = 137 + np.rint(loop_t / h).astype(int)
    reported = q[idx].astype(np.float32).astype(float)
    reported[5] += 0.3  # a value damaged on the line matches nothing and is outvoted
    assert tick_origin(times, q, loop_t, reported) == pytest.approx(origin, abs=1e-9)
    with pytest.raises(RuntimeError, match="sensor noise"):
        tick_origin(times, q, loop_t, reported + 1e-3)


def test_driver_side_noise_is_the_direct_runners_realisation() -> None:
    from policy.tasks.episodes import NoisyReadings
    from reach_driver.controllers import ControlState
    from reach_sim_bridge.model.sensors import SensorNoise

    class Seen:
        def __init__(self) -> None:
            self.readings: list[ControlState] = []

        def reset(self) -> None: ...

        def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
            self.readings.append(state)
            return np.zeros(4)

    noise = SensorNoise(0.01, 0.1)
    seen = Seen()
    noisy = NoisyReadings(seen, noise, np.random.default_rng(7))
    q, qdot = np.array([3.0, 1.5, 1.5, 3.0]), np.array([0.1, -0.2, 0.3, 0.0])
    for k in range(3):
        noisy.act(ControlState(q, qdot, 0.05 * k), q)
    rng = np.random.default_rng(7)  # SensorNoise.apply draws q then qdot per step
    for k, r in enumerate(seen.readings):
        np.testing.assert_allclose(r.q, q + rng.normal(0.0, 0.01, 4))
        np.testing.assert_allclose(r.qdot, qdot + rng.normal(0.0, 0.1, 4))
        assert r.t == 0.05 * k


def test_the_served_arm_gets_the_episodes_start_torque_scale_and_parameter_draw() -> None:
    from reach_sim_bridge.model.arm import Alpha5Arm

    episode = Episode(
        start=np.array([3.0, 1.6, 1.6, 3.0]),
        target=np.array([3.2, 1.5, 1.7, 3.1]),
        torque_scale=np.array([0.25, 1.0, 0.5, 1.0]),
    )
    seen: dict[str, Any] = {}

    class Seen(Exception):
        pass

    def inspect(server: SimServer) -> None:
        assert isinstance(server.arm, Alpha5Arm)
        seen["params"] = server.arm.params
        seen["q"] = server.snapshot().q
        seen["scale"] = np.array(server.arm.torque_scale)
        raise Seen

    with pytest.raises(Seen):
        run_episode_via_driver(
            load_controller("pid"),
            episode,
            RunConfig(param_spread=0.2),
            DriverConfig(),
            episode_seed=5,
            on_server=inspect,
        )
    direct = Alpha5Arm(dt=0.002)
    direct.randomize(0.2, rng=np.random.default_rng([5, 1]))
    assert seen["params"].as_dict() == {
        **direct.params.as_dict(),
        "torque_scale": seen["params"].torque_scale,
    }
    np.testing.assert_allclose(seen["scale"], [0.25, 1.0, 0.5, 1.0])
    np.testing.assert_allclose(seen["q"], episode.start, atol=0.01)  # held in standby
    with pytest.raises(ValueError, match="outside the arm's joint limits on B"):
        run_episode_via_driver(
            load_controller("pid"), Episode(episode.start, np.array([3, 1.5, 1.7, 7]))
        )


# ------------------------------------------------------------------- the CLI, the real path


def test_a_target_outside_the_limits_is_refused_and_nothing_moves(
    sim: SimServer, tmp_path: Path, capsys: Any
) -> None:
    q0 = sim.snapshot().q
    record = tmp_path / "refused.rrd"
    target = [*SCENARIO_1.target[:3], 6.5]  # B beyond 2 pi
    argv = ["--port", str(sim.link), "run", "--controller", "ddpg-distilled", "--target"]
    argv += [*map(str, target), "--seconds", "5", "--record", str(record)]
    assert main(argv) == Exit.LIMIT
    err = capsys.readouterr().err
    assert "B (0x02)" in err
    assert not record.exists()
    assert modes(sim) == [Mode.STANDBY] * 4  # a CURRENT packet would have switched the mode
    np.testing.assert_allclose(sim.snapshot().q, q0, atol=2e-3)


@pytest.mark.slow
def test_ddpg_reaches_its_target_through_reach_driver_and_prints_its_metrics(
    sim: SimServer, tmp_path: Path, capsys: Any
) -> None:
    record = tmp_path / "ddpg.rrd"
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller"]
    argv += ["ddpg", "--target", *map(str, DDPG_TARGET.target), "--seconds", "8"]
    argv += ["--record", str(record)]
    code = main(argv)
    out = capsys.readouterr().out
    assert code == Exit.OK, out
    assert np.max(np.abs(sim.snapshot().q - DDPG_TARGET.target)) < 0.02  # the TRUE angles
    for word in ("energy [J]", "RMSE", "settling time", "reached", "measured current"):
        assert word in out
    assert "arm left in zero_velocity" in out and f"rerun {record}" in out
    assert wait_until(lambda: modes(sim) == [Mode.ZERO_VELOCITY] * 4, timeout=10.0)
    summary: dict[str, Any] = summarize_recording(record)
    recorded = summary["recorded_summary"]
    # every control step and the state that ended it; each of the 160 ticks at 20 Hz was
    # stepped on, or counted as skipped when the loop, late on a loaded host, took a newer one
    assert summary["steps"] == recorded["steps"] + 1
    assert recorded["steps"] + recorded["skipped_states"] >= 160 and recorded["steps"] >= 120
    assert 8.0 - 1e-9 <= summary["duration_s"] <= 8.1 + 1e-9  # or a tick or two on, if late
    assert recorded["metrics"]["reached"] is True, (recorded["metrics"], out)
    # `reach-driver inspect` scores the recording like the run printed it, energy included
    # exactly when no tick was lost (the printed trace interpolates a lost one, and energy,
    # integrated from power, is the metric that interpolation moves most).
    keys = ["rmse", "mie", "msse", "settling_time_s"]
    if recorded["steps"] == 160:
        keys.append("energy_j")
    for key in keys:
        assert summary["metrics"][key] == pytest.approx(recorded["metrics"][key], rel=0.02)
    assert 5.0 < recorded["metrics"]["energy_j"] < 40.0


@pytest.mark.slow
def test_the_arm_restarting_mid_run_stops_the_run_safely_and_says_so(
    sim: SimServer, capsys: Any
) -> None:
    t0 = sim.sim_time

    def power_cycle() -> None:
        if sim.wait_sim_time(t0 + 2.0, timeout=30):
            sim.restart(downtime_s=0.3)  # new pty under the same link, fresh firmware

    cycler = threading.Thread(target=power_cycle)
    cycler.start()
    argv = ["--port", str(sim.link), "run", "--controller", "pid", "--target"]
    argv += [*map(str, SCENARIO_1.target), "--seconds", "20"]
    code = main(argv)
    cycler.join()
    captured = capsys.readouterr()
    assert code == Exit.FAILED
    assert "link down" in captured.err and "watchdog" in captured.err
    failed = next(line for line in captured.out.splitlines() if "run failed" in line)
    assert "link" in failed  # names the cause: the link went down under it
    assert "arm left in zero_velocity" in captured.out
    # The fresh firmware came up in standby; the driver put it in its safe mode.
    assert modes(sim) == [Mode.ZERO_VELOCITY] * 4


@pytest.mark.slow
def test_a_motor_fault_mid_run_stops_the_run(sim: SimServer, capsys: Any) -> None:
    t0 = sim.sim_time

    def motor_fault() -> None:
        if sim.wait_sim_time(t0 + 1.5, timeout=30):
            sim.inject_fault(4, HardwareStatus.MOTOR_OVER_CURRENT)

    injector = threading.Thread(target=motor_fault)
    injector.start()
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    argv.append("--target")
    argv += [*map(str, SCENARIO_1.target), "--seconds", "20"]
    code = main(argv)
    injector.join()
    out = capsys.readouterr().out
    assert code == Exit.FAILED
    failed = next(line for line in out.splitlines() if "run failed" in line)
    assert "D (0x04): MOTOR_OVER_CURRENT" in failed
    assert float(failed.split("t = ")[1].split(" s")[0]) < 1.5 + 1.1  # polled once a second
    assert "arm left in zero_velocity" in out
    assert modes(sim) == [Mode.ZERO_VELOCITY] * 4


def test_max_current_tightens_what_the_controller_may_command(
    sim: SimServer, tmp_path: Path, capsys: Any
) -> None:
    record = tmp_path / "gentle.rrd"
    argv = [
        "--port",
        str(sim.link),
        "--max-current",
        "100,100,100,50",
        "--watchdog",
        str(WATCHDOG_S),
        "run",
        "--controller",
        "pid",
        "--target",
        *map(str, SCENARIO_1.target),
        "--seconds",
        "1",
        "--record",
        str(record),
    ]
    assert main(argv) == Exit.OK, capsys.readouterr().out
    from reach_driver.rrd_summary import read_recording

    run = read_recording(record)
    peak = np.max(np.abs(run.current_cmd), axis=0)
    assert np.all(peak <= [100.0, 100.0, 100.0, 50.0]) and np.all(peak > 40.0)
    with pytest.raises(SystemExit) as usage:  # argparse's way out: exit 2 with the usage
        main(["--port", str(sim.link), "--max-current", "0", "info"])
    assert usage.value.code == Exit.USAGE
    assert "--max-current takes one positive value or four" in capsys.readouterr().err


def test_a_stalled_controller_is_stopped_by_the_watchdog(
    sim: SimServer,
) -> None:
    pid = load_controller("pid")
    seen: dict[str, bool] = {}
    asked: list[float] = []  # the loop times it was asked at

    class Stalls:
        def reset(self) -> None:
            pid.reset()

        def act(self, state: Any, target: np.ndarray) -> np.ndarray:
            asked.append(state.t)
            if state.t >= 0.25:  # hangs (a deadlock, a slow solver) with current applied
                seen["stopped"] = wait_until(
                    lambda: modes(sim) == [Mode.ZERO_VELOCITY] * 4, timeout=5
                )
            return np.asarray(pid.act(state, target))

    safety = SafetyConfig(watchdog_s=0.2)
    with ArmClient(open_transport(str(sim.link)), safety=safety) as client:
        summary = ControlLoop(client, Stalls(), 0.05).run(SCENARIO_1.target, 5.0)
    assert seen["stopped"], "the watchdog did not stop the arm while the controller hung"
    assert summary.error is not None and "watchdog" in summary.error
    # the steps before the hang (t = 0 to 0.2 s: 5, fewer if a late loop skipped a tick) were
    # taken; the one that hung was not
    assert asked[-1] >= 0.25 and all(t < 0.25 for t in asked[:-1])
    assert summary.steps == len(asked) - 1 <= 5
    assert summary.left_in == "zero_velocity (confirmed by the arm)"
    # ZERO_VELOCITY brakes the joints to rest (and holds them there against gravity).
    assert wait_until(lambda: np.max(np.abs(sim.snapshot().qdot)) < 0.01, timeout=5)


# ------------------------------------------------- through the driver vs the direct runner


@pytest.mark.slow
def test_the_driver_path_agrees_with_the_direct_environment() -> None:
    """Same controller, same episode: the protocol path must not degrade control (`ddpg`
    keeps memory channels across periods: a lost or doubled period would show here)."""
    ddpg = load_controller("ddpg")
    config = RunConfig(seconds=8.0)
    direct = run_episode(ddpg, DDPG_TARGET, config)
    via = run_episode_via_driver(ddpg, DDPG_TARGET, config, DriverConfig(speed=2.0))
    d, v = direct.metrics, via.result.metrics
    assert via.result.trace.q.shape == direct.trace.q.shape == (161, 4)
    assert abs(v.rmse - d.rmse) <= AGREEMENT.rmse_rel * d.rmse
    assert abs(v.mie - d.mie) <= AGREEMENT.mie_rel * d.mie
    assert abs(v.energy_j - d.energy_j) <= AGREEMENT.energy_rel * d.energy_j
    assert abs(v.settling_time_s - d.settling_time_s) <= AGREEMENT.settling_abs_s
    assert abs(v.overshoot_pct - d.overshoot_pct) <= AGREEMENT.overshoot_bound(d.overshoot_pct)
    assert np.max(np.abs(via.result.final_error - direct.final_error)) <= (
        AGREEMENT.final_error_abs
    )
    assert v.reached and d.reached
    timing = via.timing_dict()
    # the arm served at 2x: never faster (slower when the host pauses it; speed is measured
    # by the benchmarks, not here)
    assert timing["steps"] + timing["skipped_states"] >= 160 and timing["steps"] >= 120
    assert 0.0 < timing["arm_speed"] <= 2.0 * 1.05


@pytest.mark.slow
def test_the_torque_limited_scenario_through_the_driver() -> None:
    """Scenario 3: E at 25 % torque, set on the served arm, slows E as in the direct env."""
    ddpg = load_controller("ddpg")
    config = RunConfig(seconds=10.0)
    via = run_episode_via_driver(ddpg, SCENARIO_3, config, DriverConfig(speed=4.0))
    weak = run_episode(ddpg, SCENARIO_3, config)
    strong = run_episode(ddpg, Episode(SCENARIO_3.start, SCENARIO_3.target), config)
    # E at 1 s through the driver is where the weak arm's E is within 2 periods of 1 s (at 4x
    # real time a loaded machine slips the served clock by a period or so: E then moves 0.048
    # rad a period), and far short of where the full-torque arm's is (0.25 rad further)
    e_via = via.result.trace.q[20, 0]
    assert weak.trace.q[18, 0] - 0.01 <= e_via <= weak.trace.q[22, 0] + 0.01
    assert strong.trace.q[20, 0] - weak.trace.q[20, 0] > 0.15  # the scale really matters
    assert strong.trace.q[20, 0] - e_via > 0.1
    assert via.result.metrics.reached
    d, v = weak.metrics, via.result.metrics
    assert abs(v.rmse - d.rmse) <= AGREEMENT.rmse_rel * d.rmse


@pytest.mark.slow
def test_one_percent_corrupted_bytes_are_survived() -> None:
    distilled = load_controller("ddpg-distilled")
    config = RunConfig(seconds=8.0)
    via = run_episode_via_driver(
        distilled, SCENARIO_1, config, DriverConfig(speed=4.0, corrupt_rate=0.01, seed=3)
    )
    direct = run_episode(distilled, SCENARIO_1, config)
    timing = via.timing_dict()
    assert via.bad_frames > 50  # ~10 % of frames damaged, each counted
    assert timing["partial_states"] > 10  # ticks completed from the previous one
    assert via.result.metrics.reached
    assert np.max(np.abs(via.result.final_error)) < 0.02
    assert via.result.metrics.rmse <= 1.1 * direct.metrics.rmse


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "speed"),
    # MPC solves take ~15-25 ms of a 50 ms period, capped at 40 ms of wall time: at half speed
    # a period is 100 ms of wall time, so a host loaded past its cores still fits a solve
    # in each and the loop takes every state
    [("pid", 4.0), ("mpc", 0.5)],
)
def test_pid_and_mpc_reach_a_target_through_the_driver(name: str, speed: float) -> None:
    episode = Episode(start=np.array([3.0, 1.6, 1.6, 3.0]), target=np.array([3.6, 1.3, 2.0, 3.6]))
    via = run_episode_via_driver(
        load_controller(name), episode, RunConfig(seconds=4.0), DriverConfig(speed=speed)
    )
    assert via.result.metrics.reached, via.result.final_error
    assert np.max(np.abs(via.result.final_error)) < 0.02


@pytest.mark.slow
def test_evaluate_via_driver_writes_metrics_and_loop_timing(tmp_path: Path) -> None:
    targets = tmp_path / "episodes.json"
    targets.write_text(
        json.dumps([{"start": [3.0, 1.6, 1.6, 3.0], "target": [3.3, 1.5, 1.8, 3.3]}])
    )
    out = tmp_path / "eval.json"
    argv = [
        "--controller",
        "pid",
        "--targets",
        str(targets),
        "--seconds",
        "3",  # the PID settles at 2.45 s; at 2 s it is still moving (not at rest)
        "--via-driver",
        "--sim-speed",
        "2",  # 25 ms of wall time a tick: a loop a loaded host runs late skips fewer
        "--out",
        str(out),
        "--quiet",
    ]
    assert evaluate_main(argv) == 0
    data = json.loads(out.read_text())
    episode = data["episodes"][0]
    assert episode["reached"] is True
    timing = data["controller_stats"]["via_driver"]["episodes"][0]
    # 60 ticks at 20 Hz, each stepped on or counted as skipped (a loop a loaded host runs late
    # takes the newer state), most of them stepped on
    assert timing["steps"] + timing["skipped_states"] >= 60 and 30 <= timing["steps"] <= 60
    assert timing["state_age_p99_ms"] >= 0


# ------------------------------------------------------------------------------ make demo


@pytest.mark.slow
def test_demo_runs_ddpg_through_the_cli_and_writes_a_recording(tmp_path: Path) -> None:
    record = tmp_path / "demo.rrd"
    demo = [sys.executable, str(ROOT / "tools" / "demo.py"), "--speed", "4", "--seconds", "4"]
    # As `make demo` runs it: the venv not activated, so its programs are not on PATH
    path = [d for d in os.environ["PATH"].split(os.pathsep) if not (Path(d) / "rerun").exists()]
    env = {**os.environ, "PATH": os.pathsep.join(path)}
    proc = subprocess.run(
        [*demo, "--record", str(record)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
        env=env,
    )
    out = proc.stdout
    assert proc.returncode == 0, out + proc.stderr
    assert "scenario 1" in out and "RMSE" in out
    # The viewer is named one way, as the user types it here: the venv's rerun, by its path
    viewers = set(re.findall(rf"([^\s`]*rerun) {re.escape(str(record))}", out))
    assert len(viewers) == 1 and (ROOT / viewers.pop()).is_file(), out
    inspect = set(re.findall(rf"([^\s`]*reach-driver) inspect {re.escape(str(record))}", out))
    assert len(inspect) == 1 and (ROOT / inspect.pop()).is_file(), out
    # the run ends on the first state taken at or after 4 s: a host pause (50 ms of wall time
    # is 200 ms of arm time at 4x) may skip the heartbeats around it, each counted
    summary: dict[str, Any] = summarize_recording(record)
    duration = summary["duration_s"]
    assert 4.0 - 1e-9 <= duration <= 4.0 + 0.2 + 1e-9


@pytest.mark.slow
def test_lambda_reaches_scenario_1_through_reach_driver_from_a_twin_file(
    sim: SimServer, tmp_path: Path, capsys: Any
) -> None:
    """The model-based controller through the real path, its twin read from an arm file (the
    emulated arm is the nominal one, so is the twin): reached at rest, no overshoot."""
    twin = tmp_path / "arm.json"
    twin.write_text('{"frictionloss": [0.7, 0.7, 0.7, 0.075]}')
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller"]
    argv += ["lambda", "--param"]
    argv += [f"params={twin}", "--target", *map(str, SCENARIO_1.target), "--seconds", "6"]
    code = main([*argv, "--json", "-q"])
    out = capsys.readouterr().out
    assert code == Exit.OK, out
    assert np.max(np.abs(sim.snapshot().q - SCENARIO_1.target)) < 0.01  # the TRUE angles
    metrics = json.loads(out)["metrics"]
    assert metrics["reached"] is True and metrics["at_rest"] is True, metrics
    assert metrics["overshoot_pct"] < 2.0, metrics
