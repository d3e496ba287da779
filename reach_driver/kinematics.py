"""Forward kinematics of the Alpha 5 from its published joint frames.

The driver draws the arm (recordings) and reports the tool position without importing the
simulator, so it carries the kinematic chain itself: origins and axes of the vendor URDF frames
(reach_sim_bridge/model/README.md), joint angles exactly as the arm reports them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

#: Distance from the wrist frame (m1) to the tool centre point along its z axis (m): jaw base
#: 0.09975 + ~0.04 to the fingertips' centre, the point the MJCF's `tcp` site (and so the
#: emulator's KM_END_POS) reports; tests/test_kinematics.py keeps the two chains equal.
TCP_OFFSET_M = 0.09975 + 0.04


@dataclass(frozen=True)
class JointFrame:
    """One revolute joint: parent -> child origin (xyz, yaw of its rpy) and rotation axis."""

    name: str
    parent_link: str
    child_link: str
    xyz: tuple[float, float, float]
    yaw: float
    axis: tuple[float, float, float]


#: The chain base -> wrist in E, D, C, B order (URDF frames; only yaw rotations occur).
CHAIN: tuple[JointFrame, ...] = (
    JointFrame("E", "m3_inline", "m2_1_1", (0.0, 0.0, 0.014), 0.0, (0.0, 0.0, 1.0)),
    JointFrame("D", "m2_1_1", "m2", (-0.02, 0.0, 0.033), 0.0, (0.0, 1.0, 0.0)),
    JointFrame("C", "m2", "m2_1_3", (-0.04, 0.0, -0.1453), np.pi, (0.0, 1.0, 0.0)),
    JointFrame("B", "m2_1_3", "m1", (0.02, 0.0, 0.033), 2.09439, (0.0, 0.0, -1.0)),
)


class ChainFrame(NamedTuple):
    """One revolute joint of a chain generated from an MJCF (reach_driver.drawing): the link
    it moves, that link's origin and rotation in the frame of the link before it, and the
    joint's axis in the link's own frame."""

    joint: str
    link: str
    pos: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    axis: tuple[float, float, float]


def quat_rotation(quat_xyzw: tuple[float, float, float, float] | np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(quat_xyzw, dtype=float)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def axis_rotation(axis: tuple[float, float, float] | np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of `angle` radians about a unit `axis` (Rodrigues)."""
    x, y, z = np.asarray(axis, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
    )


def joint_transform(frame: JointFrame, q: float) -> tuple[np.ndarray, np.ndarray]:
    """(translation, rotation) mapping child-link coordinates into the parent link's."""
    rot = axis_rotation((0.0, 0.0, 1.0), frame.yaw) @ axis_rotation(frame.axis, q)
    return np.asarray(frame.xyz, dtype=float), rot


def link_poses(q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """World (position, rotation) of each child link m2_1_1, m2, m2_1_3, m1 for angles E D C B."""
    pos, rot = np.zeros(3), np.eye(3)
    poses = []
    for frame, angle in zip(CHAIN, np.asarray(q, dtype=float), strict=True):
        t, r = joint_transform(frame, float(angle))
        pos, rot = pos + rot @ t, rot @ r
        poses.append((pos.copy(), rot.copy()))
    return poses


def tool_position(q: np.ndarray) -> np.ndarray:
    """Tool centre point in the base frame (m)."""
    pos, rot = link_poses(q)[-1]
    return pos + rot @ np.array([0.0, 0.0, TCP_OFFSET_M])


def axis_rotations(axis: tuple[float, float, float], angles: np.ndarray) -> np.ndarray:
    """`axis_rotation` for N angles at once: N x 3 x 3."""
    x, y, z = axis
    c, s = np.cos(angles), np.sin(angles)
    C = 1.0 - c
    return np.stack(
        [
            np.stack([c + x * x * C, x * y * C - z * s, x * z * C + y * s], axis=-1),
            np.stack([y * x * C + z * s, c + y * y * C, y * z * C - x * s], axis=-1),
            np.stack([z * x * C - y * s, z * y * C + x * s, c + z * z * C], axis=-1),
        ],
        axis=-2,
    )


def tool_positions(q: np.ndarray) -> np.ndarray:
    """`tool_position` of N poses at once (N x 4 angles E D C B -> N x 3, m): what a search
    over the workspace evaluates (reach_driver.ik)."""
    qs = np.atleast_2d(np.asarray(q, dtype=float))
    pos = np.zeros((len(qs), 3))
    rot = np.broadcast_to(np.eye(3), (len(qs), 3, 3))
    for i, frame in enumerate(CHAIN):
        yaw = axis_rotation((0.0, 0.0, 1.0), frame.yaw)
        pos = pos + rot @ np.asarray(frame.xyz, dtype=float)
        rot = rot @ (yaw @ axis_rotations(frame.axis, qs[:, i]))
    return pos + rot @ np.array([0.0, 0.0, TCP_OFFSET_M])


def tool_jacobian(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tool centre point (m), 3 x 4 position Jacobian (m/rad)) at angles E D C B.

    Column i is a_i x (p - o_i): joint i's axis in the base frame times the lever from its
    origin to the tool centre point. B's column is zero: the tool centre point lies on B's
    axis (tests/test_kinematics.py checks it against the simulator's Jacobian).
    """
    poses = link_poses(q)
    pos, rot = poses[-1]
    tcp = pos + rot @ np.array([0.0, 0.0, TCP_OFFSET_M])
    jac = np.empty((3, len(CHAIN)))
    for i, (frame, (origin, child_rot)) in enumerate(zip(CHAIN, poses, strict=True)):
        axis = child_rot @ np.asarray(frame.axis, dtype=float)
        jac[:, i] = np.cross(axis, tcp - origin)
    return tcp, jac
