"""Where the arm can reach: `ik.envelope` and `ik.nearest_reachable` on the driver's own chain,
`reach-driver workspace` (no arm needed) and what `move --xyz` says when it refuses a point."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from protocol import Mode
from protocol.alpha5 import JOINTS
from reach_driver.cli import Exit, main
from reach_driver.ik import TOLERANCE_MM, UnreachableError, factory_limits, solve_or_refuse
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
