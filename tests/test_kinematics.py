"""The driver's forward kinematics and the simulator's MJCF describe the same arm.

The driver may not import the simulator, so it carries the chain itself; this test is what
keeps the two copies equal (link origins and the tool centre point, over random poses).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINTS
from reach_driver.kinematics import link_poses, tool_jacobian, tool_position
from reach_sim_bridge.model.arm import Alpha5Arm

LINKS = ("m2_1_1", "m2", "m2_1_3", "m1")


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo = np.array([FACTORY_POSITION_LIMITS[d][0] for d in JOINTS])
    hi = np.array([FACTORY_POSITION_LIMITS[d][1] for d in JOINTS])
    return rng.uniform(lo, hi, size=(n, len(JOINTS)))


@pytest.fixture(scope="module")
def arm() -> Alpha5Arm:
    return Alpha5Arm(seed=0)


@pytest.mark.parametrize(
    "q", list(_poses(12, seed=3)), ids=lambda q: "q=" + ",".join(f"{v:.2f}" for v in q)
)
def test_tool_position_matches_the_simulators_tcp(arm: Alpha5Arm, q: np.ndarray) -> None:
    arm.reset(q=q)
    x, y, z, *_ = arm.end_effector_pose()
    np.testing.assert_allclose(tool_position(q) * 1000.0, [x, y, z], atol=1e-3)  # mm


def test_link_origins_match_the_mjcf(arm: Alpha5Arm) -> None:
    for q in _poses(5, seed=4):
        arm.reset(q=q)
        mujoco.mj_kinematics(arm.model, arm.data)
        for (pos, rot), name in zip(link_poses(q), LINKS, strict=True):
            body = arm.data.body(name)
            np.testing.assert_allclose(pos, body.xpos, atol=1e-6)
            np.testing.assert_allclose(rot, body.xmat.reshape(3, 3), atol=1e-6)


def test_tool_jacobian_matches_the_simulators(arm: Alpha5Arm) -> None:
    for q in _poses(6, seed=5):
        pos, jac = tool_jacobian(q)
        sim_pos, _, sim_jacp, _ = arm.tcp_kinematics(q)
        np.testing.assert_allclose(pos, sim_pos, atol=1e-6)
        np.testing.assert_allclose(jac, sim_jacp, atol=1e-6)
        np.testing.assert_allclose(jac[:, 3], 0.0, atol=1e-9)  # B does not move the tcp
