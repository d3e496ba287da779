"""The Alpha 5 model and motor model against hand calculations from the datasheet figures.

The figures and their sources are in reach_sim_bridge/model/README.md.

The hand calculations below re-derive kinematics, statics and inertia directly from the
reference tables (frames, masses, COMs, volumes, centres of buoyancy, motor constants) with
plain numpy, independently of the MJCF, so a wrong number in the model shows up here.
"""

from __future__ import annotations

import math
from dataclasses import replace

import mujoco
import numpy as np
import pytest

from reach_sim_bridge.model.arm import MODEL_PATH, Alpha5Arm, ArmParams
from reach_sim_bridge.model.motor import MotorModel, MotorParams, no_load_speed

G = 9.81
V = 24.0
# Output torque per amp and back-EMF per output rad/s, by hand from the datasheet table.
K_EDC = 0.0134 * 1754.4 * 0.86  # 20.2 N m/A
KE_EDC = 0.0116 * 1754.4  # 20.35 V s/rad
R_EDC = 3.22
K_B = 0.0271 * 340.4 * 0.77
FRICTION = {"viscous": (2.40, 2.24, 0.82, 0.36), "coulomb": (0.7, 0.7, 0.7, 0.075)}
ARMATURE = (0.12, 0.12, 0.12, 0.007)


# -- hand kinematics from the URDF frame table ----------------------------------------------
def rot(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    if axis == "z":
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if axis == "y":
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    raise ValueError(axis)


def full_inertia(xx, yy, zz, xy, xz, yz):  # noqa: ANN001, ANN201 - table order
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


# body: (mass, COM, inertia about COM, volume L, centre of buoyancy), URDF body frames.
BODIES = {
    "m2_1_1": (
        0.161,
        (-0.00775, -0.00011, 0.01104),
        full_inertia(1.0947e-4, 1.2236e-4, 4.3987e-5, -8.08e-7, 2.9828e-5, 5.44e-7),
        0.032,
        (-0.002, 0.004, 0.017),
    ),
    "m2": (
        0.380,
        (-0.0188, -0.00073, -0.07047),
        full_inertia(8.316e-4, 8.6848e-4, 9.8249e-5, -1.896e-7, -1.3133e-4, -1.8832e-6),
        0.218,
        (-0.01953, -0.001, -0.07279),
    ),
    "m2_1_3": (
        0.142,
        (0.01091, 0.00015, 0.01591),
        full_inertia(6.3596e-5, 7.5158e-5, 4.0651e-5, 8.02e-7, -2.1363e-5, 3.37e-7),
        0.032,
        (0.01091, 0.00015, 0.01591),
    ),
    "m1": (
        0.355,
        (-0.00085, -0.00127, 0.06709),
        full_inertia(6.1833e-4, 6.229e-4, 6.2574e-5, 4.0977e-6, 6.6415e-6, -4.3286e-6),
        0.134,
        (-0.00013, 0.00003, 0.06321),
    ),
}


def frames(q: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World pose (R, p) of each link frame for arm angles q = E D C B."""
    e, d, c, b = q
    out = {}
    r, p = rot("z", e), np.array([0.0, 0.0, 0.014])
    out["m2_1_1"] = (r, p)
    p = p + r @ np.array([-0.02, 0.0, 0.033])
    r = r @ rot("y", d)
    out["m2"] = (r, p)
    p = p + r @ np.array([-0.04, 0.0, -0.1453])
    r = r @ rot("z", math.pi) @ rot("y", c)
    out["m2_1_3"] = (r, p)
    p = p + r @ np.array([0.02, 0.0, 0.033])
    r = r @ rot("z", 2.09439) @ rot("z", -b)  # axis -z
    out["m1"] = (r, p)
    return out


def hand_torque_at_d(q: np.ndarray, rho: float) -> float:
    """Torque of gravity (at each COM) and buoyancy (at each COB) about the D axis."""
    f = frames(q)
    r_d, p_d = f["m2"]
    axis = r_d @ np.array([0.0, 1.0, 0.0])
    total = 0.0
    for name in ("m2", "m2_1_3", "m1"):
        mass, com, _, vol, cob = BODIES[name]
        r, p = f[name]
        for point, force in ((com, -mass * G), (cob, rho * vol * 1e-3 * G)):
            lever = p + r @ np.array(point) - p_d
            total += float(np.cross(lever, np.array([0.0, 0.0, force])) @ axis)
    return total


def hand_inertia_about(joint_body: str, q: np.ndarray, moved: tuple[str, ...]) -> float:
    """Link inertia about a joint axis (kg m^2), parallel-axis theorem on the table values."""
    f = frames(q)
    r_j, p_j = f[joint_body]
    local_axis = np.array([0.0, 0.0, 1.0]) if joint_body == "m2_1_1" else np.array([0, 1.0, 0])
    axis = r_j @ local_axis
    total = 0.0
    for name in moved:
        mass, com, inertia, _, _ = BODIES[name]
        r, p = f[name]
        total += float(axis @ (r @ inertia @ r.T) @ axis)
        off = p + r @ np.array(com) - p_j
        total += mass * float(off @ off - (off @ axis) ** 2)
    return total


def zero_g_air() -> ArmParams:
    return ArmParams(gravity=(0.0, 0.0, 0.0), water_density=0.0)


@pytest.fixture(scope="module")
def arm() -> Alpha5Arm:
    return Alpha5Arm()


# -- the model itself -----------------------------------------------------------------------
def test_joint_order_ranges_and_actuators(arm: Alpha5Arm) -> None:
    m = arm.model
    assert [m.joint(i).name for i in range(m.njnt)] == ["E", "D", "C", "B", "A"]
    assert [m.actuator(i).name for i in range(m.nu)] == ["E", "D", "C", "B", "A"]
    np.testing.assert_allclose(
        arm.position_limits,
        [[0.0175, 6.143], [0.0175, 3.4034], [0.0175, 3.4034], [0.0, 2 * math.pi]],
    )
    assert arm.jaw_limits_mm == pytest.approx((1.3, 13.3))
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP  # implicit damping


def test_default_params_equal_the_xml() -> None:
    """ArmParams() and model/alpha5.xml must not drift apart."""
    xml = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    arm = Alpha5Arm()
    m = arm.model
    for name in (
        "dof_armature",
        "dof_damping",
        "dof_frictionloss",
        "body_mass",
        "body_inertia",
        "body_gravcomp",
    ):
        np.testing.assert_allclose(getattr(m, name), getattr(xml, name), rtol=1e-9, err_msg=name)
    assert m.opt.density == xml.opt.density and m.opt.viscosity == xml.opt.viscosity
    np.testing.assert_allclose(m.opt.gravity, xml.opt.gravity)


def test_link_cylinders_displace_table_volume_at_centre_of_buoyancy(arm: Alpha5Arm) -> None:
    m = arm.model
    for name, (_, _, _, vol, cob) in BODIES.items():
        g = m.geom(name)
        radius, half = g.size[0], g.size[1]
        assert math.pi * radius**2 * 2 * half == pytest.approx(vol * 1e-3, rel=1e-3), name
        np.testing.assert_allclose(g.pos, cob, atol=1e-4, err_msg=name)


def test_collisions_and_fluid_drag_configuration() -> None:
    arm = Alpha5Arm()
    assert arm.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    on = Alpha5Arm(ArmParams(self_collision=True))
    assert not on.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    # The base and the first moving link overlap but never collide.
    d = on._scratch
    base, first = on.model.body("m3_inline").id, on.model.body("m2_1_1").id
    for e in np.linspace(0.0175, 6.143, 13):
        d.qpos[:4] = [e, 1.7, 1.7, 1.0]
        mujoco.mj_forward(on.model, d)
        bodies = {frozenset(on.model.geom_bodyid[c.geom]) for c in d.contact[: d.ncon]}
        assert frozenset((base, first)) not in bodies
    assert arm.model.opt.density == 1000.0
    dry = Alpha5Arm(ArmParams(fluid_drag=False))
    assert dry.model.opt.density == 0.0 and dry.model.opt.viscosity == 0.0


# -- statics: gravity minus buoyancy --------------------------------------------------------
@pytest.mark.parametrize(
    "q", [(3.0, 1.3, 2.6, 1.0), (1.0, 0.5, 3.0, 4.0), (5.0, 2.5, 0.4, 2.0), (2.0, 1.57, 3.14, 0.0)]
)
@pytest.mark.parametrize("rho", [0.0, 1000.0, 1025.0])
def test_gravity_torque_at_d_matches_hand_calculation(q: tuple[float, ...], rho: float) -> None:
    arm = Alpha5Arm(ArmParams(water_density=rho))
    q_arr = np.array(q)
    # 2 mN m covers the jaw rod (0.1 g) and the buoyancy bodies (rho V / 1000) in the model.
    assert arm.gravity_torque(q_arr)[1] == pytest.approx(hand_torque_at_d(q_arr, rho), abs=2e-3)


def test_worst_case_torque_at_d_is_the_datasheet_figure() -> None:
    grid = np.linspace(0.0175, 3.4034, 61)
    worst = {
        rho: max(abs(hand_torque_at_d(np.array([3.0, d, c, 0.0]), rho)) for d in grid for c in grid)
        for rho in (0.0, 1000.0)
    }
    assert worst[0.0] == pytest.approx(1.39, abs=0.03)  # datasheet: ~1.39 N m in air
    assert worst[1000.0] == pytest.approx(0.84, abs=0.03)  # ~0.84 N m in water
    # E's axis is vertical, so it carries no gravity torque; buoyancy lifts D's load.
    arm = Alpha5Arm()
    q = np.array([3.0, 1.30, 2.63, 0.5])
    assert arm.gravity_torque(q)[0] == pytest.approx(0.0, abs=1e-9)
    air = Alpha5Arm(ArmParams(water_density=0.0)).gravity_torque(q)[1]
    assert abs(arm.gravity_torque(q)[1]) < 0.65 * abs(air)


@pytest.mark.parametrize("q", [(3.08, 1.71, 1.71, 3.14), (3.58, 1.26, 2.21, 3.94)])
def test_a_load_in_the_jaws_adds_its_inertia_and_net_weight(q: tuple[float, ...]) -> None:
    """`ArmParams.payload_kg` at the tool centre point, a solid sphere of `payload_volume_l`:
    the joint-space inertia gains m Jp^T Jp + (2/5) m r^2 Jr^T Jr and the gravity torque
    Jp^T of its net weight (mass less the water it displaces); E, whose axis is vertical,
    carries none of the weight."""
    kg, litres, rho = 1.0, 0.09, 1000.0
    bare = Alpha5Arm()
    held = Alpha5Arm(ArmParams(payload_kg=kg, payload_volume_l=litres))
    q_arr = np.array(q)
    _, _, jacp, jacr = bare.tcp_kinematics(q_arr)
    radius = (3.0 * litres * 1e-3 / (4.0 * math.pi)) ** (1.0 / 3.0)
    # the buoyancy body at its centre carries rho V / 1000 (gravcomp 1001): a ten-thousandth
    point = kg + litres * 1e-3 * rho / 1000.0
    inertia = point * jacp.T @ jacp + 0.4 * kg * radius**2 * jacr.T @ jacr
    np.testing.assert_allclose(
        held.mass_matrix(q_arr) - bare.mass_matrix(q_arr), inertia, atol=1e-9
    )
    weight = np.array([0.0, 0.0, -(kg - litres * 1e-3 * rho) * 9.81])
    added = held.gravity_torque(q_arr) - bare.gravity_torque(q_arr)
    np.testing.assert_allclose(added, jacp.T @ weight, atol=1e-9)
    assert added[0] == pytest.approx(0.0, abs=1e-9) and abs(added[1]) > 1.0


def test_a_load_is_refused_where_the_model_holds_none() -> None:
    from reach_sim_bridge.model.bravo7 import Bravo7Arm

    with pytest.raises(ValueError, match="payload_kg"):
        ArmParams(payload_kg=-1.0)
    nominal = Bravo7Arm().params
    with pytest.raises(ValueError, match="takes no payload"):
        Bravo7Arm(params=replace(nominal, payload_kg=1.0))
    bravo = Bravo7Arm()
    lighter = replace(nominal, armature=tuple(0.5 * a for a in nominal.armature))
    with pytest.raises(ValueError, match="takes no payload"):
        bravo.set_params(replace(lighter, payload_kg=1.0))
    assert bravo.params == nominal  # refused whole: nothing of it applied
    np.testing.assert_allclose(bravo.model.dof_armature[:6], nominal.armature)


def test_arm_held_by_its_gravity_torque_stays_put() -> None:
    arm = Alpha5Arm(ArmParams(frictionloss=(0.0, 0.0, 0.0, 0.0)))
    q0 = np.array([2.0, 1.2, 2.4, 1.0])
    arm.reset(q=q0)
    hold = -arm.gravity_torque(q0) / (arm.motor.torque_per_amp / 1000.0)
    arm.step(hold, n=250)
    np.testing.assert_allclose(arm.q, q0, atol=2e-3)
    arm.reset(q=q0)
    arm.step(np.zeros(4), n=250)  # unheld, without friction, D and C fall
    assert np.max(np.abs(arm.q - q0)[1:3]) > 0.05


def test_gravity_torques_are_the_full_forward_steps_to_the_bit() -> None:
    """The batch the envelope's feasibility sweeps hundreds of poses with: the same figures
    as one pose at a time, on an arm whose masses and buoyancy were set after compiling."""
    arm = Alpha5Arm()
    arm.set_params(ArmParams().randomized(11, 0.3))
    poses = np.random.default_rng(4).uniform([0.1, 0.2, 0.2, 0.1], [6.0, 3.0, 3.0, 6.0], (25, 4))
    full = mujoco.MjData(arm.model)  # the full forward step, at rest at each pose
    expected = []
    for q in poses:
        full.qpos[:] = arm.data.qpos  # the jaw where the arm holds it
        full.qpos[:4] = q
        full.qvel[:] = 0.0
        mujoco.mj_forward(arm.model, full)
        expected.append(full.qfrc_gravcomp[:4] - full.qfrc_bias[:4])
    assert np.array_equal(arm.gravity_torques(poses), np.array(expected))
    assert np.array_equal(arm.gravity_torque(poses[3]), expected[3])
    assert np.abs(expected).max() > 0.1  # loads, not zeros
    with pytest.raises(ValueError, match="rows of 4 values"):
        arm.gravity_torques(poses[:, :3])
    with pytest.raises(ValueError, match="rows of 4 values"):
        arm.gravity_torques(np.full((2, 4), np.nan))


def test_work_summed_in_one_call_is_the_single_steps_to_the_bit() -> None:
    """`step(..., n, work=w)` adds each physics step's |tau qdot| as n single steps read it:
    the energy the evaluations integrate, over the current limit, the back-EMF bound (a
    joint driven past its no-load speed brakes) and a weak joint."""
    one, many = Alpha5Arm(), Alpha5Arm()
    rng = np.random.default_rng(7)
    for arm in (one, many):
        arm.set_params(replace(ArmParams().randomized(3, 0.3), torque_scale=(1.0, 0.5, 1.0, 1.0)))
        arm.reset(q=[1.0, 1.5, 1.5, 2.0], qdot=[1.5, -0.2, 0.0, -3.0])
    regimes = {"back-EMF": 0, "limit": 0}
    for _ in range(12):
        currents = rng.uniform(-2500.0, 2500.0, 4)
        expected, got = np.zeros(4), np.zeros(4)
        for _ in range(25):
            one.step(currents, n=1)
            expected += np.abs(one.tau * one.qdot)
            drawn = np.abs(one.current_mA)
            regimes["limit"] += int(np.any(drawn >= one.current_limits_mA - 1e-9))
            regimes["back-EMF"] += int(np.any(drawn < np.minimum(np.abs(currents), 600) - 1))
        many.step(currents, n=25, work=got)
        assert np.array_equal(got, expected)
        assert np.array_equal(many.data.qpos, one.data.qpos)
        assert np.array_equal(many.data.qvel, one.data.qvel)
        assert np.array_equal(many.tau, one.tau)
    assert regimes["limit"] > 0 and regimes["back-EMF"] > 0
    for bad in (np.zeros(3), np.zeros(4, dtype=np.float32), [0.0] * 4):
        with pytest.raises(ValueError, match="work must be"):
            many.step(np.zeros(4), n=2, work=bad)  # type: ignore[arg-type]


# -- motor model ----------------------------------------------------------------------------
def test_no_load_speed_hand_value() -> None:
    speeds = no_load_speed()
    assert speeds[:3] == pytest.approx([V / KE_EDC] * 3)
    assert speeds[0] == pytest.approx(1.18, abs=0.01)
    assert speeds[3] == pytest.approx(V / (0.0545 * 340.4))
    assert no_load_speed(supply_voltage=30.0)[0] == pytest.approx(30.0 / KE_EDC)


def test_motor_torque_current_limit_and_backemf_envelope() -> None:
    motor = MotorModel()
    assert motor.torque_per_amp[:3] == pytest.approx([K_EDC] * 3)
    assert motor.torque_per_amp[3] == pytest.approx(K_B)
    at_rest = np.zeros(4)
    assert motor.torque([100, -200, 0, 50], at_rest) == pytest.approx(
        [K_EDC * 0.1, -K_EDC * 0.2, 0.0, K_B * 0.05]
    )
    # The current limit clamps (600 mA E D C, 300 mA B by default).
    assert motor.current_mA([5000, -5000, 599, 5000], at_rest) == pytest.approx(
        [600, -600, 599, 300]
    )
    # Driving along the motion at 1.1 rad/s leaves (V - Ke w) / R of headroom.
    w = np.array([1.1, -1.1, 0.5, 0.0])
    headroom = 1000 * (V - KE_EDC * 1.1) / R_EDC
    assert headroom < 600
    drawn = motor.current_mA([600, -600, 600, 0], w)
    assert drawn == pytest.approx([headroom, -headroom, 600, 0])
    # Braking against the motion is not limited by the back-EMF (only by the limit).
    assert motor.current_mA([-600, 600, 0, 0], w)[:2] == pytest.approx([-600, 600])
    # Past the no-load speed the motor brakes whatever is commanded.
    assert motor.current_mA([600, 0, 0, 0], [1.3, 0, 0, 0])[0] < 0
    assert motor.stall_torque() == pytest.approx([K_EDC * 0.6] * 3 + [K_B * 0.3])
    assert motor.backemf_damping()[0] == pytest.approx(K_EDC * KE_EDC / R_EDC)  # ~128
    motor.torque_scale = [0.25, 1, 1, 1]
    assert motor.torque([600, 0, 0, 0], at_rest)[0] == pytest.approx(0.25 * K_EDC * 0.6)
    assert motor.current_mA([600, 0, 0, 0], at_rest)[0] == pytest.approx(600)


def test_motor_rejects_bad_values() -> None:
    motor = MotorModel()
    with pytest.raises(ValueError, match="4 values"):
        motor.current_limits_mA = [600, 600]
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        motor.torque_scale = [1.5, 1, 1, 1]
    with pytest.raises(ValueError, match="supply voltage"):
        motor.supply_voltage = float("nan")
    with pytest.raises(ValueError, match="> 0"):
        MotorParams((1.0,), (0.0,), (1.0,), (1.0,), (0.5,))
    assert motor.current_limits_mA == pytest.approx([600, 600, 600, 300])  # unchanged


# -- dynamics -------------------------------------------------------------------------------
def steady_speed(k: float, ke: float, r: float, viscous: float, coulomb: float) -> float:
    """Voltage-limited steady speed: k (V - ke w) / r = viscous w + coulomb."""
    return (k * V / r - coulomb) / (k * ke / r + viscous)


def test_large_current_reaches_backemf_speed_minus_friction() -> None:
    arm = Alpha5Arm(zero_g_air())
    arm.current_limits_mA = [1e6] * 4  # no current limit: only the supply limits the speed
    arm.reset(q=[0.1, 0.1, 0.1, 0.1])
    arm.step([1e6, 1e6, 1e6, 1e6], n=200)  # 0.4 s
    for j in range(3):
        expect = steady_speed(K_EDC, KE_EDC, R_EDC, FRICTION["viscous"][j], FRICTION["coulomb"][j])
        assert arm.qdot[j] == pytest.approx(expect, rel=0.01)
        assert 0.95 * no_load_speed()[j] < arm.qdot[j] < no_load_speed()[j]
    assert arm.qdot[3] == pytest.approx(
        steady_speed(K_B, 0.0545 * 340.4, 38.6, 0.36, 0.075), rel=0.01
    )
    # The current drawn is what the back-EMF leaves, far below the command.
    assert arm.current_mA[0] == pytest.approx(1000 * (V - KE_EDC * arm.qdot[0]) / R_EDC, rel=1e-6)


def test_current_limited_joint_settles_on_the_backemf_line() -> None:
    arm = Alpha5Arm(zero_g_air())
    arm.reset(q=[0.1, 0.1, 0.1, 0.1])
    arm.step([600, 600, 600, 300], n=250)
    expect = steady_speed(K_EDC, KE_EDC, R_EDC, 2.40, 0.7)
    assert arm.qdot[0] == pytest.approx(expect, rel=0.01)
    assert arm.current_mA[0] < 600  # the supply, not the limit, binds at this speed
    assert arm.tau[0] == pytest.approx(K_EDC * arm.current_mA[0] / 1000)


@pytest.mark.parametrize(
    "joint,body,moved,current",
    [
        (1, "m2", ("m2", "m2_1_3", "m1"), 300.0),
        (1, "m2", ("m2", "m2_1_3", "m1"), -300.0),
        (0, "m2_1_1", ("m2_1_1", "m2", "m2_1_3", "m1"), 200.0),
    ],
)
def test_current_step_accelerates_by_torque_over_inertia(
    joint: int, body: str, moved: tuple[str, ...], current: float
) -> None:
    arm = Alpha5Arm(zero_g_air(), dt=0.0005)
    q0 = np.array([3.0, 1.2, 2.0, 1.0])
    arm.reset(q=q0)
    cmd = np.zeros(4)
    cmd[joint] = current
    t = 0.02
    arm.step(cmd, n=int(round(t / arm.dt)))
    inertia = ARMATURE[joint] + hand_inertia_about(body, q0, moved)
    c, fc = FRICTION["viscous"][joint], FRICTION["coulomb"][joint]
    drive = K_EDC * current / 1000 - math.copysign(fc, current)
    expect = drive / c * (1 - math.exp(-c * t / inertia))  # first-order speed response
    assert arm.qdot[joint] == pytest.approx(expect, rel=0.02)
    others = [j for j in range(4) if j != joint]
    assert np.all(np.abs(arm.qdot[others]) < 0.05 * abs(arm.qdot[joint]))


def test_mass_matrix_matches_hand_inertia(arm: Alpha5Arm) -> None:
    q = np.array([1.0, 0.8, 2.2, 3.0])
    mm = arm.mass_matrix(q)
    assert mm[1, 1] == pytest.approx(
        0.12 + hand_inertia_about("m2", q, ("m2", "m2_1_3", "m1")), rel=0.01
    )
    assert mm[0, 0] > mm[1, 1] > 0.12


@pytest.mark.parametrize("joint", [0, 1, 2, 3])
def test_joints_stop_at_their_ranges(joint: int) -> None:
    arm = Alpha5Arm()
    limits = arm.position_limits
    current = 600.0 if joint < 3 else 300.0
    for end, sign in ((1, 1.0), (0, -1.0)):
        q = limits.mean(axis=1)
        q[joint] = limits[joint, end] - sign * 0.3
        arm.reset(q=q)
        cmd = np.zeros(4)
        cmd[joint] = sign * current
        reached = []
        for _ in range(40):
            arm.step(cmd, n=25)
            reached.append(arm.q[joint])
        overshoot = sign * (np.array(reached) - limits[joint, end])
        assert overshoot.max() < 0.005
        assert overshoot[-1] > -0.005  # it got there and stays pressed against the stop
        assert abs(arm.qdot[joint]) < 1e-3


def test_torque_scale_slows_a_joint() -> None:
    def run(scale: float) -> tuple[float, float, float]:
        arm = Alpha5Arm(zero_g_air(), dt=0.0005)
        arm.torque_scale[0] = scale
        arm.reset(q=[0.1, 1.0, 2.0, 1.0])
        arm.step([600, 0, 0, 0], n=10)
        early = arm.qdot[0]
        arm.step([600, 0, 0, 0], n=1990)
        return early, arm.q[0] - 0.1, arm.tau[0]

    healthy, weak = run(1.0), run(0.25)
    full = K_EDC * 0.6
    ratio = (0.25 * full - 0.7) / (full - 0.7)
    assert weak[0] / healthy[0] == pytest.approx(ratio, rel=0.03)  # initial acceleration
    assert weak[1] < 0.9 * healthy[1]  # covers less ground in 1 s
    assert weak[2] == pytest.approx(0.25 * full, rel=0.01)  # current-limited at its speed


def test_torque_scale_via_params_and_validation() -> None:
    arm = Alpha5Arm(ArmParams(torque_scale=(0.25, 1.0, 1.0, 1.0)))
    assert arm.torque_scale == pytest.approx([0.25, 1, 1, 1])
    assert arm.params.torque_scale == (0.25, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        arm.torque_scale = [0.25, 2.0, 1.0, 1.0]
    with pytest.raises(ValueError):
        ArmParams(torque_scale=(1.0, 1.0, 1.0))  # type: ignore[arg-type]


def test_step_follows_settings_changed_in_place_and_reports_what_it_stepped() -> None:
    """`step` caches the motors' constants: an in-place edit of the torque scale or the limits
    must still take effect at the next step, and currents read after a later change of
    settings report the ones the step ran with."""
    arm = Alpha5Arm(zero_g_air())
    arm.reset(q=[3.0, 1.7, 1.7, 3.0])
    arm.step([500, 0, 0, 0], n=1)
    assert arm.tau[0] == pytest.approx(K_EDC * 0.5)
    arm.torque_scale[0] = 0.25  # in place, not through the setter
    arm.step([500, 0, 0, 0], n=1)
    assert arm.tau[0] == pytest.approx(0.25 * K_EDC * 0.5)
    arm.current_limits_mA[0] = 100.0
    arm.step([500, 0, 0, 0], n=1)
    assert arm.current_mA[0] == pytest.approx(100.0)
    arm.step([500, 0, 0, 0], n=1)
    arm.current_limits_mA = [600, 600, 600, 300]  # after the step, before the read
    arm.torque_scale = [1.0, 1.0, 1.0, 1.0]
    assert arm.current_mA[0] == pytest.approx(100.0)
    assert arm.tau[0] == pytest.approx(0.25 * K_EDC * 0.1)
    arm.step([500, 0, 0, 0], n=1)
    assert arm.tau[0] == pytest.approx(K_EDC * 0.5)


def test_current_limit_clamps_drawn_current_and_torque() -> None:
    arm = Alpha5Arm(zero_g_air())
    arm.reset(q=[3.0, 1.7, 1.7, 3.0])
    arm.step([5000, -5000, 100, 5000], n=1)
    assert arm.current_mA == pytest.approx([600, -600, 100, 300])
    assert arm.tau == pytest.approx([K_EDC * 0.6, -K_EDC * 0.6, K_EDC * 0.1, K_B * 0.3])
    arm.current_limits_mA = [200, 200, 200, 100]
    arm.reset(q=[3.0, 1.7, 1.7, 3.0])
    arm.step([5000, -5000, 100, -5000], n=1)
    assert arm.current_mA == pytest.approx([200, -200, 100, -100])
    # A lower limit gives a proportionally lower acceleration from rest.
    fast, slow = Alpha5Arm(zero_g_air()), Alpha5Arm(zero_g_air())
    slow.current_limits_mA = [300, 600, 600, 300]
    for a in (fast, slow):
        a.reset(q=[3.0, 1.7, 1.7, 3.0])
        a.step([5000, 0, 0, 0], n=2)
    assert slow.qdot[0] / fast.qdot[0] == pytest.approx(
        (K_EDC * 0.3 - 0.7) / (K_EDC * 0.6 - 0.7), rel=0.05
    )


# -- kinematics -----------------------------------------------------------------------------
@pytest.mark.parametrize("q", [(3.0, 1.5, 3.0, 0.0), (0.5, 0.3, 1.0, 2.0), (5.5, 2.9, 0.2, 5.0)])
def test_end_effector_pose_matches_hand_forward_kinematics(q: tuple[float, ...]) -> None:
    arm = Alpha5Arm()
    arm.reset(q=np.array(q))
    r, p = frames(np.array(q))["m1"]
    tcp = (p + r @ np.array([0.0, 0.0, 0.09975 + 0.04])) * 1000.0
    x, y, z, roll, pitch, yaw = arm.end_effector_pose()
    np.testing.assert_allclose([x, y, z], tcp, atol=1e-6)
    rebuilt = (
        rot("z", yaw)
        @ rot("y", pitch)
        @ np.array(
            [[1, 0, 0], [0, math.cos(roll), -math.sin(roll)], [0, math.sin(roll), math.cos(roll)]]
        )
    )
    np.testing.assert_allclose(rebuilt, r, atol=1e-9)


def test_reach_of_the_straight_arm(arm: Alpha5Arm) -> None:
    # Straight arm (C = pi): shoulder to tool centre ~0.15 + 0.033 + 0.14 m.
    arm.reset(q=[3.0, 1.5, math.pi, 0.0])
    x, y, z, *_ = arm.end_effector_pose()
    shoulder = frames(np.array([3.0, 1.5, math.pi, 0.0]))["m2"][1] * 1000
    reach = math.dist((x, y, z), shoulder)
    assert 300 < reach < 340


# -- jaw ------------------------------------------------------------------------------------
def test_jaw_opens_and_closes_between_its_stops() -> None:
    arm = Alpha5Arm()
    arm.reset(jaw_mm=5.0)
    arm.step(np.zeros(4), jaw_current_mA=200.0, n=25)
    assert arm.jaw_velocity_mm_s > 0
    speed = arm.jaw_velocity_mm_s
    assert speed < arm.jaw_motor.no_load_speed()[0] * 1000  # under the back-EMF limit
    for _ in range(200):
        arm.step(np.zeros(4), jaw_current_mA=200.0, n=25)
    assert arm.jaw_mm == pytest.approx(13.3, abs=0.05)
    for _ in range(300):
        arm.step(np.zeros(4), jaw_current_mA=-200.0, n=25)
    assert arm.jaw_mm == pytest.approx(1.3, abs=0.05)
    assert arm.jaw_current_mA == pytest.approx(-200.0)
    assert arm.jaw_force == pytest.approx(arm.jaw_motor.torque_per_amp[0] * -0.2)


# -- parameters -----------------------------------------------------------------------------
def test_randomized_params_are_seeded_and_bounded() -> None:
    base = ArmParams()
    a, b, c = base.randomized(7), base.randomized(7), base.randomized(8)
    assert a == b and a != c
    for name in ("damping", "frictionloss", "armature", "link_mass_kg", "link_volume_l"):
        ratio = np.asarray(getattr(a, name)) / np.asarray(getattr(base, name))
        assert np.all((ratio >= 0.8) & (ratio <= 1.2)), name
        assert not np.allclose(ratio, 1.0), name
    assert a.motors == base.motors and a.torque_scale == base.torque_scale
    with pytest.raises(ValueError, match="spread"):
        base.randomized(1, spread=1.5)


def test_randomize_applies_in_place_and_changes_the_physics() -> None:
    arm = Alpha5Arm(seed=3)
    q = np.array([3.0, 1.3, 2.6, 0.5])
    before = arm.gravity_torque(q)[1]
    params = arm.randomize(0.2)
    m = arm.model
    np.testing.assert_allclose(m.dof_damping[:4], params.damping)
    np.testing.assert_allclose(m.dof_armature[:4], params.armature)
    np.testing.assert_allclose(m.body_mass[m.body("m2").id], params.link_mass_kg[1])
    after = arm.gravity_torque(q)[1]
    assert after != pytest.approx(before, rel=1e-3)
    # Same seed, same draw.
    assert Alpha5Arm(seed=3).randomize(0.2) == params
    # Repeated draws stay around the nominal arm (no random walk) and keep run-time settings.
    arm.torque_scale = [0.25, 1, 1, 1]
    for _ in range(20):
        params = arm.randomize(0.2)
        ratio = np.asarray(params.damping) / np.asarray(ArmParams().damping)
        assert np.all((ratio >= 0.8) & (ratio <= 1.2))
    assert arm.torque_scale == pytest.approx([0.25, 1, 1, 1])


def test_bad_input_is_rejected_and_the_state_kept() -> None:
    arm = Alpha5Arm()
    arm.reset(q=[1.0, 1.0, 1.0, 1.0])
    arm.step([100, 100, 100, 100], n=5)
    q, t = arm.q, arm.time
    for bad in ([1, 2, 3], [1, 2, 3, float("nan")], [[1, 2, 3, 4]]):
        with pytest.raises(ValueError, match="currents_mA"):
            arm.step(bad)
    with pytest.raises(ValueError, match="n"):
        arm.step([0, 0, 0, 0], n=0)
    with pytest.raises(ValueError, match="jaw_current_mA"):
        arm.step([0, 0, 0, 0], jaw_current_mA=float("inf"))
    assert arm.time == t and np.array_equal(arm.q, q)
    with pytest.raises(ValueError, match="outside the joint ranges: D=3.5000"):
        arm.reset(q=[1.0, 3.5, 1.0, 1.0])
    with pytest.raises(ValueError, match="jaw_mm"):
        arm.reset(jaw_mm=20.0)
    with pytest.raises(ValueError, match="dt"):
        Alpha5Arm(dt=0.0)
    with pytest.raises(ValueError, match="link_mass_kg"):
        ArmParams(link_mass_kg=(0.1, 0.0, 0.1, 0.1))


def test_continuous_wrist_wraps_its_reported_angle() -> None:
    arm = Alpha5Arm(ArmParams(wrist_continuous=True))
    arm.reset(q=[3.0, 1.7, 1.7, 6.2])
    arm.step([0, 0, 0, 300], n=250)
    assert 0.0 <= arm.q[3] < 1.0  # went past 2 pi and reads from 0 again
    stopped = Alpha5Arm()
    stopped.reset(q=[3.0, 1.7, 1.7, 6.2])
    stopped.step([0, 0, 0, 300], n=250)
    assert stopped.q[3] == pytest.approx(2 * math.pi, abs=0.005)


def test_fluid_drag_is_small_against_joint_damping() -> None:
    speeds = {}
    for drag in (True, False):
        arm = Alpha5Arm(ArmParams(fluid_drag=drag, gravity=(0.0, 0.0, 0.0)))
        arm.reset(q=[0.1, 1.7, 1.7, 0.1])
        arm.step([600, 0, 0, 300], n=250)
        speeds[drag] = arm.qdot
    assert np.all(speeds[True][[0, 3]] < speeds[False][[0, 3]])  # drag does slow it
    np.testing.assert_allclose(speeds[True], speeds[False], rtol=0.005, atol=1e-4)


def test_the_twins_coulomb_friction_creeps_below_breakaway_unless_it_is_made_to_hold() -> None:
    """A documented property of the twin (docs/robustness.md, "The twin's friction creeps";
    tools/creep.py): MuJoCo's frictionloss is a soft constraint, so a joint pushed below its
    friction slides at push / ~120 N m s/rad instead of holding; `friction_holds` (its no-slip
    solver) makes the friction hold and leaves the slip above breakaway as it was."""
    from reach_sim_bridge.model import creep

    half = creep.creep_speed(6.6, 0, 0.5)  # E pushed at 3.3 N m against 6.6
    assert 3.3 / half == pytest.approx(120, rel=0.1)
    assert abs(creep.creep_speed(6.6, 0, 0.5, holds=True)) < 1e-6
    assert creep.creep_speed(1.9, 0, 1.5, holds=True) == pytest.approx(
        creep.creep_speed(1.9, 0, 1.5), rel=0.01
    )
    arm = Alpha5Arm(ArmParams(friction_holds=True))
    assert arm.model.opt.noslip_iterations > 0
    arm.set_params(ArmParams())
    assert arm.model.opt.noslip_iterations == 0
    assert ArmParams.from_json_dict({"friction_holds": True}).friction_holds
