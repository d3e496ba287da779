"""Arm models as data (`protocol.models`): the Alpha 5 and the Bravo 7 are entries of one table
built from their modules' facts, and the parts that depend on the arm take a model.

A fictional third arm, three joints D C B and the jaws, shows the table-driven parts accept a
model that is neither: the driver's limits, state, feedback check and commands, and the
emulated firmware on a MuJoCo arm of that model.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest
from conftest import wait_until

from protocol import DeviceID, Packet, PacketID, alpha5, bravo7, commands, decode_packet
from protocol.models import (
    ALPHA5,
    BRAVO7,
    MODELS,
    ArmModel,
    ArmModelName,
    MotorConstants,
    model_named,
)
from protocol.payload import pack_floats
from reach_driver import ArmClient
from reach_driver.errors import LimitError
from reach_driver.interfaces import open_transport
from reach_driver.plausibility import FeedbackCheck
from reach_driver.safety import LimitKind, SafetyConfig, SafetyGuard, envelope_problem
from reach_driver.state import ArmState, StateTable
from reach_sim_bridge.emulator.devices import DeviceSpec, LoopGains
from reach_sim_bridge.emulator.firmware import Firmware, FirmwareConfig
from reach_sim_bridge.model.arm import MotorArm
from reach_sim_bridge.model.motor import JAW_MOTOR, MotorModel, MotorParams

A, B, C, D, E = DeviceID.A, DeviceID.B, DeviceID.C, DeviceID.D, DeviceID.E

#: A fictional arm: a yaw D, a pitch C and a wrist roll B that turns a whole turn, the jaws A,
#: with the Alpha's E D C motors.
TRIAD = ArmModel(
    name="triad3",
    title="Test Triad 3",
    joints=(D, C, B),
    jaw=A,
    position_limits={D: (0.1, 3.0), C: (0.2, 2.9), B: (0.0, 2.0 * math.pi), A: (0.0, 20.0)},
    velocity_limits={D: (-0.4, 0.4), C: (-0.4, 0.4), B: (-0.8, 0.8), A: (-2.0, 2.0)},
    current_limits_mA=(500.0, 450.0, 400.0),
    jaw_current_limit_mA=250.0,
    max_joint_speed=(1.5, 1.5, 3.0),
    motors=MotorConstants(
        alpha5.MOTOR_RESISTANCE_OHM[:3],
        alpha5.MOTOR_TORQUE_CONSTANT_NM_PER_A[:3],
        alpha5.MOTOR_BACKEMF_V_S_PER_RAD[:3],
        alpha5.GEAR_RATIO[:3],
        alpha5.GEAR_EFFICIENCY[:3],
    ),
    nominal_supply_v=24.0,
    serial_baud=115200,
    base=D,
    kinematics=None,
)

TRIAD_MJCF = """
<mujoco model="triad3">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.002" integrator="Euler"><flag contact="disable"/></option>
  <default><joint limited="true" armature="0.12" damping="2.0" frictionloss="0.5"/></default>
  <worldbody>
    <body name="l1" pos="0 0 0.1">
      <joint name="D" axis="0 0 1" range="0.1 3.0"/>
      <inertial pos="0.05 0 0" mass="0.4" diaginertia="1e-3 1e-3 1e-3"/>
      <body name="l2" pos="0.1 0 0">
        <joint name="C" axis="0 1 0" range="0.2 2.9"/>
        <inertial pos="0.05 0 0" mass="0.3" diaginertia="1e-3 1e-3 1e-3"/>
        <body name="l3" pos="0.1 0 0">
          <joint name="B" axis="1 0 0" range="0 6.283185307179586"/>
          <inertial pos="0.02 0 0" mass="0.2" diaginertia="1e-4 1e-4 1e-4"/>
          <site name="tcp" pos="0.06 0 0"/>
          <body name="jaw">
            <joint name="A" type="slide" axis="1 0 0" range="0 0.020" armature="725"
                   damping="5000" frictionloss="10"/>
            <inertial pos="0 0 0" mass="0.001" diaginertia="1e-7 1e-7 1e-7"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="D"/><motor joint="C"/><motor joint="B"/><motor joint="A"/>
  </actuator>
</mujoco>
"""


def triad_arm() -> MotorArm:
    arm = MotorArm(
        mujoco.MjModel.from_xml_string(TRIAD_MJCF),
        TRIAD,
        MotorModel(MotorParams.of(TRIAD.motors), 24.0, TRIAD.current_limits_mA),
        MotorModel(JAW_MOTOR, 24.0, (TRIAD.jaw_current_limit_mA,)),
        link_bodies=("l1", "l2", "l3"),
    )
    arm.reset(q=[1.0, 1.2, 3.0], jaw_mm=5.0)
    return arm


def triad_firmware(arm: MotorArm) -> Firmware:
    def spec(device: DeviceID, gains: LoopGains) -> DeviceSpec:
        rate = TRIAD.velocity_limits[device][1]
        return DeviceSpec(device, device.name, TRIAD.unit(device), rate, gains, 300.0 + device)

    devices = (
        spec(A, LoopGains(3.0, 20.0, 150.0)),
        spec(B, LoopGains(5.0, 1e3, 2e4)),
        spec(C, LoopGains(5.0, 1e3, 2e4)),
        spec(D, LoopGains(5.0, 1e3, 2e4)),
    )
    return Firmware(arm, FirmwareConfig(model=TRIAD, devices=devices, model_number=3003.0))


# -- the table ----------------------------------------------------------------------------------
def test_the_table_holds_the_alpha_and_the_bravo_from_their_modules_facts() -> None:
    assert set(MODELS) == set(ArmModelName)
    for name, model in MODELS.items():
        assert model_named(name.value) is model and model.name == name.value
    for model, facts in ((ALPHA5, alpha5), (BRAVO7, bravo7)):
        assert model.joints == facts.JOINTS and model.jaw == facts.JAW
        assert model.joint_letters == facts.JOINT_LETTERS and model.n_joints == facts.N_JOINTS
        assert dict(model.position_limits) == facts.FACTORY_POSITION_LIMITS
        assert dict(model.velocity_limits) == facts.FACTORY_VELOCITY_LIMITS
        assert dict(model.current_limits) == facts.FACTORY_CURRENT_LIMITS
        assert model.torque_per_amp_nm == pytest.approx(facts.TORQUE_PER_AMP_NM)
        assert model.max_joint_speed == facts.MAX_JOINT_SPEED
        assert model.serial_baud == facts.SERIAL_BAUD == 115200
    assert ALPHA5.actuators == alpha5.ALL_DEVICES and ALPHA5.base == E == ALPHA5.kinematics
    assert BRAVO7.devices == (*bravo7.ALL_DEVICES, DeviceID.ROUTER, DeviceID.COMPUTE)
    assert (BRAVO7.base, BRAVO7.force_torque, BRAVO7.kinematics) == (
        DeviceID.ROUTER,
        DeviceID.ROUTER,
        DeviceID.COMPUTE,
    )
    assert ALPHA5.unit(A) == "mm" and ALPHA5.unit(B) == "rad"
    assert [ALPHA5.wraps(d) for d in ALPHA5.joints] == [False, False, False, True]
    with pytest.raises(ValueError, match="known models: alpha5, bravo7"):
        model_named("bravo5")


def test_a_model_that_does_not_hold_together_is_refused_naming_what() -> None:
    for change, message in (
        ({"joints": (D, C, C)}, "named twice"),
        ({"jaw": B}, "named twice"),
        ({"joints": ()}, "at least one joint"),
        ({"position_limits": {D: (0.1, 3.0), C: (0.2, 2.9), A: (0.0, 20.0)}}, r"missing \['B'\]"),
        ({"velocity_limits": {D: (0.1, 0.4), C: (-1, 1), B: (-1, 1), A: (-1, 1)}}, "include 0"),
        ({"current_limits_mA": (500.0, 450.0)}, "needs 3 values"),
        ({"max_joint_speed": (1.0, 1.0, 0.0)}, "needs 3 values > 0"),
        ({"base": E}, "not one of its devices"),
    ):
        with pytest.raises(ValueError, match=message):
            dataclasses.replace(TRIAD, **change)
    with pytest.raises(ValueError, match="one value per joint"):
        MotorConstants((1.0, 1.0), (1.0,), (1.0,), (1.0,), (1.0,))
    with pytest.raises(ValueError, match="gear efficiency"):
        MotorConstants((1.0,), (1.0,), (1.0,), (1.0,), (1.2,))


@pytest.mark.parametrize("model", [*MODELS.values(), TRIAD], ids=lambda m: m.name)
def test_each_models_commands_round_trip_the_wire(model: ArmModel) -> None:
    for device in model.actuators:
        lo, hi = model.position_limits[device]
        for packet in (
            commands.position(device, lo),
            commands.velocity(device, model.velocity_limits[device][1]),
            commands.current(device, -model.current_limits[device][1]),
            commands.limits(device, PacketID.POSITION_LIMITS, hi, lo),
        ):
            back = decode_packet(packet.encode())
            assert back.key == packet.key and back.floats() == pytest.approx(packet.floats())
    if model.force_torque is not None:
        tare = decode_packet(commands.force_torque_tare(model.force_torque).encode())
        assert tare.key == (DeviceID.ROUTER, PacketID.FORCE_TORQUE) and tare.floats() == [0.0] * 6


# -- the driver --------------------------------------------------------------------------------
def test_the_drivers_limits_follow_the_model() -> None:
    guard = SafetyGuard(SafetyConfig(), TRIAD)
    assert guard.position_limits() == [(0.1, 3.0), (0.2, 2.9), (0.0, 2.0 * math.pi)]
    assert guard.limit(B, LimitKind.CURRENT).high == 400.0
    assert guard.limit(E, LimitKind.POSITION).source == "none"  # not a device of this arm
    with pytest.raises(LimitError, match=r"C \(0x03\) is outside its position limit \[0.2, 2.9\]"):
        guard.check(C, LimitKind.POSITION, 3.0)
    guard.check(C, LimitKind.POSITION, 2.85)
    with pytest.raises(LimitError, match="mm"):
        guard.check(A, LimitKind.POSITION, 21.0)
    # a reported limit must lie inside this model's envelope, not the Alpha's
    assert envelope_problem(C, LimitKind.POSITION, (0.2, 2.9), TRIAD) is None
    assert envelope_problem(C, LimitKind.POSITION, (0.1, 3.0)) is None  # inside the Alpha's
    problem = envelope_problem(C, LimitKind.POSITION, (0.1, 3.0), TRIAD)
    assert problem is not None and "leave the factory envelope [0.2, 2.9] rad" in problem
    # the default stays the Alpha 5
    assert SafetyGuard().position_limits()[0] == ALPHA5.position_limits[E]


def test_state_and_feedback_check_read_the_models_joints_in_its_order() -> None:
    table = StateTable(TRIAD)
    for device, value in ((B, 0.3), (D, 1.0), (C, 2.0), (A, 7.0), (E, 9.0)):
        table.update(Packet(device, PacketID.POSITION, pack_floats(value)), 0.0)
    state = table.snapshot(1.0)
    np.testing.assert_allclose(state.q, [1.0, 2.0, 0.3])
    assert state.jaw_mm == pytest.approx(7.0) and state.qdot.shape == (3,)
    np.testing.assert_allclose(ArmState(state.joints, 1.0).q, [9.0, 1.0, 2.0, 0.3])  # Alpha

    check = FeedbackCheck(model=TRIAD)
    assert not check.check(0.0, np.array([1.0, 2.0, 0.1]), np.full(3, 0.01)).bad.any()
    # B wraps (a whole turn): 0.1 -> 6.2 rad in 0.05 s is a 0.18 rad step, not 6.1
    assert not check.check(0.05, np.array([1.0, 2.0, 6.2]), np.full(3, -0.01)).bad.any()
    verdict = check.check(0.1, np.array([1.0, 3.2, 6.2]), np.full(3, 0.02))  # C past 2.9 + 0.1
    assert verdict.bad.tolist() == [False, True, False] and verdict.why[0].startswith("C:")
    verdict = check.check(0.15, np.array([1.0, 2.0, 6.2]), np.array([0.0, 0.0, 3.6]))
    assert verdict.bad.tolist() == [False, False, True]  # B beyond its 3.0 + 0.5 rad/s
    assert FeedbackCheck().top.tolist() == list(ALPHA5.max_joint_speed)  # the default


def _sent(client: ArmClient, pid: int) -> list[Packet]:
    seen: list[Packet] = []
    client.subscribe(lambda p, _t: seen.append(p) if p.packet_id == pid else None)
    return seen


def test_the_client_commands_the_models_joints() -> None:
    client = ArmClient(
        open_transport("loop://"), safety=SafetyConfig(watchdog_s=None), model=TRIAD
    ).start(discover=False, read_limits=False)
    try:
        assert client.devices == (D, C, B, A)
        seen = _sent(client, PacketID.VELOCITY)
        for device, value in ((D, 1.0), (C, 1.5), (B, 3.0)):  # the positions the barrier needs
            client.transport.write_frames([commands.position(device, value).encode()])
        assert wait_until(lambda: np.all(np.isfinite(client.state.q)), timeout=5.0)
        sent = client.command_velocities([0.1, -0.2, 0.3])
        np.testing.assert_allclose(sent, [0.1, -0.2, 0.3])
        assert wait_until(lambda: len(seen) == 3, timeout=5.0)
        assert [(p.device_id, round(p.as_float(), 6)) for p in seen] == [
            (D, 0.1),
            (C, -0.2),
            (B, 0.3),
        ]
        with pytest.raises(ValueError, match="expected 3 values in joint order D C B, got 4"):
            client.command_velocities([0.1, 0.1, 0.1, 0.1])
        with pytest.raises(LimitError, match="outside its velocity limit"):
            client.command_velocities([0.5, 0.0, 0.0])  # D's 0.4 rad/s, not the Alpha's
        with pytest.raises(LimitError, match="inverse kinematics are the Reach Alpha 5's"):
            client.solve_xyz(100.0, 0.0, 100.0)
    finally:
        client.close(safe=False)


# -- the emulator ------------------------------------------------------------------------------
def test_the_firmware_serves_a_model_of_three_joints() -> None:
    arm = triad_arm()
    fw = triad_firmware(arm)
    assert fw.devices == (A, B, C, D)
    # every device answers its own reading, in the model's order
    for device, value in zip((D, C, B, A), (*arm.q.tolist(), 5.0), strict=True):
        reply = fw.report(device, PacketID.POSITION)
        assert reply is not None and reply.as_float() == pytest.approx(value, abs=1e-3)
    # limits round-trip the wire as the model states them ([max, min], float32)
    for device in TRIAD.actuators:
        reply = fw.report(device, PacketID.POSITION_LIMITS)
        assert reply is not None
        hi, lo = reply.floats()
        assert (lo, hi) == pytest.approx(TRIAD.position_limits[device], abs=1e-6)
        current = fw.report(device, PacketID.CURRENT_LIMITS)
        assert current is not None and current.floats()[0] == TRIAD.current_limits[device][1]
    # a POSITION command moves the named joint, and only it
    fw.handle(commands.position(C, 2.0))
    fw.tick(3.0)
    assert arm.q[1] == pytest.approx(2.0, abs=0.01)
    assert arm.q[0] == pytest.approx(1.0, abs=0.01) and arm.q[2] == pytest.approx(3.0, abs=0.01)
    # a device this arm does not have is counted, not answered
    assert fw.handle(commands.request(E, [PacketID.POSITION])) == []
    assert fw.ignored.snapshot() == {"other_device": 1}
    reply = fw.report(D, PacketID.MODEL_NUMBER)
    assert reply is not None and reply.as_float() == 3003.0
