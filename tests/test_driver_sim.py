"""End to end against the virtual arm (in-process SimServer, sped up): the CLI over a pty and
over UDP, reconnecting after the simulator restarts, the watchdog, limit refusal, garbage."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import LOOPBACK, WATCHDOG_S, default_sigint, udp_url, wait_until

from protocol import DeviceID, Mode, PacketID
from reach_driver import (
    ArmClient,
    EventKind,
    LinkConfig,
    LinkDownError,
    LinkState,
    SafetyConfig,
    open_transport,
)
from reach_driver.cli import Exit, main
from reach_sim_bridge.emulator.faults import FaultConfig

SPEED = 4.0
ROOT = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.sim(speed=SPEED, udp=LOOPBACK)


def test_info_lists_devices_versions_limits_and_status(sim, sim_port, capsys) -> None:
    code = main(["--port", sim_port, "info", "--json"])
    out = capsys.readouterr().out
    assert code == Exit.OK, out
    devices = json.loads(out)["devices"]
    assert set(devices) == {"A", "B", "C", "D", "E"}
    d = devices["D"]
    assert d["software_version"] == "0.1.0"
    assert d["serial_number"] == 4104.0
    assert d["mode"] == "standby"
    assert d["status_flags"] == []
    lo, hi = sim.arm.position_limits[1]
    assert d["limits"]["position"] == pytest.approx([lo, hi], abs=1e-6)
    assert d["limits"]["current"] == pytest.approx([-600.0, 600.0])


def test_info_table_names_each_joint(sim, capsys) -> None:
    assert main(["--port", str(sim.link), "info"]) == Exit.OK
    out = capsys.readouterr().out
    for name in ("E (0x05)", "D (0x04)", "C (0x03)", "B (0x02)", "A (0x01)", "0.1.0"):
        assert name in out


def test_move_reaches_the_target_in_position_mode(sim, sim_port, capsys) -> None:
    q0 = sim.snapshot().q
    target = q0 + np.array([0.3, -0.2, 0.25, -0.4])
    argv = ["--port", sim_port, "move", *map(str, target), "--jaw", "8", "--timeout", "30"]
    code = main(argv)
    out = capsys.readouterr().out
    assert code == Exit.OK, out
    assert "reached" in out
    snap = sim.snapshot()
    assert np.max(np.abs(snap.q - target)) < 0.03
    assert abs(snap.jaw_mm - 8.0) < 0.6
    assert wait_until(
        lambda: all(sim.firmware.mode(d) == Mode.POSITION for d in (5, 4, 3, 2, 1)), timeout=10.0
    )


def test_move_outside_a_limit_is_refused_and_nothing_moves(sim, capsys) -> None:
    q0 = sim.snapshot().q
    code = main(["--port", str(sim.link), "move", "3.0", "3.9", "1.5", "3.0"])
    err = capsys.readouterr().err
    assert code == Exit.LIMIT
    assert "limit" in err and "D (0x04)" in err
    assert all(sim.firmware.mode(d) == Mode.STANDBY for d in (5, 4, 3, 2))
    assert "position_out_of_limits" not in sim.stats().ignored  # never reached the arm
    assert np.max(np.abs(sim.snapshot().q - q0)) < 0.01


def test_move_that_cannot_finish_in_time_fails_with_a_message(sim, capsys) -> None:
    q0 = sim.snapshot().q
    target = q0 + np.array([-1.5, 0.0, 0.0, 0.0])  # ~3 s of arm time at the rate limit
    code = main(["--port", str(sim.link), "move", *map(str, target), "--timeout", "0.2"])
    assert code == Exit.FAILED
    assert "timed out" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.sim(speed=1.0)  # a loop late by a period skips a tick: 50 ms of slack, not 12.5
def test_run_pid_reaches_the_target_and_leaves_the_arm_safe(
    sim, sim_port, tmp_path, capsys
) -> None:
    q0 = sim.snapshot().q
    target = q0 + np.array([0.5, -0.4, 0.4, 0.8])
    t0 = sim.sim_time
    record = tmp_path / "run.rrd"
    argv = ["--port", sim_port, "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    argv.append("--target")
    argv += [*map(str, target), "--seconds", "4", "--record", str(record)]
    code = main(argv)
    out = capsys.readouterr().out
    assert code == Exit.OK, out
    assert "zero_velocity" in out and "latency" in out
    # The loop counted 4 s of arm time (80 heartbeats at 20 Hz), whatever the speed-up.
    assert sim.sim_time - t0 >= 4.0
    assert np.max(np.abs(sim.snapshot().q - target)) < 0.02
    assert wait_until(
        lambda: all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in (5, 4, 3, 2)), timeout=10.0
    )
    from reach_driver.rrd_summary import summarize_recording

    summary: dict[str, Any] = summarize_recording(record)
    # Every step the loop took, and the state that ended the run. At 20 Hz that is 80 steps
    # plus one, less any state the stream superseded when the host fell behind (a busy core):
    # every tick is stepped on or counted, and most are stepped on.
    taken = int(re.search(r"run:\s+(\d+)\s+steps", out).group(1))  # type: ignore[union-attr]
    skipped = int(re.search(r"skipped\s+states\s+(\d+)", out).group(1))  # type: ignore[union-attr]
    assert summary["steps"] == taken + 1
    assert 80 - skipped <= taken <= 80 and taken >= 60
    assert np.max(np.abs(summary["final_error"])) < 0.02
    assert summary["metadata"]["controller"] == "pid"


def test_run_with_an_unknown_controller_names_the_registered_ones(sim, capsys) -> None:
    argv = ["--port", str(sim.link), "run", "--controller", "nope"]
    argv += ["--target", "3", "1.5", "1.5", "3", "--seconds", "1"]
    assert main(argv) == Exit.USAGE  # a typo in the command line, as in tools/evaluate.py
    err = capsys.readouterr().err
    assert "unknown controller 'nope'" in err and "pid" in err


def test_run_target_outside_the_limits_is_refused(sim, capsys) -> None:
    argv = ["--port", udp_url(sim), "run", "--controller", "pid"]
    argv += ["--target", "3", "1.5", "-0.5", "3", "--seconds", "1"]
    assert main(argv) == Exit.LIMIT
    assert "C (0x03)" in capsys.readouterr().err
    assert sim.firmware.mode(3) == Mode.STANDBY


def test_monitor_shows_states_rates_and_link_counters(sim, capsys) -> None:
    assert main(["--port", udp_url(sim), "monitor", "--seconds", "0.6"]) == Exit.OK
    out = capsys.readouterr().out
    assert "E (0x05)" in out and "standby" in out and "frames ok" in out


def test_wrong_port_says_so(tmp_path, capsys) -> None:
    assert main(["--port", str(tmp_path / "ttyUSB7"), "info"]) == Exit.NO_ARM
    assert "no such serial port" in capsys.readouterr().err


def test_nothing_answering_says_so(capsys) -> None:
    master, slave = os.openpty()
    try:
        code = main(["--port", os.ttyname(slave), "--timeout", "0.05", "info"])
    finally:
        os.close(master)
        os.close(slave)
    assert code == Exit.NO_ARM
    assert "nothing answered" in capsys.readouterr().err


def test_garbage_only_suggests_the_baud_rate(sim_factory, capsys) -> None:
    server = sim_factory(faults=FaultConfig(corrupt_rate=1.0))
    code = main(["--port", str(server.link), "--timeout", "0.05", "info"])
    assert code == Exit.NO_ARM
    assert "wrong baud rate" in capsys.readouterr().err


def test_some_garbage_on_the_line_is_counted_and_survived(sim_factory) -> None:
    server = sim_factory(faults=FaultConfig(corrupt_rate=0.002), seed=3)
    # a 0.5 s reply timeout: what is lost here is the damaged frames, not replies a loaded host
    # delivers after the default 0.1 s (six tries of 0.1 s ran out in a 0.6 s stall)
    with ArmClient(open_transport(str(server.link)), retries=5, request_timeout_s=0.5) as arm:
        for _ in range(40):
            arm.read_joints()
        assert arm.decoder_stats.bad_total > 0
        assert arm.decoder_stats.good_frames > 300
        assert not np.isnan(arm.state.q).any()


def _client(url: str, events: list) -> ArmClient:
    arm = ArmClient(
        open_transport(url),
        link=LinkConfig(stale_link_s=0.5, keepalive_s=0.1, backoff_max_s=0.4),
    )
    arm.on_event(events.append)
    return arm.start()


def test_link_lost_when_the_sim_restarts_is_reported_and_reopened(sim, sim_port) -> None:
    events: list = []
    arm = _client(sim_port, events)
    try:
        arm.stream((PacketID.POSITION,), 10, [DeviceID.E])
        sim.stop()
        assert wait_until(lambda: arm.link_state is not LinkState.UP, timeout=10.0)
        with pytest.raises(LinkDownError, match="nothing was sent"):
            arm.command_position(DeviceID.E, 3.0)
        with pytest.raises(LinkDownError):
            arm.request(DeviceID.E, [PacketID.POSITION])
        time.sleep(0.3)
        sim.start()  # the pty comes back under the same link, UDP on the same port
        assert wait_until(lambda: arm.link_state is LinkState.UP, timeout=10.0)
        # the link is UP before the reader thread has re-sent the stream set-up and emitted
        # LINK_UP: wait for the event rather than race it
        assert wait_until(lambda: EventKind.LINK_UP in [e.kind for e in events], timeout=5.0)
        assert EventKind.LINK_DOWN in [e.kind for e in events]
        assert arm.stats.reconnects == 1
        assert arm.request(DeviceID.D, [PacketID.MODE])[PacketID.MODE].as_u8() == Mode.STANDBY
        # Streaming set up before the restart was re-applied to the fresh arm.
        n = arm.table.counts.get((5, PacketID.POSITION), 0)
        assert wait_until(
            lambda: arm.table.counts.get((5, PacketID.POSITION), 0) > n + 3, timeout=10.0
        )
    finally:
        arm.close()


def test_losing_the_link_mid_control_leaves_the_arm_safe_on_reconnect(sim) -> None:
    events: list = []
    arm = _client(udp_url(sim), events)
    try:
        arm.read_joints()
        arm.command_current(DeviceID.D, 20.0)
        assert wait_until(lambda: sim.firmware.mode(4) == Mode.CURRENT, timeout=5.0)
        sim.stop()
        sim.start()  # the same firmware state: D still in current mode
        assert sim.firmware.mode(4) == Mode.CURRENT
        assert wait_until(lambda: sim.firmware.mode(4) == Mode.ZERO_VELOCITY, timeout=10.0)
        assert arm.tripped is not None
        assert any(e.kind is EventKind.WATCHDOG for e in events)
    finally:
        arm.close()


def test_watchdog_puts_the_arm_in_zero_velocity_when_the_controller_stops(sim) -> None:
    with ArmClient(open_transport(str(sim.link)), safety=SafetyConfig(watchdog_s=0.2)) as arm:
        arm.stream((PacketID.POSITION,), 50, [DeviceID.C])
        assert wait_until(lambda: arm.joint(DeviceID.C).position is not None, timeout=10.0)
        arm.command_current(DeviceID.C, 30.0)
        assert sim.firmware.mode(3) in (Mode.CURRENT, Mode.STANDBY)
        assert wait_until(lambda: sim.firmware.mode(3) == Mode.ZERO_VELOCITY, timeout=3.0)
        assert "no command" in (arm.tripped or "")


@pytest.mark.slow
def test_ctrl_c_during_run_leaves_the_arm_safe_and_exits_130(sim) -> None:
    target = sim.snapshot().q + np.array([0.2, 0.2, 0.2, 0.2])
    cmd = [sys.executable, "-m", "reach_driver.cli", "--port", udp_url(sim)]
    cmd += ["--watchdog", str(WATCHDOG_S), "run"]
    cmd += ["--controller", "pid", "--target", *map(str, target), "--seconds", "600"]
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=default_sigint
    )
    try:
        assert wait_until(lambda: sim.firmware.mode(5) == Mode.CURRENT, timeout=30.0)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == Exit.INTERRUPTED, err
    assert b"interrupted: by SIGINT; arm left in zero_velocity (confirmed by the arm)" in err
    assert all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in (5, 4, 3, 2))


def test_limits_written_to_the_arm_are_read_back_and_enforced(sim) -> None:
    from reach_driver import LimitError, LimitKind

    with ArmClient(open_transport(str(sim.link))) as arm:
        assert arm.write_limits(DeviceID.D, LimitKind.CURRENT, 400.0, -400.0) == (-400.0, 400.0)
        assert arm.guard.limit(DeviceID.D, LimitKind.CURRENT).high == 400.0
        assert sim.arm.current_limits_mA[1] == 400.0  # the arm itself took it
        arm.read_joints()
        with pytest.raises(LimitError, match=r"current 450 mA for joint D .*\[-400, 400\]"):
            arm.command_current(DeviceID.D, 450.0)
        sent = arm.command_velocities([0.1, -0.1, 0.0, 0.2])
        np.testing.assert_allclose(sent, [0.1, -0.1, 0.0, 0.2])
        assert wait_until(lambda: sim.firmware.mode(2) == Mode.VELOCITY, timeout=10.0)
        with pytest.raises(LimitError, match="velocity limit"):
            arm.command_velocity(DeviceID.E, 0.6)  # the firmware rate limit is 0.5236
        arm.safe_stop()


def test_a_link_error_flag_is_only_a_warning_for_move(sim, capsys) -> None:
    from protocol import Packet

    with ArmClient(open_transport(str(sim.link))) as arm:
        arm.write_frames_unchecked([Packet(DeviceID.D, PacketID.MODE, b"").encode()])  # bad payload
        assert wait_until(lambda: "SERIAL_ERROR" in arm.read_status().get(4, []), timeout=10.0)
    target = sim.snapshot().q + np.array([0.0, 0.1, 0.0, 0.0])
    assert main(["--port", str(sim.link), "move", *map(str, target)]) == Exit.OK
    out = capsys.readouterr().out
    assert "warning" in out and "SERIAL_ERROR" in out


class FaultyArm:
    """A minimal arm on UDP that answers REQUESTs from canned values; D reports a motor
    over-current (the emulator cannot be told to fake motor faults)."""

    def __init__(self) -> None:
        import socket
        import threading

        from protocol import HardwareStatus, Packet, PacketDecoder
        from protocol.payload import pack_floats

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.values: dict[tuple[int, int], bytes] = {}
        for dev in (5, 4, 3, 2):
            self.values[(dev, PacketID.MODE)] = bytes([Mode.STANDBY])
            self.values[(dev, PacketID.POSITION)] = pack_floats(1.5)
            self.values[(dev, PacketID.VELOCITY)] = pack_floats(0.0)
            self.values[(dev, PacketID.POSITION_LIMITS)] = pack_floats(3.4, 0.02)
            self.values[(dev, PacketID.VELOCITY_LIMITS)] = pack_floats(0.5, -0.5)
            self.values[(dev, PacketID.CURRENT_LIMITS)] = pack_floats(300.0, -300.0)
            status = HardwareStatus.MOTOR_OVER_CURRENT if dev == 4 else HardwareStatus.NONE
            self.values[(dev, PacketID.HARDWARE_STATUS)] = status.to_bytes()
        self.received: list[Packet] = []
        self._decoder = PacketDecoder()
        self._packet = Packet
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        host, port = self.sock.getsockname()
        return f"udp://{host}:{port}"

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, peer = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            out = b""
            for p in self._decoder.feed(data):
                self.received.append(p)
                if p.packet_id == PacketID.REQUEST:
                    for pid in p.data:
                        value = self.values.get((int(p.device_id), pid))
                        if value is not None:
                            out += self._packet(p.device_id, pid, value).encode()
            if out:
                self.sock.sendto(out, peer)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


def test_move_refuses_to_start_when_a_joint_reports_a_motor_fault(capsys) -> None:
    arm = FaultyArm()
    try:
        code = main(["--port", arm.url, "move", "1.5", "1.6", "1.5", "1.5"])
    finally:
        arm.close()
    assert code == Exit.FAILED
    assert "MOTOR_OVER_CURRENT" in capsys.readouterr().err
    assert not [p for p in arm.received if p.packet_id == PacketID.POSITION]


def test_info_names_the_status_flags_of_a_faulty_joint(capsys) -> None:
    arm = FaultyArm()
    try:
        assert main(["--port", arm.url, "info", "--json"]) == Exit.OK
    finally:
        arm.close()
    devices = json.loads(capsys.readouterr().out)["devices"]
    assert devices["D"]["status_flags"] == ["MOTOR_OVER_CURRENT"]
    assert devices["E"]["status_flags"] == []
    assert "A" not in devices  # the jaw never answered: not listed


def test_rs485_mode_talks_to_one_device_at_a_time(sim) -> None:
    with ArmClient(open_transport(str(sim.link), rs485=True)) as arm:
        assert arm.found_devices == (5, 4, 3, 2, 1)
        writes = arm.transport.stats.writes
        state = arm.read_joints()
        assert not np.isnan(state.q).any()
        assert arm.transport.stats.writes - writes == 4  # a REQUEST each, never a broadcast


def test_a_second_udp_client_taking_the_stream_is_named_and_the_arm_made_safe(sim) -> None:
    """A3-6: over UDP the arm streams to the last host that wrote to it, so a second client
    (here what `info` does: discover, identity, limits) takes the heartbeat of a running,
    stream-paced controller. Its watchdog must still make the arm safe, and say that another
    client took the stream rather than blame the controller or a dead link."""
    url = udp_url(sim)
    events: list = []
    with ArmClient(open_transport(url), safety=SafetyConfig(watchdog_s=0.2)) as arm:
        arm.on_event(events.append)

        def step(packet, t) -> None:  # noqa: ANN001 - a controller paced by the heartbeat
            if packet.key == (DeviceID.E, PacketID.POSITION) and arm.tripped is None:
                arm.command_current(DeviceID.C, 0.0)

        arm.subscribe(step)
        arm.stream((PacketID.POSITION, PacketID.VELOCITY), 50)
        assert wait_until(lambda: sim.firmware.mode(3) == Mode.CURRENT, timeout=10.0)
        with ArmClient(open_transport(url)) as other:  # `info`: reads only, then polls
            # A command of the controller's in flight may land after any one request of the
            # other client and take the stream back; while it keeps polling, it soon keeps it.
            assert wait_until(
                lambda: other.request(DeviceID.B, [PacketID.MODE]) and arm.tripped, timeout=10.0
            )
        assert wait_until(lambda: "another client" in (arm.tripped or ""), timeout=10.0), (
            arm.tripped
        )
        assert wait_until(lambda: sim.firmware.mode(3) == Mode.ZERO_VELOCITY, timeout=10.0)
        said = [e.message for e in events if e.kind is EventKind.WATCHDOG]
        assert any("took the stream" in m and "UDP" in m for m in said), said
        assert "no command" not in (arm.tripped or "")


def test_a_busy_host_that_did_not_read_the_udp_stream_is_not_blamed_on_another_client(
    sim,
) -> None:
    """A host too loaded to read the stream for longer than the watchdog trips it over UDP
    with no other client anywhere: the arm still answers the probe (it streams, to us), which
    was named "another client on this arm's UDP port took the stream". The trip says the
    machine was busy; the arm is made safe as ever. The stall is the reader's, simulated."""
    url = udp_url(sim)
    with ArmClient(open_transport(url), safety=SafetyConfig(watchdog_s=0.2)) as arm:

        def step(packet, t) -> None:  # noqa: ANN001 - a controller paced by the heartbeat
            if packet.key == (DeviceID.E, PacketID.POSITION) and arm.tripped is None:
                arm.command_current(DeviceID.C, 0.0)

        arm.subscribe(step)
        arm.stream((PacketID.POSITION, PacketID.VELOCITY), 50)
        assert wait_until(lambda: sim.firmware.mode(3) == Mode.CURRENT, timeout=10.0)
        read, stalled = arm.transport.read, list[bool]()

        def stalling_read() -> bytes:
            if not stalled:
                stalled.append(True)
                time.sleep(0.5)  # the host did not run this reader for 2.5 watchdogs
            return read()

        arm.transport.read = stalling_read  # type: ignore[method-assign]
        assert wait_until(lambda: arm.tripped is not None, timeout=10.0)
        assert wait_until(lambda: sim.firmware.mode(3) == Mode.ZERO_VELOCITY, timeout=10.0)
        # any answer to a probe comes before the answer to this later request
        arm.request(DeviceID.E, [PacketID.HEARTBEAT_FREQUENCY])
        tripped = arm.tripped or ""
    assert "another client" not in tripped and "took the stream" not in tripped, tripped
    assert "this process itself had not run" in tripped and "busy" in tripped, tripped


def test_info_over_udp_says_when_another_client_was_streaming(sim, capsys) -> None:
    """A3-6, the second client's side: `info` cannot avoid taking a UDP arm's stream (the
    arm streams to the last host that wrote to it), so it says it found one running."""
    url = udp_url(sim)
    with ArmClient(open_transport(url)) as arm:
        arm.stream((PacketID.POSITION,), 20, [DeviceID.E, DeviceID.D])
        assert wait_until(lambda: arm.joint(DeviceID.D).position is not None, timeout=10.0)
        assert main(["--port", url, "info", "--json"]) == Exit.OK
        captured = capsys.readouterr()
        json.loads(captured.out)  # the warning stays off stdout
        err = " ".join(captured.err.split())
        assert "E (0x05), D (0x04) streamed a heartbeat at 20 Hz" in err
        assert "One UDP arm serves one commanding client" in err
        arm.stop_stream()
    assert main(["--port", url, "info"]) == Exit.OK
    assert "streamed a heartbeat" not in capsys.readouterr().err
