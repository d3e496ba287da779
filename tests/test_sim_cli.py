"""The `reach-sim` command: options, output, serving, and clean shutdown on signals."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from protocol import DeviceID, Packet, PacketDecoder, PacketID, commands
from reach_sim_bridge.cli import build_parser, config_from_args, main
from reach_sim_bridge.model.sensors import SensorNoise

WALL_LIMIT_S = 30.0
CLI = [sys.executable, "-m", "reach_sim_bridge.cli"]


def parse(*argv: str):  # noqa: ANN201
    return config_from_args(build_parser().parse_args(list(argv)))


def test_help_explains_every_option(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in (
        "--link",
        "--udp",
        "--no-pty",
        "--speed",
        "--baud",
        "--start",
        "--torque-scale",
        "--sensor-noise",
        "--randomize-params",
        "--corrupt-rate",
        "--drop-rate",
        "--latency-ms",
        "--seed",
        "--stats-interval",
    ):
        assert option in text
    assert "127.0.0.1:6789" in text and "SIGTERM" in text


def test_options_build_the_config() -> None:
    config = parse(
        "--udp",
        "--speed",
        "5",
        "--baud",
        "115200",
        "--torque-scale",
        "E=0.25",
        "--torque-scale",
        "b=0.5",
        "--sensor-noise",
        "--drop-rate",
        "0.1",
        "--corrupt-rate",
        "0.01",
        "--latency-ms",
        "4",
        "--randomize-params",
        "7",
        "--start",
        "1.0",
        "0.5",
        "2.0",
        "4.0",
        "--link",
        "/tmp/x",
    )
    assert config.udp == ("127.0.0.1", 6789)
    assert config.speed == 5.0 and config.baud == 115200 and config.link == "/tmp/x"
    assert config.faults.torque_scale == (0.25, 1.0, 1.0, 0.5)
    assert config.faults.sensor_noise == SensorNoise()
    assert (config.faults.drop_rate, config.faults.corrupt_rate) == (0.1, 0.01)
    assert config.faults.latency_ms == 4.0 and config.faults.randomize_seed == 7
    assert config.start == (1.0, 0.5, 2.0, 4.0)
    assert parse().udp is None and parse().pty
    assert parse("--udp", "9000").udp == ("127.0.0.1", 9000)
    assert parse("--udp", "0.0.0.0:6790").udp == ("0.0.0.0", 6790)
    assert parse("--sensor-noise", "0.01,0.05").faults.sensor_noise == SensorNoise(0.01, 0.05)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--speed", "0"], "must be > 0"),
        (["--drop-rate", "1.5"], "probability"),
        (["--udp", "host:port"], "port must be a number"),
        (["--torque-scale", "F=0.5"], "JOINT one of E D C B"),
        (["--torque-scale", "E=2"], "must be in [0, 1]"),
        (["--no-pty"], "nothing to serve"),
        (["--start", "1", "9", "2", "4"], "outside the joint ranges"),
        (["--baud", "fast"], "whole number"),
    ],
)
def test_bad_options_are_refused_with_a_clear_message(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def _start(*argv: str) -> tuple[subprocess.Popen[str], dict[str, str]]:
    proc = subprocess.Popen(
        [*CLI, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    lines: dict[str, str] = {}
    wanted = (
        {"pty"}
        | ({"link"} if "--link" in argv else set())
        | ({"udp"} if "--udp" in argv else set())
    )
    while not wanted <= lines.keys():
        line = proc.stdout.readline()
        assert line, f"reach-sim exited early: {proc.wait()} {proc.stderr.read()}"  # type: ignore[union-attr]
        key, _, value = line.strip().partition(" ")
        lines[key] = value
    return proc, lines


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_serves_pty_link_and_udp_then_stops_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    link = tmp_path / "alpha5"
    proc, lines = _start("--link", str(link), "--udp", "127.0.0.1:0", "--speed", "5")
    try:
        assert lines["link"] == str(link) and os.readlink(link) == lines["pty"]
        request = commands.request(DeviceID.D, [PacketID.SERIAL_NUMBER]).encode()
        with serial.Serial(str(link), 115200, timeout=0.05) as port:
            port.write(request)
            decoder = PacketDecoder()
            got: list[Packet] = []
            deadline = time.monotonic() + WALL_LIMIT_S
            while not got:
                assert time.monotonic() < deadline
                got = decoder.feed(port.read(64))
        assert got[0].key == (DeviceID.D, PacketID.SERIAL_NUMBER)
        host, _, port_text = lines["udp"].rpartition(":")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(WALL_LIMIT_S)
            sock.sendto(request, (host, int(port_text)))
            data, _ = sock.recvfrom(65535)
        assert PacketDecoder().feed(data) == got
    finally:
        proc.send_signal(sig)
        code = proc.wait(timeout=WALL_LIMIT_S)
    assert code == 0
    assert not link.is_symlink()


def test_link_onto_a_real_file_fails_without_touching_it(tmp_path: Path) -> None:
    precious = tmp_path / "notes.txt"
    precious.write_text("keep")
    result = subprocess.run(
        [*CLI, "--link", str(precious)], capture_output=True, text=True, timeout=WALL_LIMIT_S
    )
    assert result.returncode == 1
    assert "not a symlink" in result.stderr
    assert precious.read_text() == "keep"


def test_reach_sim_is_quiet_by_default_and_says_its_version() -> None:
    assert build_parser().parse_args([]).stats_interval is None  # main(): never; 10 s with -v
    proc = subprocess.run(
        [sys.executable, "-m", "reach_sim_bridge", "--version"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0 and proc.stdout.startswith("reach-sim ")
