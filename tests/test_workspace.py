"""Where the arm can reach: `ik.envelope` and `ik.nearest_reachable` on the driver's own chain,
`reach-driver workspace` (no arm needed) and what `move --xyz` says when it refuses a point."""

from __future__ import annotations

import json
import math
import re
from typing import NamedTuple

import numpy as np
import pytest

from protocol import Mode
from protocol.alpha5 import JOINTS
from protocol.models import ALPHA5, BRAVO7, ArmModel
from reach_driver.cli import Exit, main
from reach_driver.drawing import drawing_for
from reach_driver.ik import (
    TOLERANCE_MM,
    Envelope,
    UnreachableError,
    envelope,
    factory_limits,
    solve_or_refuse,
)
from reach_driver.kinematics import tool_position

LIMITS = factory_limits()
START = np.array([3.1, 1.7, 1.7, 3.1])


@pytest.fixture(scope="module")
def sampled() -> np.ndarray:
    """Tool centre points (mm) of 200 000 random poses inside the factory limits."""
    from reach_driver.kinematics import tool_positions

    rng = np.random.default_rng(5)
    q = rng.uniform(LIMITS[:, 0], LIMITS[:, 1], size=(200_000, 4))
    return tool_positions(q) * 1000.0


# ------------------------------------------------------------------ the kinematics


def test_the_batched_forward_kinematics_is_the_chain() -> None:
    from reach_driver.kinematics import tool_positions

    rng = np.random.default_rng(3)
    q = rng.uniform(LIMITS[:, 0], LIMITS[:, 1], size=(50, 4))
    np.testing.assert_allclose(tool_positions(q), [tool_position(p) for p in q], atol=1e-12)


def test_the_envelope_holds_every_pose_and_is_reached(sampled: np.ndarray) -> None:
    from reach_driver.ik import envelope

    env = envelope()
    radius = np.hypot(sampled[:, 0], sampled[:, 1])
    assert env.radius_mm[0] - 0.01 <= radius.min() and radius.max() <= env.radius_mm[1] + 0.01
    assert env.z_mm[0] - 0.01 <= sampled[:, 2].min() and sampled[:, 2].max() <= env.z_mm[1] + 0.01
    assert np.linalg.norm(sampled, axis=1).max() <= env.reach_mm + 0.01
    # and its bounds are where poses get: random ones come within a few mm of each
    assert radius.max() > env.radius_mm[1] - 5 and radius.min() < env.radius_mm[0] + 5
    assert sampled[:, 2].max() > env.z_mm[1] - 5 and sampled[:, 2].min() < env.z_mm[0] + 5
    np.testing.assert_array_equal(env.limits, LIMITS)


@pytest.mark.parametrize(
    "target",
    [(2000.0, 0.0, 0.0), (0.0, 0.0, -400.0), (50.0, -20.0, -350.0), (0.0, 0.0, 0.0)],
    ids=["far", "below", "below-off-axis", "the-base"],
)
def test_an_unreachable_point_gets_the_nearest_reachable_one(
    target: tuple[float, float, float], sampled: np.ndarray
) -> None:
    from reach_driver.ik import nearest_reachable

    sol = nearest_reachable(target, START, LIMITS)
    assert not sol.reachable
    assert np.all(sol.q >= LIMITS[:, 0]) and np.all(sol.q <= LIMITS[:, 1])
    point = tool_position(sol.q) * 1000.0
    np.testing.assert_allclose(sol.point_mm, point)
    assert sol.error_mm == pytest.approx(float(np.linalg.norm(point - target)))
    # no pose of 200 000 inside the limits gets nearer (the solver alone missed by 54 mm below)
    assert sol.error_mm <= float(np.linalg.norm(sampled - target, axis=1).min()) + 0.1
    with pytest.raises(UnreachableError) as refused:
        solve_or_refuse(target, START, LIMITS)
    np.testing.assert_allclose(refused.value.nearest_mm, point)
    np.testing.assert_allclose(refused.value.best, sol.q)


def test_a_reachable_point_is_solved_as_before() -> None:
    from reach_driver.ik import nearest_reachable

    q = np.array([1.2, 1.1, 2.0, 0.4])
    target = tool_position(q) * 1000.0
    sol = nearest_reachable(target.tolist(), START, LIMITS)
    assert sol.reachable and sol.error_mm <= TOLERANCE_MM
    assert sol.q[3] == START[3]  # B keeps its angle


# ------------------------------------------------------------------ reach-driver workspace


def _numbers(line: str) -> list[float]:
    return [float(v) for v in re.findall(r"-?\d+\.\d+", line)]


def test_workspace_needs_no_arm_and_prints_the_envelope(monkeypatch, capsys) -> None:
    from reach_driver.ik import envelope

    monkeypatch.delenv("REACH_PORT", raising=False)
    assert main(["workspace"]) == Exit.OK
    out = capsys.readouterr().out
    env = envelope()
    lines = out.splitlines()
    radius = next(x for x in lines if x.startswith("distance from the base's z axis"))
    height = next(x for x in lines if x.startswith("height z"))
    farthest = next(x for x in lines if x.startswith("distance from the base's origin"))
    assert _numbers(radius) == [round(v, 1) for v in env.radius_mm]
    assert _numbers(height) == [round(v, 1) for v in env.z_mm]
    assert _numbers(farthest) == [round(env.reach_mm, 1)]
    d = next(x for x in lines if x.split()[:1] == ["D"])
    assert _numbers(d)[:2] == [0.0175, 3.4034]  # the limits it used, rad then degrees
    assert "position limits used (factory)" in out


def test_workspace_json_and_a_margin_narrow_the_limits(capsys) -> None:
    from reach_driver.ik import envelope

    assert main(["workspace", "--json", "--position-margin", "0.1"]) == Exit.OK
    data = json.loads(capsys.readouterr().out)
    assert data["position_limits_rad"]["D"] == [pytest.approx(0.1175), pytest.approx(3.3034)]
    assert data["position_margin_rad"] == 0.1
    assert data["z_mm"][0] > envelope().z_mm[0] + 1.0  # the elbow folds less far
    assert "target" not in data


def test_workspace_xyz_gives_the_angles_of_a_reachable_point(capsys) -> None:
    target = tool_position(np.array([4.0, 1.0, 2.2, 1.0])) * 1000.0
    argv = ["workspace", "--xyz", *(f"{v:.3f}" for v in target), "--json"]
    assert main(argv) == Exit.OK
    point = json.loads(capsys.readouterr().out)["target"]
    assert point["reachable"] is True
    angles = point["angles_rad"]
    q = np.array([angles["E"], angles["D"], angles["C"], 0.0])
    assert np.linalg.norm(tool_position(q) * 1000.0 - target) <= TOLERANCE_MM
    assert main(argv[:-1]) == Exit.OK
    said = capsys.readouterr().out.splitlines()[-1]
    assert "mm is reachable at E " in said and "(B any angle)" in said, said


def test_workspace_xyz_out_of_reach_names_the_nearest_point_and_exits_3(capsys) -> None:
    assert main(["workspace", "--xyz", "0", "0", "-400", "--json"]) == Exit.LIMIT
    point = json.loads(capsys.readouterr().out)["target"]
    assert point["reachable"] is False
    a = point["angles_rad"]
    near = tool_position(np.array([a["E"], a["D"], a["C"], 0.0])) * 1000.0
    np.testing.assert_allclose(point["point_mm"], near, atol=0.01)
    assert point["distance_mm"] == pytest.approx(np.linalg.norm(near - [0, 0, -400]), abs=0.01)
    assert main(["workspace", "--xyz", "0", "0", "-400"]) == Exit.LIMIT
    said = capsys.readouterr().out.splitlines()[-1]
    assert said.startswith("(0.0, 0.0, -400.0) mm is out of reach; the nearest reachable point")
    assert f"{point['distance_mm']:.1f} mm away" in said


def test_a_non_finite_xyz_is_a_bad_command_line(capsys) -> None:
    with pytest.raises(SystemExit) as done:
        main(["workspace", "--xyz", "nan", "0", "0"])
    assert done.value.code == Exit.USAGE
    assert "must be a finite number" in capsys.readouterr().err


# ------------------------------------------------------------------ move --xyz


@pytest.mark.sim(speed=8.0)
def test_move_xyz_refusal_names_the_nearest_reachable_point(sim, capsys) -> None:
    q0 = sim.snapshot().q
    far = (0.0, 0.0, -400.0)
    code = main(["--port", str(sim.link), "move", "--xyz", *map(str, far)])
    err = capsys.readouterr().err
    assert code == Exit.LIMIT
    found = re.search(
        r"the nearest reachable point is \((\S+), (\S+), (\S+)\) mm, (\S+) mm away, at "
        r"E (\S+) D (\S+) C (\S+) B (\S+) rad",
        " ".join(err.split()),
    )
    assert found, err
    x, y, z, away, *angles = (float(v) for v in found.groups())
    near = tool_position(np.array(angles)) * 1000.0
    np.testing.assert_allclose([x, y, z], near, atol=1.0)  # printed to 0.1 mm, angles 1 mrad
    assert away == pytest.approx(np.linalg.norm(near - far), abs=1.0)
    assert away < 140.0  # the nearest, not where the solver gave up (189 mm)
    assert all(sim.firmware.mode(d) == Mode.STANDBY for d in JOINTS)  # nothing was sent
    assert np.max(np.abs(sim.snapshot().q - q0)) < 0.01


# ------------------------------------------------------------------ any model: the Bravo 7
#
# Independent of the driver's chains: the Alpha's URDF frames (reach_sim_bridge/model/README.md)
# and the Bravo's datasheet DH table (tests/test_bravo7_model.py, bravo7.md), typed in. Each arm
# stretched out straight from its shoulder is its farthest from the yaw axis (horizontal) and its
# highest (upright): its shoulder's offset plus the lengths of its rigid segments, shoulder to
# elbow, elbow to wrist pitch, wrist pitch to the tool centre point.


class Stretch(NamedTuple):
    """An arm stretched out straight from its shoulder (mm)."""

    shoulder_offset: float  # the shoulder's axis from the yaw axis
    shoulder_height: float  # above the base frame
    segments: tuple[float, ...]  # rigid lengths: shoulder to elbow to wrist pitch to tool

    @property
    def radius(self) -> float:
        return self.shoulder_offset + sum(self.segments)

    @property
    def height(self) -> float:
        return self.shoulder_height + sum(self.segments)


ALPHA5_STRETCH = Stretch(
    shoulder_offset=20.0,  # D's axis from E's
    shoulder_height=14.0 + 33.0,
    segments=(math.hypot(40.0, 145.3), math.hypot(20.0, 33.0 + 99.75 + 40.0)),
)
BRAVO7_STRETCH = Stretch(
    shoulder_offset=46.0,  # a1: F's axis from G's
    shoulder_height=41.45 + 117.48,  # d0 - d1
    segments=(
        math.hypot(5.2, 290.77),  # a2
        math.hypot(160.26, 40.8 + 40.8),  # d4 along the forearm, a3 + a4 across it
        math.hypot(224.16 + 120.0, 40.8),  # d6 + the tool's 120 mm, a5 across
    ),
)
BRAVO7_LIMITS = np.array([BRAVO7.position_limits[d] for d in BRAVO7.joints])


def _dh_tool_mm(q: np.ndarray) -> np.ndarray:
    """The Bravo's tool centre point (mm) by the datasheet's DH table, not the driver's chain."""
    from test_bravo7_model import dh_frames

    return dh_frames(np.asarray(q, dtype=float))["tcp"][:3, 3] * 1000.0


@pytest.fixture(scope="module")
def bravo_envelope() -> Envelope:
    return envelope(BRAVO7_LIMITS, drawing_for(BRAVO7))


@pytest.mark.parametrize(
    ("model", "facts"),
    [(ALPHA5, ALPHA5_STRETCH), (BRAVO7, BRAVO7_STRETCH)],
    ids=["alpha5", "bravo7"],
)
def test_the_farthest_and_highest_reach_are_the_arm_stretched_out(
    model: ArmModel, facts: Stretch
) -> None:
    limits = np.array([model.position_limits[d] for d in model.joints])
    env = envelope(limits, drawing_for(model))
    assert env.radius_mm[1] == pytest.approx(facts.radius, abs=0.01)
    assert env.z_mm[1] == pytest.approx(facts.height, abs=0.01)
    assert env.radius_mm[0] == pytest.approx(0.0, abs=0.01)  # the tool over the yaw axis


def test_the_bravos_bounds_are_its_poses_by_the_datasheet(bravo_envelope: Envelope) -> None:
    env = bravo_envelope
    assert env.axis_mm == pytest.approx((67.5, 0.0))  # a0: G's axis off the base frame's
    measures = {
        "radius_min": lambda p: math.hypot(p[0] - 67.5, p[1]),
        "radius_max": lambda p: math.hypot(p[0] - 67.5, p[1]),
        "z_min": lambda p: p[2],
        "z_max": lambda p: p[2],
        "reach": lambda p: float(np.linalg.norm(p)),
    }
    bounds = {
        "radius_min": env.radius_mm[0],
        "radius_max": env.radius_mm[1],
        "z_min": env.z_mm[0],
        "z_max": env.z_mm[1],
        "reach": env.reach_mm,
    }
    for name, measure in measures.items():
        q = env.poses[name]
        assert np.all(q >= BRAVO7_LIMITS[:, 0]) and np.all(q <= BRAVO7_LIMITS[:, 1]), name
        assert measure(_dh_tool_mm(q)) == pytest.approx(bounds[name], abs=0.01), name


def test_the_bravos_envelope_holds_every_pose(bravo_envelope: Envelope) -> None:
    rng = np.random.default_rng(7)
    q = rng.uniform(BRAVO7_LIMITS[:, 0], BRAVO7_LIMITS[:, 1], size=(3000, 6))
    p = np.array([_dh_tool_mm(x) for x in q])
    radius = np.hypot(p[:, 0] - 67.5, p[:, 1])
    env = bravo_envelope
    assert env.radius_mm[0] - 0.01 <= radius.min() and radius.max() <= env.radius_mm[1] + 0.01
    assert env.z_mm[0] - 0.01 <= p[:, 2].min() and p[:, 2].max() <= env.z_mm[1] + 0.01
    assert np.linalg.norm(p, axis=1).max() <= env.reach_mm + 0.01


def test_workspace_for_the_bravo_prints_its_envelope_and_limits(capsys) -> None:
    assert main(["--arm", "bravo7", "workspace"]) == Exit.OK
    out = capsys.readouterr().out
    lines = out.splitlines()
    radius = next(x for x in lines if x.startswith("distance from G's axis (at x 67.5 y 0.0)"))
    assert _numbers(radius)[-2:] == [0.0, round(BRAVO7_STRETCH.radius, 1)]
    assert "G sets the bearing; B turns the tool about its own axis" in " ".join(out.split())
    rows = [x.split()[0] for x in lines if len(x.split()) == 5 and x.split()[0] in "GFEDCB"]
    assert rows == ["G", "F", "E", "D", "C", "B"]
    f = next(x for x in lines if x.split()[:1] == ["F"])
    assert _numbers(f)[:2] == [0.0, 3.2]


def test_workspace_for_the_bravo_json_margin_and_a_reachable_point(capsys) -> None:
    q = np.array([2.0, 1.2, 1.9, 2.5, 1.4, 0.7])
    target = _dh_tool_mm(q)
    argv = ["--arm", "bravo7", "workspace", "--position-margin", "0.1", "--json", "--xyz"]
    assert main([*argv, *(f"{v:.3f}" for v in target)]) == Exit.OK
    data = json.loads(capsys.readouterr().out)
    assert data["position_limits_rad"]["F"] == [pytest.approx(0.1), pytest.approx(3.1)]
    assert data["axis_mm"] == [67.5, 0.0]
    point = data["target"]
    assert point["reachable"] is True and set(point["angles_rad"]) == {"G", "F", "E", "D", "C"}
    angles = np.array([*point["angles_rad"].values(), 0.0])  # B any angle
    assert all(0.1 - 1e-9 <= v <= 3.1 + 1e-9 for v in angles[1:3])
    assert np.linalg.norm(_dh_tool_mm(angles) - target) <= TOLERANCE_MM


def test_workspace_for_the_bravo_names_the_nearest_point_and_exits_3(capsys) -> None:
    far = np.array([0.0, 0.0, -1000.0])  # under the base, past the arm hanging down
    assert main(["--arm", "bravo7", "workspace", "--json", "--xyz", *map(str, far)]) == Exit.LIMIT
    point = json.loads(capsys.readouterr().out)["target"]
    assert point["reachable"] is False
    near = _dh_tool_mm(np.array([*point["angles_rad"].values(), 0.0]))
    np.testing.assert_allclose(point["point_mm"], near, atol=0.01)
    assert point["distance_mm"] == pytest.approx(np.linalg.norm(near - far), abs=0.01)
    # the nearest inside the limits: no pose of 3000 random ones gets nearer
    rng = np.random.default_rng(11)
    q = rng.uniform(BRAVO7_LIMITS[:, 0], BRAVO7_LIMITS[:, 1], size=(3000, 6))
    sampled = np.array([_dh_tool_mm(x) for x in q])
    assert point["distance_mm"] <= float(np.linalg.norm(sampled - far, axis=1).min()) + 0.1
    assert main(["--arm", "bravo7", "workspace", "--xyz", *map(str, far)]) == Exit.LIMIT
    said = capsys.readouterr().out.splitlines()[-1]
    assert "mm is out of reach; the nearest reachable point is" in said
    assert said.endswith("rad (B any angle)") and " G " in said
