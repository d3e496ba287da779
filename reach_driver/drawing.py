"""How the driver draws each arm model in its recordings: the kinematic chain, the link geoms
and the tool centre point, as data the driver carries (it may not import the simulator),
posed by the angles the arm reports.

The Alpha 5's are `reach_driver.kinematics.CHAIN` and `reach_driver.arm_geometry.GEOMS`; the
Bravo 7's `reach_driver.bravo7_drawing`, both generated from the MJCFs by
tools/gen_arm_geometry.py and checked against them by tests/test_recording_views.py.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver import bravo7_drawing
from reach_driver.arm_geometry import GEOMS, LinkGeom
from reach_driver.kinematics import (
    CHAIN,
    TCP_OFFSET_M,
    axis_rotation,
    axis_rotations,
    quat_rotation,
)

__all__ = ["DRAWINGS", "ArmDrawing", "drawing_for"]


@dataclass(frozen=True)
class ArmDrawing:
    """One model's drawing: per joint (the model's order) the link it moves, that link's
    origin and fixed rotation in the previous link's frame and its axis; every geom by link
    (the base's in the world's frame); the tool centre point in the last link's frame."""

    base_link: str
    links: tuple[str, ...]
    origins: tuple[np.ndarray, ...]
    rotations: tuple[np.ndarray, ...]  # before the joint turns
    axes: tuple[tuple[float, float, float], ...]
    geoms: tuple[LinkGeom, ...]
    tcp: np.ndarray

    def joint_transform(self, i: int, q: float) -> tuple[np.ndarray, np.ndarray]:
        """(translation, rotation) mapping link i's coordinates into its parent's at angle q."""
        return self.origins[i], self.rotations[i] @ axis_rotation(self.axes[i], q)

    def link_poses(self, q: Sequence[float] | np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """World (position, rotation) of each moving link at angles `q`."""
        pos, rot = np.zeros(3), np.eye(3)
        poses = []
        for i, angle in enumerate(np.asarray(q, dtype=float)):
            t, r = self.joint_transform(i, float(angle))
            pos, rot = pos + rot @ t, rot @ r
            poses.append((pos.copy(), rot.copy()))
        return poses

    def link_geoms(self, link: str) -> list[LinkGeom]:
        return [g for g in self.geoms if g.link == link]

    def tool_position(self, q: Sequence[float] | np.ndarray) -> np.ndarray:
        """The tool centre point in the base frame (m) at angles `q`."""
        pos, rot = self.link_poses(q)[-1]
        return pos + rot @ self.tcp

    def tool_positions(self, q: np.ndarray) -> np.ndarray:
        """`tool_position` of N poses at once (N x joints -> N x 3, m): what a search over
        the workspace evaluates (reach_driver.ik)."""
        qs = np.atleast_2d(np.asarray(q, dtype=float))
        pos = np.zeros((len(qs), 3))
        rot = np.broadcast_to(np.eye(3), (len(qs), 3, 3))
        for i, (origin, fixed, axis) in enumerate(
            zip(self.origins, self.rotations, self.axes, strict=True)
        ):
            pos = pos + rot @ origin
            rot = rot @ (fixed @ axis_rotations(axis, qs[:, i]))
        return pos + rot @ self.tcp

    @property
    def yaw_axis(self) -> tuple[np.ndarray, float]:
        """The axis the first joint turns the whole arm about: where it meets the base's x y
        plane (m), and +1 if a positive angle turns the arm anticlockwise seen from above, -1
        if clockwise. ValueError if that axis is not vertical (then no one angle sets the
        tool's bearing)."""
        pos, rot = self.link_poses(np.zeros(len(self.links)))[0]
        axis = rot @ np.asarray(self.axes[0], dtype=float)
        if abs(abs(float(axis[2])) - 1.0) > 1e-9:
            raise ValueError(f"the first joint's axis {axis.round(6).tolist()} is not vertical")
        return pos[:2].copy(), math.copysign(1.0, float(axis[2]))

    @property
    def positioning(self) -> tuple[int, ...]:
        """The joints that move the tool centre point: all but those whose axis runs through
        it (within 0.1 mm: the wrist roll, B on both arms), which only turn the tool."""
        q = np.zeros(len(self.links))
        tcp = self.tool_position(q)
        out = []
        for i, (pos, rot) in enumerate(self.link_poses(q)):
            axis = rot @ np.asarray(self.axes[i], dtype=float)
            off = tcp - pos
            if np.linalg.norm(off - axis * float(off @ axis)) > 1e-4:  # 0.1 mm
                out.append(i)
        return tuple(out)


def _alpha5() -> ArmDrawing:
    return ArmDrawing(
        base_link="m3_inline",
        links=tuple(f.child_link for f in CHAIN),
        origins=tuple(np.asarray(f.xyz, dtype=float) for f in CHAIN),
        # as kinematics.joint_transform turns them: the frame's yaw, then the joint
        rotations=tuple(axis_rotation((0.0, 0.0, 1.0), f.yaw) for f in CHAIN),
        axes=tuple(f.axis for f in CHAIN),
        geoms=GEOMS,
        tcp=np.array([0.0, 0.0, TCP_OFFSET_M]),
    )


def _bravo7() -> ArmDrawing:
    frames = bravo7_drawing.FRAMES
    return ArmDrawing(
        base_link=bravo7_drawing.BASE_LINK,
        links=tuple(f.link for f in frames),
        origins=tuple(np.asarray(f.pos, dtype=float) for f in frames),
        rotations=tuple(quat_rotation(f.quat_xyzw) for f in frames),
        axes=tuple(f.axis for f in frames),
        geoms=bravo7_drawing.GEOMS,
        tcp=np.asarray(bravo7_drawing.TCP, dtype=float),
    )


#: Each model's drawing, by `ArmModel.name`.
DRAWINGS: Mapping[str, ArmDrawing] = MappingProxyType(
    {ALPHA5.name: _alpha5(), BRAVO7.name: _bravo7()}
)


def drawing_for(model: ArmModel) -> ArmDrawing:
    """The model's drawing (ValueError naming the models drawn if it has none)."""
    try:
        return DRAWINGS[model.name]
    except KeyError:
        raise ValueError(
            f"no drawing of the {model.title} (drawn: {', '.join(DRAWINGS)})"
        ) from None
