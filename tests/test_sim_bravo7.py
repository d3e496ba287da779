"""`reach-sim --arm bravo7`: the virtual Reach Bravo 7 over a real pty and UDP, with only the
codec (and, last, the driver given the Bravo's model).

Written from the facts (protocol/bravo7.py, reach_sim_bridge/model/bravo7.md): devices 0x01
(jaws) to 0x07 (base yaw G) and the base's router 0x0D, which reports the wrist's
force-torque sensor as FORCE_TORQUE (0xD8): six float32, force (N) then torque (N m) in the
sensor's frame (z along the wrist axis towards the jaws), tared by six zeros written to it.
The jaws (link 7) weigh 0.64 kg with their centre of mass at (1, 1, 0) mm in the flange frame
and displace 0.16 L centred at (1, -27, 0) mm; the push rod, 0.1 g, at (0, -10, 0) mm.

Waits are bounded by the arm's time read from the server; the wall-clock limits only turn a
broken server into a failure instead of a hang.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import serial
from conftest import LOOPBACK, WATCHDOG_S, SimFactory

from protocol import DeviceID, HardwareStatus, Mode, Packet, PacketDecoder, PacketID, commands
from protocol.models import ALPHA5, BRAVO7
from reach_driver import ArmClient
from reach_driver.interfaces import open_transport
from reach_driver.safety import LimitKind, SafetyConfig
from reach_sim_bridge.cli import build_parser, config_from_args, main
from reach_sim_bridge.emulator.faults import Leak
from reach_sim_bridge.emulator.firmware import Firmware
from reach_sim_bridge.emulator.server import SimConfig, SimServer
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.bravo7 import Bravo7Arm
from reach_sim_bridge.model.params import ArmParams

A, B, C, D, E, F, G = (DeviceID(i) for i in range(1, 8))
ROUTER = DeviceID.ROUTER
BROADCAST = DeviceID.BROADCAST
JOINTS = (G, F, E, D, C, B)  # base to tip, as the Bravo's arrays are
WALL_LIMIT_S = 30.0
GRAVITY = 9.81
WATER = 1000.0  # kg/m^3: the virtual Bravo is in fresh water

pytestmark = pytest.mark.sim(model=BRAVO7, udp=LOOPBACK, speed=4.0)


class Client:
    """A host on the pty or UDP with nothing but the codec."""

    def __init__(self, server: SimServer, kind: str) -> None:
        self.server = server
        self.decoder = PacketDecoder()
        self.backlog: list[Packet] = []
        self.port: serial.Serial | None = None
        self.sock: socket.socket | None = None
        if kind == "pty":
            assert server.pty_path is not None
            self.port = serial.Serial(server.pty_path, 115200, timeout=0.02)
        else:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.settimeout(0.02)

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
        if self.sock is not None:
            self.sock.close()

    def send(self, *packets: Packet) -> None:
        data = b"".join(p.encode() for p in packets)
        if self.port is not None:
            self.port.write(data)
            self.port.flush()
        else:
            assert self.sock is not None and self.server.udp_address is not None
            self.sock.sendto(data, self.server.udp_address)

    def _read(self) -> list[Packet]:
        if self.port is not None:
            return self.decoder.feed(self.port.read(self.port.in_waiting or 1))
        assert self.sock is not None
        try:
            data, _ = self.sock.recvfrom(65535)
        except TimeoutError:
            return []
        return self.decoder.feed(data)

    def collect(self, done: Callable[[list[Packet]], bool]) -> list[Packet]:
        got, self.backlog = self.backlog, []
        deadline = time.monotonic() + WALL_LIMIT_S
        while not done(got):
            assert time.monotonic() < deadline, f"no complete answer; got {got}"
            got.extend(self._read())
        return got

    def ask(self, device: int, *ids: int) -> list[Packet]:
        """One REQUEST; the replies it asks for, in order (other traffic kept for later; the
        same packets sent unprompted before it are dropped as stale)."""
        wanted = [(int(device), int(pid)) for pid in ids]
        while arrived := self._read():
            self.backlog.extend(arrived)
        self.backlog = [p for p in self.backlog if p.key not in wanted]
        self.send(commands.request(device, ids))
        got = self.collect(lambda ps: all(any(p.key == w for p in ps) for w in wanted))
        replies = [next(p for p in got if p.key == w) for w in wanted]
        self.backlog = [p for p in got if p not in replies]
        return replies

    def value(self, device: int, pid: int) -> float:
        return self.ask(device, pid)[0].as_float()

    def force_torque(self) -> np.ndarray:
        reply = self.ask(ROUTER, PacketID.FORCE_TORQUE)[0]
        assert len(reply.data) == 24
        return np.array(reply.floats())

    def wait_sim(self, seconds: float) -> None:
        assert self.server.wait_sim_time(self.server.sim_time + seconds, timeout=WALL_LIMIT_S)


@pytest.fixture(params=["pty", "udp"])
def client(request: pytest.FixtureRequest, sim: SimServer) -> Iterator[Client]:
    c = Client(sim, request.param)
    yield c
    c.close()


def jaws_load(server: SimServer) -> np.ndarray:
    """What the sensor should read with the arm at rest, by hand from the jaws' datasheet
    figures: weight and buoyancy at their centres, in the sensor frame (x_s = x7, y_s = z7,
    z_s = -y7 of the flange frame), torque about its origin. Only the sensor's orientation
    is read from the arm (where the gravity points)."""
    rotation, jaw_m = server.observe(
        lambda arm, _fw: (arm.data.site("ft").xmat.reshape(3, 3).copy(), arm.jaw_mm / 1000.0)
    )
    down = rotation.T @ np.array([0.0, 0.0, -GRAVITY])  # gravity in the sensor frame

    def in_sensor(x7: float, y7: float, z7: float) -> np.ndarray:
        return np.array([x7, z7, -y7])

    loads = (
        (0.64 * down, in_sensor(0.001, 0.001, 0.0)),  # the jaws' weight
        (-WATER * 0.16e-3 * down, in_sensor(0.001, -0.027, 0.0)),  # their buoyancy
        (1e-4 * down, in_sensor(0.0, -0.010 - jaw_m, 0.0)),  # the push rod
    )
    force = sum(f for f, _ in loads)
    torque = sum(np.cross(r, f) for f, r in loads)
    return np.concatenate([force, torque])


def settle(client: Client, device: int, target: float) -> None:
    """Command a position and wait (arm time) until the joint is there and still."""
    client.send(commands.position(device, target))
    start = client.server.sim_time
    while abs(client.value(device, PacketID.POSITION) - target) > 0.005 or (
        abs(client.value(device, PacketID.VELOCITY)) > 0.002
    ):
        assert client.server.sim_time - start < 10.0, f"{device!r} did not reach {target}"
        client.wait_sim(0.1)
    client.wait_sim(0.5)


# -- the devices -------------------------------------------------------------------------------
def test_all_seven_devices_answer_their_positions(client: Client) -> None:
    client.wait_sim(1.0)  # the joints held still where they started
    client.send(commands.request(BROADCAST, [PacketID.POSITION]))
    replies = client.collect(lambda ps: len({p.device_id for p in ps}) >= 7)
    truth = client.server.snapshot()
    by_device = {int(p.device_id): p.as_float() for p in replies}
    assert sorted(by_device) == [1, 2, 3, 4, 5, 6, 7]  # the router has no position
    for device, q in zip(JOINTS, truth.q, strict=True):
        assert by_device[device] == pytest.approx(q, abs=0.002)
        assert client.value(device, PacketID.POSITION) == pytest.approx(q, abs=0.002)
    assert by_device[A] == pytest.approx(truth.jaw_mm, abs=0.01)
    # the router answers for itself, not for a joint
    ident = client.ask(ROUTER, PacketID.DEVICE_ID, PacketID.MODEL_NUMBER, PacketID.VOLTAGE)
    assert ident[0].data == bytes([0x0D]) and ident[1].as_float() == 7007.0
    assert 20.0 < ident[2].as_float() <= 24.0
    for device in (*JOINTS, A):
        hi, lo = client.ask(device, PacketID.POSITION_LIMITS)[0].floats()
        assert (lo, hi) == pytest.approx(BRAVO7.position_limits[device], abs=1e-6)
        current = client.ask(device, PacketID.CURRENT_LIMITS)[0].floats()
        assert current == [BRAVO7.current_limits[device][1], BRAVO7.current_limits[device][0]]


def test_position_velocity_and_current_commands_move_the_named_joint(client: Client) -> None:
    before = client.server.snapshot().q
    settle(client, F, 2.0)  # the shoulder, against gravity and the datasheet friction
    after = client.server.snapshot().q
    assert after[1] == pytest.approx(2.0, abs=0.005)
    others = [0, 2, 3, 4, 5]
    np.testing.assert_allclose(after[others], before[others], atol=0.01)

    client.send(commands.velocity(E, -0.2))
    client.wait_sim(0.5)
    assert client.value(E, PacketID.VELOCITY) == pytest.approx(-0.2, abs=0.01)
    # Each reading is taken at an arm time inside its request's bracket, which a loaded host
    # widens, so the move is checked against the arm time that can have passed between them.
    t0 = client.server.sim_time
    start = client.value(E, PacketID.POSITION)
    t1 = client.server.sim_time
    client.wait_sim(1.0)
    t2 = client.server.sim_time
    moved = client.value(E, PacketID.POSITION) - start
    t3 = client.server.sim_time
    assert t2 - t1 >= 1.0
    assert -0.2 * (t3 - t0) - 0.015 <= moved <= -0.2 * (t2 - t1) + 0.015
    assert client.ask(E, PacketID.MODE)[0].u8s() == [Mode.VELOCITY]
    client.send(commands.mode(E, Mode.ZERO_VELOCITY))

    start = client.value(C, PacketID.POSITION)
    client.send(commands.current(C, 1000.0))  # 25.8 N m against 9.5 of friction: it turns up
    client.wait_sim(0.3)
    assert client.value(C, PacketID.CURRENT) == pytest.approx(1000.0, abs=1.0)
    assert client.value(C, PacketID.POSITION) - start > 0.05
    client.send(commands.current(C, 5000.0))  # beyond C's 1500 mA: saturated there
    client.wait_sim(0.05)
    applied = client.server.observe(lambda _arm, fw: fw.setpoints(C)[2])
    assert applied == 1500.0 and client.value(C, PacketID.CURRENT) <= 1500.0
    client.send(commands.mode(C, Mode.ZERO_VELOCITY))


# -- the force-torque sensor ---------------------------------------------------------------------
def test_force_torque_reads_the_jaws_load_follows_the_pose_and_tares_to_zero(
    client: Client,
) -> None:
    client.wait_sim(1.0)  # at rest, held
    reading = client.force_torque()
    expected = jaws_load(client.server)
    np.testing.assert_allclose(reading[:3], expected[:3], atol=0.02)  # N
    np.testing.assert_allclose(reading[3:], expected[3:], atol=0.002)  # N m
    assert np.linalg.norm(reading[:3]) == pytest.approx(
        (0.64 + 1e-4 - WATER * 0.16e-3) * GRAVITY, rel=0.01
    )

    settle(client, C, 2.4)  # the wrist pitches: the load turns in the sensor frame
    turned = client.force_torque()
    np.testing.assert_allclose(turned[:3], jaws_load(client.server)[:3], atol=0.02)
    assert np.linalg.norm(turned[:3] - reading[:3]) > 1.0

    client.send(commands.force_torque_tare(ROUTER))
    client.wait_sim(0.1)
    np.testing.assert_allclose(client.force_torque(), np.zeros(6), atol=0.01)

    settle(client, C, 1.6)  # back: the tared sensor reads the change from the tare's pose
    np.testing.assert_allclose(client.force_torque()[:3], reading[:3] - turned[:3], atol=0.03)

    # only six zeros may be written, and only to the router
    client.send(Packet(ROUTER, PacketID.FORCE_TORQUE, bytes(23)))
    client.send(commands.force_torque_tare(F))
    client.wait_sim(0.1)
    stats = client.server.stats()
    assert stats.firmware_errors.get("bad_payload") == 1
    assert stats.ignored.get("no_force_torque_sensor") == 1
    assert client.ask(F, PacketID.POSITION)  # the arm answers on


def test_the_twins_reading_is_the_jaws_weight_in_air() -> None:
    arm = Bravo7Arm(water_density=0.0)
    arm.reset(q=[1.0, 1.6, 1.6, 0.3, 1.0, 0.5])
    arm.data.qacc[:] = 0.0  # at rest: no inertial load
    reading = arm.force_torque()
    rotation = arm.data.site("ft").xmat.reshape(3, 3)
    down = rotation.T @ np.array([0.0, 0.0, -GRAVITY])
    np.testing.assert_allclose(reading[:3], (0.64 + 1e-4) * down, atol=1e-9)
    jaws = np.cross([0.001, 0.0, -0.001], 0.64 * down)
    rod = np.cross([0.0, 0.0, 0.010 + arm.jaw_mm / 1000.0], 1e-4 * down)
    np.testing.assert_allclose(reading[3:], jaws + rod, atol=1e-9)


def test_a_bravo_sim_recording_is_the_bravo_and_reads_back_with_inspect(
    sim: SimServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from reach_driver.cli import Exit
    from reach_driver.cli import main as driver
    from reach_driver.rrd_summary import read_recording
    from reach_sim_bridge.emulator.recording import SimRecorder, drawn_bodies

    path = tmp_path / "bravo.rrd"
    recorder = SimRecorder(sim, path, rate_hz=50.0)
    recorder.start()
    client = Client(sim, "pty")
    try:
        start = sim.snapshot().q
        client.send(commands.position(F, start[1] + 0.3))
        client.wait_sim(1.5)
    finally:
        client.close()
        truth = sim.snapshot()
        recorder.stop()
    # the MJCF's own links are drawn: base, the six links, the jaws' housing and fingers
    model = sim.arm.model  # its bodies' names: fixed at load
    names = [model.body(b).name for b in drawn_bodies(model)]
    assert names == [*(f"link{i}" for i in range(8)), "jaw"]
    run = read_recording(path)
    assert run.metadata["arm"] == "bravo7" and run.model is BRAVO7
    assert run.q.shape[1] == 6 and len(run.step) >= 40
    assert run.q[0, 1] == pytest.approx(start[1], abs=0.01)  # F, from where it was
    assert run.q[-1, 1] == pytest.approx(truth.q[1], abs=0.05) and run.q[-1, 1] > start[1] + 0.2
    assert np.nanmax(run.target[:, 1]) == pytest.approx(start[1] + 0.3, abs=1e-6)
    assert driver(["inspect", str(path), "--json"]) == Exit.OK
    summary = json.loads(capsys.readouterr().out)
    assert summary["kind"] == "simulator" and summary["arm"] == "bravo7"
    assert summary["joints"] == ["G", "F", "E", "D", "C", "B"]
    assert summary["final_modes"][1] == "position"
    assert summary["final_position"][1] == pytest.approx(truth.q[1], abs=0.05)


def test_reach_sim_records_the_bravo(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from conftest import recorded_steps, wait_until

    from reach_driver.cli import Exit
    from reach_driver.cli import main as driver

    path = tmp_path / "cli.rrd"
    cli = [sys.executable, "-m", "reach_sim_bridge.cli", "--arm", "bravo7", "--speed", "4"]
    proc = subprocess.Popen(
        [*cli, "--record", str(path), "--stats-interval", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("pty "), proc.stderr
        assert wait_until(lambda: len(recorded_steps(path)) >= 10, timeout=WALL_LIMIT_S)
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=WALL_LIMIT_S)
    assert proc.returncode == 0, err
    assert f"recording {path}" in out
    assert driver(["inspect", str(path)]) == Exit.OK
    said = capsys.readouterr().out
    assert "simulator recording" in said and "final true state of the Reach Bravo 7" in said
    table = [line.split() for line in said.splitlines()]
    rows = [cells[0] for cells in table if len(cells) == 4 and cells[1] == "standby"]
    assert rows == ["G", "F", "E", "D", "C", "B"], said


def test_the_alpha_still_knows_no_force_torque_packet() -> None:
    fw = Firmware(Alpha5Arm())
    assert fw.handle(commands.force_torque_tare(E)) == []
    assert fw.handle(commands.request(E, [PacketID.FORCE_TORQUE])) == []
    assert fw.errors.snapshot() == {"unknown_packet": 1}
    assert fw.ignored.snapshot() == {"unsupported_request": 1}


# -- the line, the faults and the climate, as for the Alpha -------------------------------------
def test_half_duplex_broadcast_answers_collide_and_single_ones_arrive(
    sim_factory: SimFactory,
) -> None:
    server = sim_factory(model=BRAVO7, baud=115200, half_duplex=True)
    client = Client(server, "pty")
    try:
        client.send(commands.request(BROADCAST, [PacketID.POSITION]))
        client.wait_sim(0.5)
        arrived = [*client._read(), *client._read()]
        assert [p for p in arrived if p.packet_id == PacketID.POSITION] == []
        assert server.stats().ignored.get("broadcast_collision") == 1
        assert client.value(G, PacketID.POSITION) == pytest.approx(server.snapshot().q[0], abs=0.01)
        assert client.force_torque().shape == (6,)
    finally:
        client.close()


def test_faults_and_climate_as_for_the_alpha(client: Client) -> None:
    server = client.server
    for device in (*JOINTS, A, ROUTER):
        temperature, humidity, pressure, volts = (
            p.as_float()
            for p in client.ask(
                device,
                PacketID.TEMPERATURE,
                PacketID.HUMIDITY,
                PacketID.PRESSURE,
                PacketID.VOLTAGE,
            )
        )
        assert 15.0 < temperature < 40.0 and humidity == pytest.approx(10.0, abs=1.0)
        assert 0.9 < pressure < 1.2 and 20.0 < volts <= 24.0
    server.inject_fault(F, HardwareStatus.MOTOR_DRIVER_FAULT)
    status = client.collect(lambda ps: any(p.key == (F, PacketID.HARDWARE_STATUS) for p in ps))
    flags = next(p for p in status if p.key == (F, PacketID.HARDWARE_STATUS))
    assert HardwareStatus.from_bytes(flags.data) == HardwareStatus.MOTOR_DRIVER_FAULT
    server.observe(lambda _arm, fw: fw.inject_leak(Leak(int(ROUTER), time_constant_s=2.0)))
    client.wait_sim(3.0)
    leak = HardwareStatus.from_bytes(client.ask(ROUTER, PacketID.HARDWARE_STATUS)[0].data)
    assert HardwareStatus.OVER_HUMIDITY in leak


def _parse(*argv: str):  # noqa: ANN202
    """The SimConfig `reach-sim argv` serves."""
    return config_from_args(build_parser().parse_args(list(argv)))


def test_options_for_the_bravo_and_the_alpha_stays_the_default(
    sim_factory: SimFactory, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _parse().model is ALPHA5 and _parse("--udp").udp == ("127.0.0.1", 6789)
    config = _parse("--arm", "bravo7", "--udp", "--torque-scale", "G=0.25", "--sensor-noise")
    assert config.model is BRAVO7 and config.udp == ("127.0.0.1", 6789)
    assert config.faults.torque_scale == (0.25, 1.0, 1.0, 1.0, 1.0, 1.0)
    start = (1.0, 1.5, 1.5, 3.0, 1.5, 3.0)
    config = _parse("--arm", "bravo7", "--no-pty", "--udp", "0", "--start", *map(str, start))
    assert config.start == start
    server = sim_factory(config=config)
    np.testing.assert_allclose(server.snapshot().q, start, atol=0.01)
    noisy = sim_factory(model=BRAVO7, udp=LOOPBACK, faults=_parse("--sensor-noise").faults)
    client = Client(noisy, "udp")
    try:
        readings = {client.value(E, PacketID.POSITION) for _ in range(4)}
        assert len(readings) > 1  # noise on what is reported
    finally:
        client.close()
    scaled = sim_factory(config=_parse("--arm", "bravo7", "--torque-scale", "d=0.5"))
    assert scaled.arm.torque_scale.tolist() == [1.0, 1.0, 1.0, 0.5, 1.0, 1.0]
    for argv, message in (
        (["--arm", "bravo7", "--start", "1", "1", "1", "1"], "takes 6 angles (G F E D C B)"),
        (["--arm", "bravo7", "--torque-scale", "X=1"], "JOINT one of G F E D C B"),
        (["--arm", "bravo5"], "invalid choice"),
        (["--start", "1", "1", "1", "1", "1", "1"], "takes 4 angles (E D C B)"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err


# -- an identified Bravo (--params) and a perturbed one (--randomize-params) ---------------------
def test_the_nominal_bravo_as_parameters_is_its_mjcf() -> None:
    """`ArmParams` of the nominal Bravo, applied, leave the MJCF's model as it was written."""
    from reach_sim_bridge.model.bravo7 import load

    for water, drag in ((WATER, True), (0.0, True), (1025.0, False)):
        written, arm = load(water, drag), Bravo7Arm(water_density=water, fluid_drag=drag)
        for name in ("dof_armature", "dof_damping", "dof_frictionloss", "body_mass"):
            # to the last bit but one: the lift's litres x density summed in another order
            np.testing.assert_allclose(getattr(arm.model, name), getattr(written, name), rtol=1e-12)
        np.testing.assert_allclose(arm.model.body_inertia, written.body_inertia, rtol=1e-12)
        assert (arm.model.opt.density, arm.model.opt.viscosity) == (
            written.opt.density,
            written.opt.viscosity,
        )
        assert arm.params.n_joints == 6 and arm.params.water_density == water


def test_reach_sim_serves_the_bravo_a_params_file_describes(
    sim_factory: SimFactory, tmp_path: Path
) -> None:
    from reach_sim_bridge.model.bravo7 import gravity_torque, load

    nominal = Bravo7Arm.nominal()
    friction = list(nominal.frictionloss)
    friction[1] *= 2.0  # F's
    path = tmp_path / "bravo.json"
    path.write_text(json.dumps({"water_density": 0.0, "frictionloss": friction, "_fit": {}}))
    config = _parse("--arm", "bravo7", "--params", str(path), "--no-pty", "--udp", "0")
    assert config.params is not None and config.params.frictionloss == tuple(friction)
    server = sim_factory(config=config)
    arm = server.arm
    assert arm.model.dof_frictionloss[1] == pytest.approx(friction[1])
    np.testing.assert_array_equal(arm.model.dof_armature[:6], nominal.armature)  # the rest nominal
    # in air: the weight the MJCF's links have out of the water, no lift
    q = np.array([1.0, 1.2, 1.9, 2.5, 1.4, 0.7])
    # (to 0.1 mN m: the jaws stand 5 mm open here, shut there, moving their 0.1 g push rod)
    np.testing.assert_allclose(arm.gravity_torque(q), gravity_torque(load(0.0), q), atol=1e-4)
    assert not np.allclose(arm.gravity_torque(q), gravity_torque(load(WATER), q), atol=0.1)
    client = Client(server, "udp")  # and it is served
    try:
        assert client.value(F, PacketID.POSITION) == pytest.approx(server.snapshot().q[1], abs=0.01)
    finally:
        client.close()


def test_randomize_params_perturbs_the_bravo_around_its_nominal_arm(
    sim_factory: SimFactory,
) -> None:
    nominal = Bravo7Arm.nominal()
    drawn = []
    for _ in range(2):
        config = _parse("--arm", "bravo7", "--randomize-params", "3", "--no-pty", "--udp", "0")
        drawn.append(sim_factory(config=config).arm.params)
    first = drawn[0]
    assert first == drawn[1]  # the seed decides the arm
    for name in ("armature", "damping", "frictionloss", "link_mass_kg", "link_volume_l"):
        ratio = np.asarray(getattr(first, name)) / np.asarray(getattr(nominal, name))
        assert len(ratio) == 6 and np.all(np.abs(ratio - 1.0) <= 0.2 + 1e-12), name
        assert np.any(np.abs(ratio - 1.0) > 0.01), name  # perturbed, per joint
    for name in ("current_limits_mA", "torque_scale", "supply_voltage", "motors"):
        assert getattr(first, name) == getattr(nominal, name), name


def test_a_params_file_of_the_other_arm_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    alpha = tmp_path / "alpha.json"
    alpha.write_text('{"frictionloss": [0.7, 0.7, 0.7, 0.075]}')
    bravo = tmp_path / "bravo.json"
    bravo.write_text(json.dumps({"motors": {"gear_ratio": [120.0] * 6}}))
    for argv, message in (
        (
            ["--arm", "bravo7", "--params", str(alpha)],
            f"{alpha}: describes an arm of 4 joints (E D C B: a Reach Alpha 5), not a "
            "Reach Bravo 7 (6 joints G F E D C B)",
        ),
        (
            ["--params", str(bravo)],
            f"{bravo}: describes an arm of 6 joints (G F E D C B: a Reach Bravo 7), not a "
            "Reach Alpha 5 (4 joints E D C B)",
        ),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert err.splitlines()[-1] == f"reach-sim: error: {message}", err
        assert "Traceback" not in err
    with pytest.raises(ValueError, match="describe a Reach Alpha 5, not the Reach Bravo 7"):
        SimServer(SimConfig(model=BRAVO7, params=ArmParams()))


def test_reach_sim_serves_the_bravo_on_a_pty_and_udp(tmp_path: Path) -> None:
    link = tmp_path / "bravo7"
    cli = [sys.executable, "-m", "reach_sim_bridge.cli", "--arm", "bravo7", "--speed", "4"]
    proc = subprocess.Popen(
        [*cli, "--link", str(link), "--udp", "127.0.0.1:0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        lines: dict[str, str] = {}
        while not {"pty", "link", "udp"} <= lines.keys():
            line = proc.stdout.readline()
            assert line, f"reach-sim exited early: {proc.wait()}"
            key, _, value = line.strip().partition(" ")
            lines[key] = value
        host, port = lines["udp"].rsplit(":", 1)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(WALL_LIMIT_S)
            sock.sendto(
                commands.request(ROUTER, [PacketID.FORCE_TORQUE]).encode(), (host, int(port))
            )
            reply = PacketDecoder().feed(sock.recvfrom(65535)[0])
        assert [(p.key, len(p.floats())) for p in reply] == [((ROUTER, PacketID.FORCE_TORQUE), 6)]
        with serial.Serial(str(link), 115200, timeout=WALL_LIMIT_S) as port_:
            port_.write(commands.request(G, [PacketID.POSITION]).encode())
            decoder, got = PacketDecoder(), list[Packet]()
            deadline = time.monotonic() + WALL_LIMIT_S
            while not got and time.monotonic() < deadline:
                got = decoder.feed(port_.read(port_.in_waiting or 1))
        assert got and got[0].key == (G, PacketID.POSITION)
        assert got[0].as_float() == pytest.approx(np.pi, abs=0.01)  # mid-range of 0..2 pi
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(WALL_LIMIT_S) == 0


# -- the driver, given the Bravo's model ---------------------------------------------------------
def test_the_driver_runs_the_virtual_bravo_with_its_model(sim: SimServer) -> None:
    assert sim.udp_address is not None
    host, port = sim.udp_address
    with ArmClient(
        open_transport(f"udp://{host}:{port}"),
        model=BRAVO7,
        safety=SafetyConfig(watchdog_s=WATCHDOG_S),
    ) as arm:
        assert sorted(arm.found_devices) == [1, 2, 3, 4, 5, 6, 7] and not arm.warnings
        # the Bravo's limits are read from the arm and adopted inside its factory envelope
        assert arm.guard.has_arm_limit(F, LimitKind.POSITION)
        assert arm.guard.limit(G, LimitKind.CURRENT).high == 2000.0
        state = arm.read_joints()
        np.testing.assert_allclose(state.q, sim.snapshot().q, atol=0.01)
        target = state.q.copy()
        target[2] = 1.2  # E
        arm.command_positions(target)
        assert sim.wait_sim_time(sim.sim_time + 4.0, timeout=WALL_LIMIT_S)
        np.testing.assert_allclose(arm.read_joints().q, target, atol=0.01)
        stop = arm.make_safe()
        assert stop.confirmed
