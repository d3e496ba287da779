"""`reach-driver` on a Reach Bravo 7: the virtual one (`reach-sim --arm bravo7`, in process)
over a real pty and UDP, the model found from the devices that answer or named by `--arm`.

Written from the facts (protocol/bravo7.py, reach_sim_bridge/model/bravo7.md): joints G F E
D C B are devices 0x07 to 0x02, the jaws 0x01 (mm); an Alpha 5 has no 0x06 or 0x07. Waits are
on the arm's reports and modes, bounded by the conftest deadlines.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import LOOPBACK, WATCHDOG_S, still_actor

from protocol import Mode
from protocol.models import ALPHA5, BRAVO7
from reach_driver.cli import Exit, main

pytestmark = pytest.mark.sim(model=BRAVO7, udp=LOOPBACK, speed=4.0)

DEVICES = {"G", "F", "E", "D", "C", "B", "A"}
JOINT_IDS = (7, 6, 5, 4, 3, 2)  # G F E D C B


def _status(argv: list[str]) -> int:
    """main's exit status, parse errors included (a traceback fails the test)."""
    try:
        return int(main(argv))
    except SystemExit as exc:
        return int(exc.code or 0)


def _untouched(sim) -> bool:
    return all(sim.firmware.mode(d) == Mode.STANDBY for d in (*JOINT_IDS, 1))


# -- 1: the model at connect -----------------------------------------------------------------


def test_info_finds_the_bravo_and_lists_its_seven_devices(sim, sim_port, capsys) -> None:
    code = main(["--port", sim_port, "info", "--json"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    info = json.loads(captured.out)
    assert info["arm"] == "bravo7"
    assert set(info["devices"]) == DEVICES
    g = info["devices"]["G"]
    assert g["device"] == 7
    assert g["limits"]["position"] == pytest.approx([0.0, 2 * np.pi], abs=1e-5)
    assert g["limits"]["current"] == pytest.approx([-2000.0, 2000.0])
    assert info["devices"]["A"]["limits"]["position"] == pytest.approx([0.0, 10.0])
    assert "arm: Reach Bravo 7 (A B C D E F G (0x01-0x07) answer)" in captured.err


def test_info_table_names_the_bravo_and_its_joint_order(sim, capsys) -> None:
    assert main(["--port", str(sim.link), "info"]) == Exit.OK
    out = capsys.readouterr().out
    flat = " ".join(out.split())  # a title or caption wider than the table wraps
    assert f"Reach Bravo 7 on {sim.link}: 7 device(s)" in flat
    assert "joints G F E D C B in rad and rad/s, the jaw A in mm and mm/s" in flat
    rows = [line.split()[0] for line in out.splitlines() if "(0x0" in line]
    assert rows[:7] == ["G", "F", "E", "D", "C", "B", "A"]


def test_arm_alpha5_on_the_bravo_is_refused_naming_what_answered(sim, capsys) -> None:
    code = _status(["--port", str(sim.link), "--arm", "alpha5", "move", "3", "1.5", "1.5", "3"])
    err = capsys.readouterr().err
    assert code == Exit.NO_ARM, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("wrong arm: ")
    assert "not a Reach Alpha 5" in err
    assert "A B C D E F G (0x01-0x07) answer" in err
    assert "--arm bravo7" in err
    assert _untouched(sim)


def test_arm_bravo7_on_an_alpha_is_refused_naming_the_silent_joints(sim_factory, capsys) -> None:
    alpha = sim_factory(model=ALPHA5)
    code = _status(["--port", str(alpha.link), "--arm", "bravo7", "info"])
    err = capsys.readouterr().err
    assert code == Exit.NO_ARM, err
    assert "not a Reach Bravo 7: A B C D E (0x01-0x05) answer, a Reach Alpha 5's" in err
    assert "F G (0x06-0x07) do not" in err
    assert "--arm alpha5" in err


def test_arm_bravo7_on_the_bravo_and_the_alpha_found_as_before(
    sim, sim_factory, tmp_path, capsys
) -> None:
    assert main(["--port", str(sim.link), "--arm", "bravo7", "info", "--json"]) == Exit.OK
    captured = capsys.readouterr()
    assert set(json.loads(captured.out)["devices"]) == DEVICES
    assert "arm:" not in captured.err  # named, not found: nothing to say
    alpha = sim_factory(model=ALPHA5, link=str(tmp_path / "alpha"))
    assert main(["--port", str(alpha.link), "info"]) == Exit.OK
    captured = capsys.readouterr()
    flat = " ".join(captured.out.split())
    assert f"Reach arm on {alpha.link}: 5 device(s)" in flat
    assert "joints E D C B in rad and rad/s" in flat
    assert "arm:" not in captured.err
    assert _status(["--port", str(alpha.link), "move", "G=1"]) == Exit.USAGE
    assert "no joint G of the Reach Alpha 5 on" in capsys.readouterr().err


# -- monitor -------------------------------------------------------------------------------


def test_monitor_streams_all_seven_devices(sim, sim_port, capsys) -> None:
    code = main(["--port", sim_port, "monitor", "--json", "--seconds", "1.2", "--rate", "20"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    rows = [json.loads(line) for line in captured.out.splitlines() if line.strip()]
    assert rows, captured.out
    last = rows[-1]["devices"]
    assert set(last) == DEVICES
    assert all(last[d]["rate_hz"] > 0 for d in DEVICES), last
    snap = sim.snapshot()
    reported = [last[letter]["position"] for letter in ("G", "F", "E", "D", "C", "B")]
    assert reported == pytest.approx(snap.q, abs=0.01)


def test_monitor_line_and_table_name_the_bravos_joints(sim, capsys) -> None:
    assert main(["--port", str(sim.link), "monitor", "--seconds", "1.2"]) == Exit.OK
    out = capsys.readouterr().out
    assert "position [rad, A mm] G " in out
    for name in ("G (0x07)", "F (0x06)", "B (0x02)", "A (0x01)"):
        assert name in out, out


# -- move ----------------------------------------------------------------------------------


def test_move_takes_six_angles_and_the_jaw(sim, sim_port, capsys) -> None:
    q0 = sim.snapshot().q
    target = q0 + np.array([0.2, -0.15, 0.2, -0.3, 0.15, 0.3])
    argv = ["--port", sim_port, "move", *map(str, target), "6", "--timeout", "60", "-q"]
    code = main(argv)
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    assert "reached within 0.02 rad: G " in captured.out
    snap = sim.snapshot()
    assert np.max(np.abs(snap.q - target)) < 0.03
    assert abs(snap.jaw_mm - 6.0) < 0.6
    assert all(sim.firmware.mode(d) == Mode.POSITION for d in (*JOINT_IDS, 1))


def test_move_by_joint_name_leaves_the_others_where_they_are(sim, capsys) -> None:
    q0 = sim.snapshot().q
    goal = q0[1] - 0.25  # F
    code = main(["--port", str(sim.link), "move", f"F={goal}", "--timeout", "60", "-q"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    q = sim.snapshot().q
    assert abs(q[1] - goal) < 0.03
    others = [0, 2, 3, 4, 5]
    assert np.max(np.abs(q[others] - q0[others])) < 0.03


@pytest.mark.parametrize(
    ("angles", "expected"),
    [
        (
            ["3", "1.5", "1.5", "3"],
            "move needs the six angles G F E D C B (rad) of the Reach Bravo 7",
        ),
        (["3", "1.5", "1.5", "3", "1.5"], "B (rad) of the Reach Bravo 7 on"),
        (["H=1"], "no joint H (Reach Alpha 5: E D C B, the jaw A; Reach Bravo 7: G F E"),
    ],
)
def test_move_with_the_wrong_angles_says_what_the_bravo_takes(
    sim, angles, expected, capsys
) -> None:
    code = _status(["--port", str(sim.link), "move", *angles])
    err = capsys.readouterr().err
    assert code == Exit.USAGE, err
    assert expected in err, err
    assert f"got {len(angles)}" in err or "=" in angles[0]
    assert "nothing was sent" in err or "or --xyz" in err
    assert "Traceback" not in err
    assert _untouched(sim)


def test_the_jaw_given_twice_is_refused(sim, capsys) -> None:
    q = sim.snapshot().q
    code = _status(["--port", str(sim.link), "move", *map(str, q), "5", "--jaw", "6"])
    err = capsys.readouterr().err
    assert code == Exit.USAGE, err
    assert "the jaw is given twice" in err
    assert _untouched(sim)


def test_max_current_counts_the_bravos_joints(sim, capsys) -> None:
    q = sim.snapshot().q
    argv = ["--port", str(sim.link), "--max-current", "300,300,300,300", "move", *map(str, q)]
    code = _status(argv)
    err = capsys.readouterr().err
    assert code == Exit.USAGE, err
    assert "six comma-separated (G,F,E,D,C,B) for the Reach Bravo 7" in err
    assert _untouched(sim)


def test_move_xyz_puts_the_bravos_tool_centre_point_there(sim, capsys) -> None:
    from reach_sim_bridge.model.bravo7 import Bravo7Arm

    twin = Bravo7Arm()  # the MJCF's own tool centre point: the sim's site, not the driver's
    here = np.array(twin.pose_at(sim.snapshot().q)[:3])
    goal = here + np.array([40.0, -30.0, 25.0])
    argv = ["--port", str(sim.link), "move", "--xyz", *map(str, goal), "--timeout", "60"]
    code = main([*argv, "-q"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    assert "tool centre point" in captured.out
    reached = np.array(twin.pose_at(sim.snapshot().q)[:3])
    assert np.linalg.norm(reached - goal) < 5.0, (reached, goal)  # mm: 0.02 rad per joint


def test_an_unreachable_point_is_refused_before_anything_moves(sim, capsys) -> None:
    code = _status(["--port", str(sim.link), "move", "--xyz", "3000", "0", "0"])
    err = capsys.readouterr().err
    assert code == Exit.LIMIT, err
    assert "out of reach" in err and "nothing was sent" in err
    assert _untouched(sim)
    # the nearest reachable point over the whole workspace, as `workspace --xyz` names it
    said = re.search(r"the nearest reachable point is \((.+?)\) mm, (\S+) mm away", err)
    assert said, err
    assert _status(["--arm", "bravo7", "workspace", "--xyz", "3000", "0", "0", "--json"]) == 3
    point = json.loads(capsys.readouterr().out)["target"]
    np.testing.assert_allclose([float(v) for v in said[1].split(", ")], point["point_mm"], atol=1)
    assert float(said[2]) == pytest.approx(point["distance_mm"], abs=1.0)


# -- 2: run ----------------------------------------------------------------------------------


def test_run_pid_reaches_its_targets_on_the_bravo_over_a_pty(sim, capsys) -> None:
    q0 = sim.snapshot().q
    target = q0 + np.array([0.25, -0.3, 0.3, -0.35, 0.2, 0.45])
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "pid", "--target", *map(str, target), "--seconds", "6", "--json"]
    code = main([*argv, "-q"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    out = json.loads(captured.out)
    assert out["arm"] == "bravo7" and out["ok"], out["error"]
    assert out["stopped_by"] == "duration"
    assert len(out["final_q"]) == 6
    assert np.max(np.abs(out["final_error"])) < 0.02, out["final_error"]
    assert out["metrics"]["reached"], out["metrics"]
    assert out["left_in"] == "zero_velocity (confirmed by the arm)"
    # the arm, not only the driver: where it is and the mode it was left in
    assert np.max(np.abs(sim.snapshot().q - target)) < 0.03
    assert all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in JOINT_IDS)


def test_run_ddpg_drives_the_bravo_with_a_bravo_actor(sim, tmp_path, capsys) -> None:
    """An actor trained for the Bravo (here one that asks for no current: the plumbing, not a
    policy) runs through the driver with six joints in and out."""
    weights = still_actor(tmp_path / "bravo_actor.npz", BRAVO7)
    target = sim.snapshot().q
    argv = ["--port", str(sim.link), "--arm", "bravo7", "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "ddpg", "--param", f"weights={weights}"]
    code = main([*argv, "--target", *map(str, target), "--seconds", "1", "--json", "-q"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    out = json.loads(captured.out)
    assert out["arm"] == "bravo7" and out["ok"], out["error"]
    assert len(out["final_q"]) == 6
    assert out["left_in"] == "zero_velocity (confirmed by the arm)"


@pytest.mark.sim(speed=1.0)  # ticks a loaded host skips at 4x would cost it the overshoot
def test_run_lambda_reaches_its_targets_on_the_bravo_over_a_pty(sim, capsys) -> None:
    """The model-based controller, its twin the Bravo's MJCF (the emulated arm's own):
    reached at rest, none 2 % past its goal."""
    q0 = sim.snapshot().q
    target = q0 + np.array([0.25, -0.3, 0.3, -0.35, 0.2, 0.45])
    argv = ["--port", str(sim.link), "--arm", "bravo7", "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "lambda", "--target", *map(str, target), "--seconds", "6"]
    code = main([*argv, "--json", "-q"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    out = json.loads(captured.out)
    assert out["arm"] == "bravo7" and out["ok"], out["error"]
    assert out["stopped_by"] == "duration"
    assert np.max(np.abs(out["final_error"])) < 0.02, out["final_error"]
    metrics = out["metrics"]
    assert metrics["reached"] and metrics["at_rest"] and metrics["overshoot_pct"] < 2.0, metrics
    assert out["left_in"] == "zero_velocity (confirmed by the arm)"
    assert np.max(np.abs(sim.snapshot().q - target)) < 0.02  # the arm's true angles
    assert all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in JOINT_IDS)


@pytest.mark.sim(speed=1.0)  # a solve takes up to 40 ms: a 4x arm's period is 12.5 ms
def test_run_mpc_reaches_its_targets_on_the_bravo_over_a_pty(sim, capsys) -> None:
    """The MPC, its prediction model the Bravo's MJCF and motors, its weights the Bravo's."""
    pytest.importorskip("casadi")
    q0 = sim.snapshot().q
    target = q0 + np.array([0.25, -0.3, 0.3, -0.35, 0.2, 0.45])
    argv = ["--port", str(sim.link), "--arm", "bravo7", "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "mpc", "--target", *map(str, target), "--seconds", "6"]
    code = main([*argv, "--json", "-q"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    out = json.loads(captured.out)
    assert out["arm"] == "bravo7" and out["ok"], out["error"]
    assert out["stopped_by"] == "duration"
    assert np.max(np.abs(out["final_error"])) < 0.02, out["final_error"]
    metrics = out["metrics"]
    assert metrics["reached"] and metrics["overshoot_pct"] < 5.0, metrics
    assert out["left_in"] == "zero_velocity (confirmed by the arm)"
    assert np.max(np.abs(sim.snapshot().q - target)) < 0.02  # the arm's true angles
    assert all(sim.firmware.mode(d) == Mode.ZERO_VELOCITY for d in JOINT_IDS)


def test_run_lambda_refuses_an_alpha_arm_file_on_the_bravo(sim, tmp_path, capsys) -> None:
    twin = tmp_path / "arm.json"
    twin.write_text('{"frictionloss": [0.7, 0.7, 0.7, 0.075]}')
    target = sim.snapshot().q
    argv = ["--port", str(sim.link), "run", "--controller", "lambda", "--param"]
    argv += [f"params={twin}", "--target", *map(str, target), "--seconds", "1"]
    code = _status(argv)
    err = capsys.readouterr().err
    assert code == Exit.USAGE, err
    flat = " ".join(err.split())
    assert "describes an arm of 4 joints (E D C B: a Reach Alpha 5), not a Reach Bravo 7" in flat
    assert "Traceback" not in err, err
    assert len([line for line in err.splitlines() if line.startswith("error:")]) == 1, err
    assert _untouched(sim)


def test_run_lambda_told_an_identified_bravo_reaches_its_targets(
    sim_factory, tmp_path, capsys
) -> None:
    """An arm file of the Bravo's six joints is its twin: the arm served is that Bravo (in
    air, F's friction half again the MJCF's) and lambda, told it, reaches at rest."""
    from policy.controllers.lambda_control import make_controller
    from reach_sim_bridge.model.arms import load_params
    from reach_sim_bridge.model.bravo7 import Bravo7Arm

    friction = list(Bravo7Arm.nominal().frictionloss)
    friction[1] *= 1.5
    path = tmp_path / "bravo.json"
    path.write_text(json.dumps({"water_density": 0.0, "frictionloss": friction}))
    told = make_controller(params=str(path), model=BRAVO7)
    assert told.params.water_density == 0.0 and told.params.frictionloss == tuple(friction)
    np.testing.assert_allclose(told.friction, friction)
    sim = sim_factory(model=BRAVO7, params=load_params(path, BRAVO7), speed=1.0)
    q0 = sim.snapshot().q
    target = q0 + np.array([0.25, -0.3, 0.3, -0.35, 0.2, 0.45])
    argv = ["--port", str(sim.link), "--arm", "bravo7", "--watchdog", str(WATCHDOG_S), "run"]
    argv += ["--controller", "lambda", "--param", f"params={path}"]
    argv += ["--target", *map(str, target), "--seconds", "6"]
    code = main([*argv, "--json", "-q"])
    captured = capsys.readouterr()
    assert code == Exit.OK, captured.err
    out = json.loads(captured.out)
    assert out["arm"] == "bravo7" and out["ok"], out["error"]
    metrics = out["metrics"]
    assert metrics["reached"] and metrics["at_rest"] and metrics["overshoot_pct"] < 2.0, metrics
    assert np.max(np.abs(sim.snapshot().q - target)) < 0.02  # the arm's true angles
    assert out["left_in"] == "zero_velocity (confirmed by the arm)"


def test_run_prints_the_bravos_joints_and_torque_constants(sim, capsys) -> None:
    target = sim.snapshot().q + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.2])
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller"]
    argv += ["pid", "--target", *map(str, target), "--seconds", "1", "-q"]
    assert main(argv) == Exit.OK
    out = capsys.readouterr().out
    rows = [line.split()[0] for line in out.splitlines() if line.strip()[:2] in JOINT_ROWS]
    assert rows[:6] == ["G", "F", "E", "D", "C", "B"]
    assert "N m/A (G F E D C B)" in out
    assert "arm left in zero_velocity (confirmed by the arm)" in out


JOINT_ROWS = {"G ", "F ", "E ", "D ", "C ", "B "}


@pytest.mark.parametrize(
    ("run", "expected"),
    [
        (["--controller", "pid", "--target", "3", "1.5", "1.5", "3"], "run --target needs the six"),
        (
            ["--controller", "ddpg", "--target", "3", "1.5", "1.5", "3", "1.5", "3"],
            "ddpg_actor.npz: the weights hold an actor for the Reach Alpha 5 (4 joints), not "
            "the Reach Bravo 7: drive a Reach Alpha 5 with it (reach-driver --arm alpha5) or "
            "train one for the Reach Bravo 7 (tools/train.py --arm bravo7); nothing was sent",
        ),
        (
            ["--controller", "ddpg-distilled", "--target", "3", "1.5", "1.5", "3", "1.5", "3"],
            "controller 'ddpg-distilled' drives the Reach Alpha 5 only, not the Reach Bravo 7",
        ),
        (
            ["--controller", "pid", "--target", "3", "1.5", "1.5", "3", "1.5", "3"]
            + ["--param", "kp=1,2,3,4"],
            "kp needs one value or 6 (joint order G F E D C B)",
        ),
    ],
)
def test_run_refuses_what_does_not_fit_the_bravo_before_anything_moves(
    sim, run, expected, capsys
) -> None:
    code = _status(["--port", str(sim.link), "run", *run, "--seconds", "1"])
    err = capsys.readouterr().err
    assert code == Exit.USAGE, err
    assert expected in err, err
    assert "Traceback" not in err
    assert _untouched(sim)


# -- 3: recordings ---------------------------------------------------------------------------


def test_a_bravo_run_recorded_reads_back_with_inspect_and_export(sim, tmp_path, capsys) -> None:
    record, table = tmp_path / "bravo.rrd", tmp_path / "bravo.csv"
    target = sim.snapshot().q + np.array([0.2, -0.2, 0.2, -0.2, 0.2, 0.3])
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller"]
    argv += ["pid", "--target", *map(str, target), "--seconds", "4", "--json", "-q"]
    assert main([*argv, "--record", str(record)]) == Exit.OK
    ran = json.loads(capsys.readouterr().out)
    assert main(["inspect", str(record), "--json"]) == Exit.OK
    seen = json.loads(capsys.readouterr().out)
    assert seen["arm"] == "bravo7" and seen["metadata"]["arm"] == "bravo7"
    assert seen["joints"] == ["G", "F", "E", "D", "C", "B"]
    assert seen["steps"] == ran["steps"] + 1  # and the state that ended the run
    np.testing.assert_allclose(seen["final_target"], target, atol=1e-9)
    np.testing.assert_allclose(seen["final_position"], ran["final_q"], atol=1e-9)
    assert seen["metrics"]["reached"] == ran["metrics"]["reached"] is True
    assert seen["diagnostics"]["devices"] == ["G", "F", "E", "D", "C", "B", "A"]
    assert seen["diagnostics"]["final_status"]["G"] == ["ok"]
    assert main(["inspect", str(record)]) == Exit.OK
    assert "final state of the Reach Bravo 7 (rad)" in capsys.readouterr().out
    assert main(["export", str(record), "--to", str(table)]) == Exit.OK
    header = table.read_text().splitlines()[0].split(",")
    assert header[2:8] == [f"q_{j}_rad" for j in "GFEDCB"]


def test_a_bravo_recording_draws_the_bravo_from_its_mjcf(sim, tmp_path, capsys) -> None:
    import warnings

    from rerun.chunk import RrdReader

    record = tmp_path / "bravo.rrd"
    argv = ["--port", str(sim.link), "monitor", "--seconds", "0.5", "--json"]
    assert main([*argv, "--record", str(record)]) == Exit.OK
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        entities = {str(c.entity_path) for c in RrdReader(record).stream().to_chunks()}
    chain = "/arm/link1/link2/link3/link4/link5/link6"
    assert {chain, f"{chain}/tcp", "/target/link1", "/joints/G/position"} <= entities
    assert "/arm/m2_1_1" not in entities  # not the Alpha's links
