"""End-effector moves by the driver's own inverse kinematics (reach_driver/ik.py): they agree
with the virtual arm's solver, go out as checked joint POSITION commands, reach a Cartesian
target on the virtual arm, and an unreachable target is refused before anything moves."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import wait_until

from protocol import DeviceID, HardwareStatus, Mode, Packet, PacketID, commands
from protocol.alpha5 import JOINTS
from reach_driver import ArmClient, LimitError, open_transport
from reach_driver.cli import Exit, main
from reach_driver.errors import ArmFaultError
from reach_driver.ik import (
    TOLERANCE_MM,
    UnreachableError,
    factory_limits,
    solve_or_refuse,
    solve_position,
)
from reach_driver.kinematics import tool_position
from reach_sim_bridge.emulator.server import SimServer
from reach_sim_bridge.model import ik as sim_ik
from reach_sim_bridge.model.arm import Alpha5Arm

SPEED = 8.0
LIMITS = factory_limits()
FAR = (2000.0, 0.0, 0.0)  # mm: twice the arm's length away


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    inner = LIMITS + np.array([0.15, -0.15])  # away from the bounds
    return rng.uniform(inner[:, 0], inner[:, 1], size=(n, 4))


pytestmark = pytest.mark.sim(speed=SPEED)


# ------------------------------------------------------------------ the solver


@pytest.mark.parametrize("q", list(_poses(8, seed=11)), ids=lambda q: f"E={q[0]:.2f},D={q[1]:.2f}")
def test_solves_the_forward_kinematics_of_a_pose_back(q: np.ndarray) -> None:
    target = tool_position(q) * 1000.0
    start = np.array([3.1, 1.7, 1.7, 1.0])
    sol = solve_position(target.tolist(), start, LIMITS)
    assert sol.reachable
    assert np.linalg.norm(tool_position(sol.q) * 1000.0 - target) <= TOLERANCE_MM
    assert np.all(sol.q >= LIMITS[:, 0]) and np.all(sol.q <= LIMITS[:, 1])
    assert sol.q[3] == pytest.approx(1.0)  # B is free: it keeps its angle


def test_an_unreachable_target_is_refused_with_the_distance() -> None:
    with pytest.raises(UnreachableError) as err:
        solve_or_refuse(FAR, [3.1, 1.7, 1.7, 3.1], LIMITS)
    assert isinstance(err.value, LimitError)
    assert err.value.distance_mm > 1000.0
    assert "out of reach" in str(err.value) and "nothing was sent" in str(err.value)
    assert f"{err.value.distance_mm:.1f} mm" in str(err.value)


def test_tighter_limits_make_a_target_unreachable() -> None:
    q = np.array([3.1, 1.0, 1.2, 3.1])
    target = tool_position(q) * 1000.0
    tight = LIMITS.copy()
    tight[1] = [1.5, 2.5]  # D may not reach 1.0, and no other branch gets there
    assert solve_position(target.tolist(), q, LIMITS).reachable
    with pytest.raises(UnreachableError):
        solve_or_refuse(target.tolist(), q, tight)


@pytest.fixture(scope="module")
def arm() -> Alpha5Arm:
    return Alpha5Arm(seed=0)


@pytest.mark.parametrize("q", list(_poses(6, seed=12)), ids=lambda q: f"E={q[0]:.2f},D={q[1]:.2f}")
def test_the_driver_and_the_simulator_solve_alike(arm: Alpha5Arm, q: np.ndarray) -> None:
    """From the same start both solvers reach the target, on the same branch."""
    target = tool_position(q) * 1000.0
    start = np.clip(q + np.array([0.3, -0.25, 0.25, 0.0]), LIMITS[:, 0], LIMITS[:, 1])
    ours = solve_position(target.tolist(), start, LIMITS)
    theirs = sim_ik.solve(arm, (*target, 0.0, 0.0, 0.0), start, LIMITS)
    assert ours.reachable and theirs.reachable
    arm.reset(q=theirs.q)
    x, y, z, *_ = arm.end_effector_pose()
    assert np.linalg.norm(np.array([x, y, z]) - target) <= TOLERANCE_MM
    np.testing.assert_allclose(ours.q[:3], theirs.q[:3], atol=0.02)


def test_both_solvers_refuse_the_same_far_target(arm: Alpha5Arm) -> None:
    start = np.array([3.1, 1.7, 1.7, 3.1])
    assert not solve_position(FAR, start, LIMITS).reachable
    assert not sim_ik.solve(arm, (*FAR, 0.0, 0.0, 0.0), start, LIMITS).reachable


# ------------------------------------------------------------------ the client


def _client(sim: SimServer) -> ArmClient:
    return ArmClient(open_transport(str(sim.link))).start()


def _target_near(q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = np.clip(q0 + np.array([0.35, -0.3, 0.3, 0.0]), LIMITS[:, 0], LIMITS[:, 1])
    return q, tool_position(q) * 1000.0


def test_command_xyz_sends_checked_joint_positions_and_reaches_the_target(sim) -> None:
    with _client(sim) as client:
        q0 = client.read_joints((PacketID.POSITION,)).q
        _, target = _target_near(q0)
        checked: list[Packet] = []
        gate_check = client._gate.check_packet

        def spy(packet: Packet) -> None:
            checked.append(packet)
            gate_check(packet)

        client._gate.check_packet = spy  # type: ignore[method-assign]
        q = client.command_xyz(*target)
        # Four joint POSITION commands, each through the gate: no KM_END_POS.
        assert [(p.device_id, p.packet_id) for p in checked] == [
            (d, PacketID.POSITION) for d in JOINTS
        ]
        np.testing.assert_allclose([p.as_float() for p in checked], q, atol=1e-5)
        assert np.linalg.norm(tool_position(q) * 1000.0 - target) <= TOLERANCE_MM
        assert q[3] == pytest.approx(q0[3], abs=1e-9)

        def there() -> bool:
            now = client.read_joints((PacketID.POSITION,)).q
            return bool(np.linalg.norm(tool_position(now) * 1000.0 - target) < 2.0)

        assert wait_until(there, timeout=20.0, poll_s=0.05)
        assert all(sim.firmware.mode(d) == Mode.POSITION for d in JOINTS)


def test_command_xyz_refuses_an_unreachable_target_and_nothing_moves(sim) -> None:
    with _client(sim) as client:
        q0 = client.read_joints((PacketID.POSITION,)).q
        with pytest.raises(UnreachableError):
            client.command_xyz(*FAR)
        assert all(sim.firmware.mode(d) == Mode.STANDBY for d in JOINTS)
        np.testing.assert_allclose(client.read_joints((PacketID.POSITION,)).q, q0, atol=0.01)


def test_command_xyz_goes_through_the_fault_gate(sim) -> None:
    with _client(sim) as client:
        q0 = client.read_joints((PacketID.POSITION,)).q
        sim.inject_fault(int(DeviceID.C), HardwareStatus.ENCODER_FAULT)
        assert wait_until(lambda: bool(client.read_status([int(DeviceID.C)])[3]), timeout=5.0)
        with pytest.raises(ArmFaultError, match="ENCODER_FAULT"):
            client.command_xyz(*_target_near(q0)[1])
        assert all(sim.firmware.mode(d) == Mode.STANDBY for d in JOINTS)


def test_raw_km_end_pos_is_still_refused(sim) -> None:
    with _client(sim) as client:
        packet: Packet = commands.end_position(DeviceID.E, 300.0, 0.0, 100.0, 0.0, 0.0, 0.0)
        with pytest.raises(LimitError, match="KM_END_POS"):
            client.send(packet)


# ------------------------------------------------------------------ the CLI


def _reported_q(sim: SimServer) -> np.ndarray:
    with _client(sim) as client:
        return client.read_joints((PacketID.POSITION,)).q


def test_move_xyz_reaches_the_cartesian_target_within_5_mm(sim, capsys) -> None:
    _, target = _target_near(sim.snapshot().q)
    argv = ["--port", str(sim.link), "move", "--xyz", *map(str, target), "--timeout", "30"]
    code = main(argv)
    out = capsys.readouterr().out
    assert code == Exit.OK, out
    assert "reached" in out and "mm" in out
    reached = tool_position(_reported_q(sim)) * 1000.0  # FK of the angles the arm reports
    assert np.linalg.norm(reached - target) < 5.0


def test_move_xyz_unreachable_exits_non_zero_and_nothing_moves(sim, capsys) -> None:
    q0 = sim.snapshot().q
    code = main(["--port", str(sim.link), "move", "--xyz", *map(str, FAR)])
    err = capsys.readouterr().err
    assert code == Exit.LIMIT
    assert "out of reach" in err and "mm away" in err
    assert all(sim.firmware.mode(d) == Mode.STANDBY for d in JOINTS)
    assert np.max(np.abs(sim.snapshot().q - q0)) < 0.01


@pytest.mark.parametrize(
    "argv",
    [["move", "--xyz", "300", "0", "100", "3", "1.5", "1.5", "3"], ["move", "3", "1.5"], ["move"]],
    ids=["both", "three-angles", "neither"],
)
def test_move_takes_four_angles_or_xyz(sim, argv: list[str], capsys) -> None:
    assert main(["--port", str(sim.link), *argv]) == Exit.USAGE
    assert "--xyz" in capsys.readouterr().err
    assert all(sim.firmware.mode(d) == Mode.STANDBY for d in JOINTS)
