"""The Bravo 7 twin (model/bravo7.xml) and its motor constants against hand calculations.

The figures and their sources are in reach_sim_bridge/model/bravo7.md. Everything "hand" here
is re-derived with plain numpy from the datasheet's tables, typed in below in the datasheet's
own units (mm, kg, kg mm^2, litres) and conventions (standard DH rows, products of inertia),
never read from the MJCF: a wrong number in the model shows up as a disagreement.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from protocol import alpha5, bravo7
from protocol.ids import DeviceID
from reach_sim_bridge.model import bravo7 as twin
from reach_sim_bridge.model.motor import (
    ALPHA5_MOTORS,
    BRAVO7_JAW_MOTOR,
    BRAVO7_MOTORS,
    MotorModel,
    no_load_speed,
)

PI = math.pi
G = 9.81
V = 24.0  # assumed supply (bravo7.md)

# -- the datasheet, typed in -----------------------------------------------------------------
# DH table, standard convention, one row per frame {k} -> {k+1}: d (mm), theta offset (rad;
# the joint angle is added for rows 1..6), a (mm), alpha (rad). Row 2's offset and length come
# from the 5.2 mm elbow offset over the 290.77 mm upper arm.
THETA_S = math.atan(5.2 / 290.77)
DH_ROWS = (
    (41.45, 0.0, 67.5, PI),
    (-117.48, PI, 46.0, -PI / 2),
    (0.0, -PI / 2 + THETA_S, math.hypot(5.2, 290.77), 0.0),
    (0.0, -PI / 2 - THETA_S, 40.8, -PI / 2),
    (-160.26, PI, 40.8, -PI / 2),
    (0.0, 0.0, 40.8, -PI / 2),
    (-224.16, 0.0, 0.0, PI / 2),
    (0.0, -PI / 2, 120.0, 0.0),
)
# Per link (0 base .. 6 wrist, 7 closed jaws), in the link's inertial frame:
# mass kg, COM mm, I about the COM (xx, yy, zz) kg mm^2 and products (xy, xz, yz) as printed,
# I about the frame origin and its products as printed, volume L, centre of buoyancy mm.
LINKS = {
    0: (1.85, (-15, 1, -2), (2528, 2593, 3312), (-20, 23, 7),
        (2535, 2980, 3697), (-53, 65, 4), 0.81, (-16, 1, -1)),
    1: (1.62, (31, 10, -98), (3179, 4209, 2387), (233, -1024, -344),
        (18856, 21257, 4130), (771, -5936, -2039), 0.74, (27, 9, -101)),
    2: (2.12, (176, 22, 4), (3420, 35166, 35981), (-1868, 3150, -79),
        (4439, 100570, 102343), (6169, 4586, 98), 1.96, (157, 39, 0)),
    3: (1.33, (34, -46, -3), (1809, 1557, 2024), (-398, 156, -197),
        (4660, 3143, 6438), (-2512, 21, -15), 0.44, (38, -48, -6)),
    4: (1.33, (28, 12, -145), (1983, 2676, 1526), (180, -641, -264),
        (29892, 31470, 2780), (624, -6084, -2526), 0.59, (23, 9, -146)),
    5: (0.97, (31, -39, -6), (1272, 1205, 1511), (-346, 116, -189),
        (2761, 2204, 3938), (-1534, -53, 20), 0.39, (36, -42, -9)),
    6: (1.09, (0, 0, -127), (1977, 1986, 1035), (0, -15, 1),
        (19498, 19506, 1035), (-1, -35, 14), 0.53, (0, 0, -145)),
    7: (0.64, (1, 1, 0), (2237, 309, 2258), (-18, 0, 1),
        (2238, 309, 2259), (-18, 0, 1), 0.16, (1, -27, 0)),
}  # fmt: skip
# Actuator table, G F E D C B then the jaws: R, Kt (N m/A), Kv (V s/rad), ratio, input-side
# friction F (N mm) and damping B (N mm s/rad).
KT = (0.222, 0.222, 0.215, 0.215, 0.215, 0.209)
KV = (0.181, 0.181, 0.176, 0.176, 0.176, 0.171)
R = (1.0, 1.0, 2.3, 2.3, 2.3, 5.9)
GR = 120.0
JAW_GR_PER_M = 39.27e3
F_IN, B_IN, B_IN_JAW = 79e-3, 1.43e-3, 0.89e-3  # N m, N m s/rad at the motor
ROTOR_INERTIA = 2e-5  # kg m^2, assumed (bravo7.md)
LINK_NAMES = [f"link{i}" for i in range(8)]
JOINT_RANGES = [(0, 2 * PI), (0, 3.2), (0, 3.2), (0, 2 * PI), (0, 3.2), (0, 2 * PI)]


# -- hand kinematics and statics ---------------------------------------------------------------
def _rz(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    return out


def _rx(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    out = np.eye(4)
    out[1:3, 1:3] = [[c, -s], [s, c]]
    return out


def _tr(x: float, y: float, z: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = (x, y, z)
    return out


def _row(k: int, theta: float) -> np.ndarray:
    d, offset, a, alpha = DH_ROWS[k]
    return _rz(theta + offset) @ _tr(0, 0, d / 1000) @ _tr(a / 1000, 0, 0) @ _rx(alpha)


def dh_frames(q: np.ndarray) -> dict[object, np.ndarray]:
    """World (= base frame {0}) pose of each link's inertial frame 0..7 and of the TCP {8}.

    Link 0's is DH frame {1}; link i's (1..6) is DH frame {i} turned by its joint (theta_i plus
    the row's offset); link 7's is DH frame {7}, the flange."""
    out: dict[object, np.ndarray] = {}
    t = _row(0, 0.0)
    out[0] = t
    for i in range(1, 7):
        out[i] = t @ _rz(q[i - 1] + DH_ROWS[i][1])
        t = t @ _row(i, q[i - 1])
    out[7] = t
    out["tcp"] = t @ _row(7, 0.0)
    return out


def tensor(diag: tuple[float, ...], products: tuple[float, ...]) -> np.ndarray:
    """Inertia tensor (kg m^2) from diagonal moments and printed products (kg mm^2): the
    tensor's off-diagonal entries are minus the products."""
    xx, yy, zz = diag
    xy, xz, yz = (-p for p in products)
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]], float) * 1e-6


def hand_torques(q: np.ndarray, rho: float, gravity: tuple[float, float, float]) -> np.ndarray:
    """Torque of gravity (at each COM) and buoyancy (at each centre of buoyancy) about each
    joint axis G..B: joint i turns about the z axis of link i's frame, at its origin."""
    frames = dh_frames(q)
    g = np.array(gravity, float)
    out = np.zeros(6)
    for j in range(1, 7):
        origin, axis = frames[j][:3, 3], frames[j][:3, 2]
        for i in range(j, 8):
            mass, com, _, _, _, _, vol, cob = LINKS[i]
            rot, pos = frames[i][:3, :3], frames[i][:3, 3]
            for point, force in ((com, mass * g), (cob, -rho * vol * 1e-3 * g)):
                lever = pos + rot @ (np.array(point) / 1000) - origin
                out[j - 1] += float(np.cross(lever, force) @ axis)
    return out


def hand_inertia_about(joint: int, q: np.ndarray) -> float:
    """Inertia (kg m^2) of the links joint `joint` (0 = G) moves, about its axis."""
    frames = dh_frames(q)
    origin, axis = frames[joint + 1][:3, 3], frames[joint + 1][:3, 2]
    total = 0.0
    for i in range(joint + 1, 8):
        mass, com, diag, products, *_ = LINKS[i]
        rot, pos = frames[i][:3, :3], frames[i][:3, 3]
        total += float(axis @ rot @ tensor(diag, products) @ rot.T @ axis)
        off = pos + rot @ (np.array(com) / 1000) - origin
        total += mass * float(off @ off - (off @ axis) ** 2)
    return total


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return twin.load()


def at(model: mujoco.MjModel, q: np.ndarray) -> mujoco.MjData:
    data = mujoco.MjData(model)
    data.qpos[:6] = q
    mujoco.mj_forward(model, data)
    return data


# -- the model as the facts say ---------------------------------------------------------------
def test_joint_order_ranges_and_actuators(model: mujoco.MjModel) -> None:
    names = ["G", "F", "E", "D", "C", "B", "A"]
    assert [model.joint(i).name for i in range(model.njnt)] == names
    assert [model.actuator(i).name for i in range(model.nu)] == names
    assert list(model.jnt_qposadr) == list(range(7)) and model.nq == 7
    np.testing.assert_allclose(model.jnt_range[:6], JOINT_RANGES)
    np.testing.assert_allclose(model.jnt_range[6], [0.0, 0.010])
    assert model.jnt_type[6] == mujoco.mjtJoint.mjJNT_SLIDE
    # The simulator's ranges are the protocol's envelope (jaws: metres vs mm).
    for name, device in zip(names, bravo7.ALL_DEVICES, strict=True):
        scale = 1000.0 if device == DeviceID.A else 1.0
        assert tuple(model.joint(name).range * scale) == pytest.approx(
            bravo7.FACTORY_POSITION_LIMITS[device]
        )
    # Device order: the datasheet's actuators 1..7 (base to jaws) are devices 0x07..0x01.
    assert [int(d) for d in bravo7.ALL_DEVICES] == [7, 6, 5, 4, 3, 2, 1]
    assert twin.JOINTS == ("G", "F", "E", "D", "C", "B")
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT


def test_each_link_mass_and_the_total_are_the_datasheets() -> None:
    air = twin.load(water_density=0.0)
    for i, name in enumerate(LINK_NAMES):
        assert air.body(name).mass[0] == pytest.approx(LINKS[i][0]), name
    links = sum(LINKS[i][0] for i in LINKS)
    assert links == pytest.approx(10.95)
    # Everything else weighs nothing in air: the jaw push rod is a 0.1 g placeholder.
    assert air.body_mass.sum() == pytest.approx(links + 1e-4, abs=1e-9)
    assert mujoco.mj_getTotalmass(air) == pytest.approx(10.9501)
    moving = links - LINKS[0][0]
    assert moving == pytest.approx(9.10)


def test_centres_of_mass_and_inertia_tensors_are_the_datasheets(model: mujoco.MjModel) -> None:
    for i, name in enumerate(LINK_NAMES):
        _, com, diag, products, *_ = LINKS[i]
        body = model.body(name)
        np.testing.assert_allclose(body.ipos, np.array(com) / 1000, atol=1e-12, err_msg=name)
        flat = np.zeros(9)
        mujoco.mju_quat2Mat(flat, body.iquat)
        rot = flat.reshape(3, 3)
        rebuilt = rot @ np.diag(body.inertia) @ rot.T
        np.testing.assert_allclose(rebuilt, tensor(diag, products), atol=1e-10, err_msg=name)


def test_datasheet_off_diagonals_are_products_of_inertia() -> None:
    """Why the MJCF flips their sign: the printed inertia about the frame origin follows from
    the one about the COM by the parallel-axis theorem only if the printed off-diagonals are
    products (+sum of xy dm), within the rounding of the 1 mm COM."""
    for i, (mass, com, diag, products, diag_o, products_o, *_) in LINKS.items():
        c = np.array(com, float)
        transfer = mass * (c @ c * np.eye(3) - np.outer(c, c))  # kg mm^2
        # COM coordinates rounded to 1 mm move an entry by up to about m (|c_i| + |c_j|) mm
        slack = 1.2 * mass * np.abs(c).sum() + 5.0
        as_products = tensor(diag, products) * 1e6 + transfer
        np.testing.assert_allclose(as_products, tensor(diag_o, products_o) * 1e6, atol=slack)
        as_tensor = -tensor((0, 0, 0), products) * 1e6 + np.diag(diag) + transfer
        wrong = np.abs(as_tensor - (-tensor((0, 0, 0), products_o) * 1e6 + np.diag(diag_o)))
        if np.abs(products).max() > 100:  # large enough for the sign to show
            assert wrong.max() > slack, i


@pytest.mark.parametrize(
    "q",
    [
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        (1.0, 1.6, 1.6, 0.0, 1.0, 0.5),
        (5.5, 0.4, 2.9, 3.5, 2.2, 6.0),
        (3.0, 3.1, 0.2, 1.2, 3.1, 2.5),
    ],
)
def test_forward_kinematics_is_the_datasheet_dh_chain(model: mujoco.MjModel, q: tuple) -> None:
    data = at(model, np.array(q))
    frames = dh_frames(np.array(q))
    for i, name in enumerate(LINK_NAMES):
        body = model.body(name).id
        np.testing.assert_allclose(data.xpos[body], frames[i][:3, 3], atol=1e-9, err_msg=name)
        np.testing.assert_allclose(
            data.xmat[body].reshape(3, 3), frames[i][:3, :3], atol=1e-9, err_msg=name
        )
    tcp = data.site("tcp")
    np.testing.assert_allclose(tcp.xpos, frames["tcp"][:3, 3], atol=1e-9)
    np.testing.assert_allclose(tcp.xmat.reshape(3, 3), frames["tcp"][:3, :3], atol=1e-9)
    # Each joint turns about its link frame's z axis, at that frame's origin.
    for j in range(6):
        np.testing.assert_allclose(data.xanchor[j], frames[j + 1][:3, 3], atol=1e-9)
        np.testing.assert_allclose(data.xaxis[j], frames[j + 1][:3, 2], atol=1e-9)


def test_zero_pose_and_link_lengths(model: mujoco.MjModel) -> None:
    """At all-zero angles the upper arm hangs from the shoulder, 158.93 mm above the base
    frame, and the arm is folded: the TCP is 315.74 mm below the base frame."""
    data = at(model, np.zeros(6))
    shoulder, elbow = data.xanchor[1], data.xanchor[2]
    assert shoulder[2] == pytest.approx(0.15893)
    assert np.linalg.norm(elbow - shoulder) == pytest.approx(0.2908165, abs=1e-7)
    # straight down but for the datasheet's 5.2 mm elbow offset
    np.testing.assert_allclose(elbow - shoulder, [-0.0052, 0.0, -0.29077], atol=1e-12)
    np.testing.assert_allclose(data.site("tcp").xpos, [-0.0245, 0.0, -0.31574], atol=1e-9)
    # Forearm-roll axis to wrist pitch to flange to TCP, along the chain.
    data = at(model, np.array([0.0, 1.6, 1.6, 0.0, 1.6, 0.0]))
    flange = data.xpos[model.body("link7").id]
    assert np.linalg.norm(data.site("tcp").xpos - flange) == pytest.approx(0.120)


def test_link_cylinders_displace_the_datasheet_volume_at_the_centre_of_buoyancy(
    model: mujoco.MjModel,
) -> None:
    for i, name in enumerate(LINK_NAMES):
        vol, cob = LINKS[i][6], LINKS[i][7]
        geom = model.geom(name)
        radius, half = geom.size[0], geom.size[1]
        assert math.pi * radius**2 * 2 * half == pytest.approx(vol * 1e-3, rel=1e-3), name
        np.testing.assert_allclose(geom.pos, np.array(cob) / 1000, atol=1e-6, err_msg=name)
        if i:
            buoy = model.body(name + "_buoyancy")
            np.testing.assert_allclose(buoy.pos, np.array(cob) / 1000, atol=1e-12)
            assert model.body_gravcomp[buoy.id] == twin.BUOYANCY_GRAVCOMP
    assert twin.LINK_VOLUME_L == tuple(LINKS[i][6] for i in range(1, 8))
    assert sum(LINKS[i][6] for i in LINKS) == pytest.approx(5.62)


def test_the_xml_as_written_is_the_arm_in_fresh_water() -> None:
    """`load()` sets buoyancy from the volumes; the XML's own buoyancy masses must say the
    same for rho = 1000 (mass rho V / 1000, gravcomp 1001: a net rho V g upward)."""
    xml = mujoco.MjModel.from_xml_path(str(twin.MODEL_PATH))
    loaded = twin.load(1000.0)
    np.testing.assert_allclose(xml.body_mass, loaded.body_mass, rtol=1e-12)
    assert xml.opt.density == loaded.opt.density == 1000.0
    assert xml.opt.viscosity == loaded.opt.viscosity == 0.0009
    data = at(xml, np.zeros(6))
    for i in range(1, 8):
        body = xml.body(f"link{i}_buoyancy").id
        lift = (xml.body_gravcomp[body] - 1.0) * xml.body_mass[body] * G
        assert lift == pytest.approx(1000.0 * LINKS[i][6] * 1e-3 * G)
    assert data.qfrc_gravcomp.any()
    assert twin.load(1000.0, fluid_drag=False).opt.density == 0.0
    assert twin.load(0.0).opt.density == 0.0 and twin.load(0.0).opt.viscosity == 0.0
    # Drag acts on the moving links' cylinders only (the base is welded).
    drag = [bool(xml.geom_fluid[xml.geom(f"link{i}").id, 0]) for i in range(8)]
    assert drag == [False] + [True] * 7


def test_joint_friction_damping_and_armature_are_the_datasheets_reflected(
    model: mujoco.MjModel,
) -> None:
    np.testing.assert_allclose(model.dof_frictionloss[:6], F_IN * GR)  # 9.48 N m
    np.testing.assert_allclose(model.dof_damping[:6], B_IN * GR**2)  # 20.6 N m s/rad
    np.testing.assert_allclose(model.dof_armature[:6], ROTOR_INERTIA * GR**2)  # 0.288 kg m^2
    assert model.dof_frictionloss[6] == pytest.approx(F_IN * JAW_GR_PER_M)  # 3.1 kN
    assert model.dof_damping[6] == pytest.approx(B_IN_JAW * JAW_GR_PER_M**2)
    assert model.dof_armature[6] == pytest.approx(ROTOR_INERTIA * JAW_GR_PER_M**2)


# -- statics: gravity minus buoyancy ------------------------------------------------------------
POSES = [
    (0.0, 1.55, 2.7, PI, 2.4, 0.0),  # near the shoulder's worst case
    (1.0, 1.6, 1.6, 0.0, 1.0, 0.5),
    (5.5, 0.4, 2.9, 3.5, 2.2, 6.0),
    (3.0, 3.1, 0.2, 1.2, 3.1, 2.5),
]
GRAVITY = {
    "upright": (0.0, 0.0, -G),
    "on its side": (-G, 0.0, 0.0),  # base frame x up: G carries load too
    "tilted": (0.0, G * math.sqrt(0.5), -G * math.sqrt(0.5)),
}


@pytest.mark.parametrize("q", POSES)
@pytest.mark.parametrize("rho", [0.0, 1000.0, 1025.0])
@pytest.mark.parametrize("mount", list(GRAVITY))
def test_static_torque_at_each_joint_matches_hand_calculation(
    q: tuple, rho: float, mount: str
) -> None:
    m = twin.load(water_density=rho)
    m.opt.gravity[:] = GRAVITY[mount]
    hand = hand_torques(np.array(q), rho, GRAVITY[mount])
    # 1 mN m covers the jaw push rod (0.1 g) the datasheet does not list.
    np.testing.assert_allclose(twin.gravity_torque(m, q), hand, atol=1e-3)
    if mount == "upright":
        assert twin.gravity_torque(m, q)[0] == pytest.approx(0.0, abs=1e-9)


def test_worst_case_figures_and_that_the_motors_hold_them() -> None:
    """bravo7.md's worst-case static loads (base upright), at the poses a grid search found
    (F in 0.05 rad steps, E 0.1, C 0.2, D quarter turns, G = B = 0), and the assumed current
    limits against them."""
    figures = {  # joint index: (pose, air N m, fresh water N m)
        1: ((0.0, 1.55, 2.7, PI, 2.4, 0.0), 29.83, 16.33),
        2: ((0.0, 1.15, 3.1, PI, 2.4, 0.0), 10.87, None),
        4: ((0.0, 2.55, 2.8, 0.0, 2.2, 0.0), 3.28, None),
    }
    for joint, (q, air, fresh) in figures.items():
        assert abs(twin.gravity_torque(twin.load(0.0), q)[joint]) == pytest.approx(air, abs=0.01)
        if fresh is not None:
            got = twin.gravity_torque(twin.load(1000.0), q)[joint]
            assert abs(got) == pytest.approx(fresh, abs=0.01)
    # At the assumed limits each motor holds its worst load plus its datasheet friction.
    stall = np.array(bravo7.TORQUE_PER_AMP_NM) * np.array(bravo7.DEFAULT_CURRENT_LIMITS_MA) / 1000
    assert stall[1] > 1.3 * (29.83 + F_IN * GR)  # shoulder: 53.3 against 39.3 N m
    assert stall[2] > 1.3 * (10.87 + F_IN * GR)
    assert stall[4] > 1.3 * (3.28 + F_IN * GR)


# -- dynamics: a free swing, motor off ---------------------------------------------------------
def equilibrium(joint: int, q: np.ndarray, rho: float) -> tuple[float, float]:
    """Where the joint hangs at rest (hand statics, bisection) and the restoring stiffness
    k = -d(torque)/d(angle) there (N m/rad)."""

    def torque(x: float) -> float:
        pose = q.copy()
        pose[joint] = x
        return hand_torques(pose, rho, (0.0, 0.0, -G))[joint]

    lo, hi = JOINT_RANGES[joint]
    xs = np.linspace(lo, hi, 33)
    vals = [torque(x) for x in xs]
    k = next(n for n in range(32) if vals[n] > 0.0 >= vals[n + 1])  # restoring crossing
    a, b = xs[k], xs[k + 1]
    for _ in range(60):
        mid = 0.5 * (a + b)
        a, b = (mid, b) if torque(mid) > 0.0 else (a, mid)
    x0 = 0.5 * (a + b)
    h = 1e-4
    return x0, -(torque(x0 + h) - torque(x0 - h)) / (2 * h)


def swing(
    joint: int,
    q: np.ndarray,
    rho: float,
    damping: float,
    start: float,
    seconds: float,
    drag: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Release one joint (motor off, no Coulomb friction) at `start` with the others held
    (huge armature, and put back each step); the joint's angle over time."""
    m = twin.load(water_density=rho, fluid_drag=drag)
    others = [j for j in range(7) if j != joint]
    m.dof_armature[others] = 1e6
    m.dof_frictionloss[:] = 0.0
    m.dof_damping[:] = 0.0
    m.dof_damping[joint] = damping
    d = mujoco.MjData(m)
    pose = np.append(q, 0.005)  # jaw half open, away from its stops
    pose[joint] = start
    d.qpos[:] = pose
    n = int(round(seconds / m.opt.timestep))
    angle = np.empty(n + 1)
    angle[0] = start
    for i in range(n):
        mujoco.mj_step(m, d)
        d.qpos[others] = pose[others]
        d.qvel[others] = 0.0
        angle[i + 1] = d.qpos[joint]
    return np.arange(n + 1) * m.opt.timestep, angle


def crossings(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Times x crosses zero (linear interpolation)."""
    idx = np.flatnonzero(np.signbit(x[:-1]) != np.signbit(x[1:]))
    return t[idx] - x[idx] * (t[idx + 1] - t[idx]) / (x[idx + 1] - x[idx])


SWING_POSE = np.array([1.0, 1.6, 1.6, 0.0, 1.0, 0.5])
AMPLITUDE = 0.03  # rad: small enough that the pendulum is linear (period shift < 1e-4)


@pytest.mark.parametrize("joint,rho", [(4, 0.0), (2, 0.0), (1, 0.0), (4, 1000.0), (1, 1025.0)])
def test_free_swing_period_is_the_pendulums(joint: int, rho: float) -> None:
    """Undamped: T = 2 pi sqrt(I / k), I = armature + the links' inertia about the axis
    (parallel-axis theorem on the datasheet tensors), k from the hand statics (in water the
    buoyancy's restoring moment is in k). Within 0.5 %."""
    x0, k = equilibrium(joint, SWING_POSE, rho)
    inertia = ROTOR_INERTIA * GR**2 + hand_inertia_about(joint, SWING_POSE)
    period = 2 * PI * math.sqrt(inertia / k)
    t, angle = swing(joint, SWING_POSE, rho, 0.0, x0 + AMPLITUDE, 2.2 * period)
    zeros = crossings(t, angle - x0)
    assert len(zeros) >= 4
    measured = 2 * float(np.mean(np.diff(zeros)))
    assert measured == pytest.approx(period, rel=0.005)
    # No damping: the amplitude holds (the integrator neither gains nor loses energy).
    assert np.max(np.abs(angle[len(angle) // 2 :] - x0)) == pytest.approx(AMPLITUDE, rel=0.01)


def test_water_drag_damps_a_free_swing_a_little() -> None:
    """The ellipsoid drag model on the link cylinders: a 0.3 rad swing of C in water loses
    amplitude it keeps without drag, but far less than the joint's own damping would take."""
    x0, _ = equilibrium(4, SWING_POSE, 1000.0)
    runs = {
        drag: swing(4, SWING_POSE, 1000.0, 0.0, x0 + 0.3, 2.7, drag=drag)[1] - x0
        for drag in (False, True)
    }
    assert np.max(np.abs(runs[False][-500:])) == pytest.approx(0.3, rel=0.01)
    kept = np.max(np.abs(runs[True][-500:])) / 0.3
    assert 0.8 < kept < 0.98  # [M] 0.90


@pytest.mark.parametrize("joint", [4, 1])
def test_lightly_damped_swing_decays_as_the_hand_calculation(joint: int) -> None:
    """Damping set to a tenth of critical: damped period 2 pi / (w_n sqrt(1 - z^2)) and the
    amplitude falling by exp(-z w_n T_d) each period, within 1 %."""
    x0, k = equilibrium(joint, SWING_POSE, 0.0)
    inertia = ROTOR_INERTIA * GR**2 + hand_inertia_about(joint, SWING_POSE)
    zeta = 0.1
    wn = math.sqrt(k / inertia)
    c = 2 * zeta * math.sqrt(k * inertia)
    td = 2 * PI / (wn * math.sqrt(1 - zeta**2))
    t, angle = swing(joint, SWING_POSE, 0.0, c, x0 + AMPLITUDE, 2.2 * td)
    zeros = crossings(t, angle - x0)
    assert 2 * float(np.mean(np.diff(zeros))) == pytest.approx(td, rel=0.01)
    # Peaks one period apart: the first is the release itself.
    one = int(round(td / (t[1] - t[0])))
    window = slice(one - 50, one + 50)
    peak = float(np.max(angle[window] - x0))
    assert peak / AMPLITUDE == pytest.approx(math.exp(-zeta * wn * td), rel=0.01)


@pytest.mark.parametrize("joint", [4, 2])
def test_swing_with_the_datasheet_damping_creeps_back_as_overdamped(joint: int) -> None:
    """With the model's own viscous damping (20.6 N m s/rad) the joint does not swing at all:
    the hand solution of I x'' + c x' + k x = 0 from rest is two decaying exponentials, and
    the model follows it within 1 % of the release offset."""
    x0, k = equilibrium(joint, SWING_POSE, 0.0)
    inertia = ROTOR_INERTIA * GR**2 + hand_inertia_about(joint, SWING_POSE)
    c = B_IN * GR**2
    disc = c * c - 4 * k * inertia
    assert disc > 0  # overdamped
    s1, s2 = (-c + math.sqrt(disc)) / (2 * inertia), (-c - math.sqrt(disc)) / (2 * inertia)
    t, angle = swing(joint, SWING_POSE, 0.0, c, x0 + AMPLITUDE, 3.0)
    hand = AMPLITUDE * (s1 * np.exp(s2 * t) - s2 * np.exp(s1 * t)) / (s1 - s2)
    np.testing.assert_allclose(angle - x0, hand, atol=0.01 * AMPLITUDE)
    assert np.all(np.diff(angle) <= 1e-12)  # never passes the rest angle


# -- motors --------------------------------------------------------------------------------------
def test_motor_constants_and_what_they_give_at_the_joint() -> None:
    assert BRAVO7_MOTORS.count == 6 and BRAVO7_JAW_MOTOR.count == 1
    assert BRAVO7_MOTORS.torque_constant == KT
    assert BRAVO7_MOTORS.backemf_constant == KV
    assert BRAVO7_MOTORS.resistance_ohm == R
    assert BRAVO7_MOTORS.gear_ratio == (GR,) * 6
    per_amp = [k * GR for k in KT]  # 26.64 G F, 25.8 E D C, 25.08 B (N m/A)
    np.testing.assert_allclose(BRAVO7_MOTORS.torque_per_amp(), per_amp)
    np.testing.assert_allclose(bravo7.TORQUE_PER_AMP_NM, per_amp)
    assert per_amp[1] == pytest.approx(26.64)
    speeds = no_load_speed(BRAVO7_MOTORS, bravo7.NOMINAL_SUPPLY_V)
    np.testing.assert_allclose(speeds, [V / (kv * GR) for kv in KV])  # 1.10 .. 1.17 rad/s
    assert speeds[1] == pytest.approx(1.105, abs=0.001)
    # The assumed velocity limits sit below what the motors can do at the supply.
    limits = [bravo7.FACTORY_VELOCITY_LIMITS[d][1] for d in bravo7.JOINTS]
    assert np.all(np.array(limits) < speeds)
    motor = MotorModel(BRAVO7_MOTORS, V, bravo7.DEFAULT_CURRENT_LIMITS_MA)
    assert motor.current_mA([5000] * 6, np.zeros(6)) == pytest.approx(
        list(bravo7.DEFAULT_CURRENT_LIMITS_MA)
    )
    assert motor.stall_torque()[1] == pytest.approx(26.64 * 2.0)
    # The jaws: motor radians per metre of travel, so N per A and m/s come out directly.
    jaw = MotorModel(BRAVO7_JAW_MOTOR, V, (bravo7.DEFAULT_JAW_CURRENT_LIMIT_MA,))
    assert jaw.torque_per_amp[0] == pytest.approx(0.209 * JAW_GR_PER_M)  # ~8.2 kN/A
    assert bravo7.JAW_FORCE_PER_AMP_N == pytest.approx(jaw.torque_per_amp[0])
    jaw_speed_mm_s = jaw.no_load_speed()[0] * 1000
    assert jaw_speed_mm_s == pytest.approx(V / (0.171 * 39.27), rel=1e-9)  # 3.57 mm/s
    assert bravo7.FACTORY_VELOCITY_LIMITS[DeviceID.A][1] < jaw_speed_mm_s


def test_the_alphas_motors_are_unchanged() -> None:
    np.testing.assert_allclose(
        ALPHA5_MOTORS.torque_per_amp(), [0.0134 * 1754.4 * 0.86] * 3 + [0.0271 * 340.4 * 0.77]
    )
    assert MotorModel().current_limits_mA == pytest.approx([600, 600, 600, 300])
    assert alpha5.JOINT_LETTERS == ("E", "D", "C", "B")


def test_bad_input_is_one_clear_error() -> None:
    with pytest.raises(ValueError, match="water_density is kg/m"):
        twin.load(water_density=-1.0)
    with pytest.raises(ValueError, match="water_density is kg/m"):
        twin.load(water_density=float("nan"))
    m = twin.load()
    with pytest.raises(ValueError, match=r"6 finite angles \(G F E D C B\)"):
        twin.gravity_torque(m, [0.0] * 5)
    with pytest.raises(ValueError, match="6 finite angles"):
        twin.gravity_torque(m, [0.0] * 5 + [float("inf")])
