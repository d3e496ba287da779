"""What the control loop streams must fit the link: on a 115200 baud line CURRENT, POSITION
and VELOCITY of four joints (120 B a state) fit 96 Hz, POSITION and VELOCITY (80 B) 144 Hz."""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest

from protocol import PacketID
from reach_driver import ArmClient, ControlLoop, ControlState, open_transport
from reach_driver.control import TELEMETRY, TELEMETRY_WITH_CURRENT, telemetry_fits
from reach_sim_bridge.emulator.server import SimConfig, SimServer

LINE = 115200 / 10  # bytes/s, 8N1


def test_telemetry_fits_the_wire_budget_arithmetic() -> None:
    assert telemetry_fits(TELEMETRY_WITH_CURRENT, 96, LINE)
    assert not telemetry_fits(TELEMETRY_WITH_CURRENT, 97, LINE)
    assert telemetry_fits(TELEMETRY, 144, LINE)
    assert not telemetry_fits(TELEMETRY, 145, LINE)
    assert telemetry_fits(TELEMETRY_WITH_CURRENT, 255, None)  # UDP, CAN: not the limit


class Zero:
    def reset(self) -> None:
        pass

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        return np.zeros(4)


@pytest.fixture
def slow_line(tmp_path: Path) -> Iterator[tuple[ArmClient, list[tuple[int, ...]]]]:
    server = SimServer(SimConfig(speed=2.0, link=str(tmp_path / "arm"), baud=115200))
    server.start()
    client = ArmClient(open_transport(str(server.link))).start()
    streamed: list[tuple[int, ...]] = []
    real_stream = client.stream

    def spy(ids: Sequence[int], hz: int, devices: Sequence[int]) -> int:
        streamed.append(tuple(int(i) for i in ids))  # what the loop asks the joints to stream
        return real_stream(ids, hz, devices)

    # a spy in the method's place (the loop passes every argument: no defaults needed)
    client.stream = spy  # type: ignore[method-assign, assignment]
    yield client, streamed
    client.close()
    server.stop()
    assert server.error is None


def test_a_rate_the_line_cannot_carry_with_current_streams_without_it(slow_line, caplog) -> None:
    client, streamed = slow_line
    q = client.read_joints((PacketID.POSITION, PacketID.VELOCITY)).q
    with caplog.at_level(logging.WARNING, logger="reach_driver.control"):
        summary = ControlLoop(client, Zero(), 1 / 120).run(q, 0.3)
    assert summary.ok, summary.error
    assert streamed == [tuple(int(i) for i in TELEMETRY)]
    assert "120 Hz exceeds the line with CURRENT" in caplog.text
    assert summary.trace is not None and np.isnan(summary.trace.current_mA[1:]).all()


def test_a_rate_that_fits_keeps_the_measured_current(slow_line) -> None:
    client, streamed = slow_line
    q = client.read_joints((PacketID.POSITION, PacketID.VELOCITY)).q
    summary = ControlLoop(client, Zero(), 1 / 50).run(q, 0.3)
    assert summary.ok, summary.error
    assert streamed == [tuple(int(i) for i in TELEMETRY_WITH_CURRENT)]


def test_a_heartbeat_the_line_cannot_carry_is_capped_and_said(slow_line, caplog) -> None:
    client, _ = slow_line
    ids = (PacketID.POSITION, PacketID.VELOCITY, PacketID.CURRENT, PacketID.MODE)
    devices = (5, 4, 3, 2, 1)
    with caplog.at_level(logging.WARNING, logger="reach_driver.client"):
        hz = client.stream(ids, 255, devices)
    # 5 devices x (3 float replies of 10 B + a MODE reply of 7 B) = 185 B a beat: 62 Hz.
    assert hz == int(LINE // 185) == 62
    assert "streaming at 62 Hz" in caplog.text
    assert client.stream(ids, 20, devices) == 20  # what fits is left alone
    client.stop_stream()


def test_a_stream_that_cannot_fit_even_at_1_hz_is_refused(slow_line) -> None:
    from reach_driver import LimitError
    from reach_driver.streaming import Stream

    client, _ = slow_line
    assert Stream((PacketID.POSITION,), 1, (5,)).bytes_per_beat() == 10
    client.transport.baud = 50  # 5 B/s: not even one reply a second (the estimate only)
    with pytest.raises(LimitError, match="even at 1 Hz"):
        client.stream((PacketID.POSITION,), 1, (5,))
