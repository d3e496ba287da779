"""Arm parameter files (`--params FILE.json`): the format, its errors, and that the simulator,
the evaluation runner and training really use the arm a file describes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from policy.campaigns.evaluation import Episode, RunConfig, run_episode
from policy.rl.env import EnvConfig
from policy.rl.scoring import params_arm_factory
from reach_sim_bridge.cli import build_parser, config_from_args, main
from reach_sim_bridge.emulator.server import SimServer
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import (
    ArmParams,
    ParamsFileError,
    load_arm_params,
    save_arm_params,
)
from reach_sim_bridge.model.twin import (
    Combination,
    Estimate,
    FitMetadata,
    FittedTwin,
    Unidentified,
    read_twin,
    write_twin,
)

ROOT = Path(__file__).resolve().parents[1]


def _write(tmp_path: Path, data: Any, name: str = "arm.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(data), encoding="utf-8")
    return path


def test_a_subset_overrides_and_the_rest_stays_nominal(tmp_path: Path) -> None:
    path = _write(tmp_path, {"frictionloss": [1.5, 1.0, 0.5, 0.1], "water_density": 1025})
    params = load_arm_params(path)
    assert params.frictionloss == (1.5, 1.0, 0.5, 0.1)
    assert params.water_density == 1025.0
    nominal = ArmParams()
    assert params.armature == nominal.armature and params.damping == nominal.damping
    assert params.motors == nominal.motors


def test_round_trip_of_every_field(tmp_path: Path) -> None:
    params = ArmParams(
        wrist_continuous=True, gravity=(0.0, 9.81, 0.0), torque_scale=(0.25, 1.0, 1.0, 0.5)
    ).randomized(7)
    path = save_arm_params(params, tmp_path / "out" / "arm.json", extra={"_fit": {"r2": 0.99}})
    data = json.loads(path.read_text())
    assert set(data) == {*params.to_json_dict(), "_fit"}
    assert load_arm_params(path) == params
    assert ArmParams.from_json_dict(params.to_json_dict()) == params


def test_motor_tables_can_be_given_in_part(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        {"motors": {"efficiency": [0.8, 0.8, 0.8, 0.7]}, "jaw_motor": {"efficiency": 0.3}},
    )
    params = load_arm_params(path)
    assert params.motors.efficiency == (0.8, 0.8, 0.8, 0.7)
    assert params.motors.gear_ratio == ArmParams().motors.gear_ratio
    assert params.jaw_motor.efficiency == (0.3,)


def test_metadata_keys_are_ignored_but_plain_extra_keys_refused(tmp_path: Path) -> None:
    assert load_arm_params(_write(tmp_path, {"_fit": {"anything": 1}, "_comment": "x"})) == (
        ArmParams()
    )
    with pytest.raises(ValueError, match="start with '_'"):
        save_arm_params(ArmParams(), tmp_path / "x.json", extra={"fit": 1})


IDENTIFIED = ROOT / "tests" / "data" / "identified_seed11.json"


def test_a_fitted_twin_round_trips(tmp_path: Path) -> None:
    """`write_twin` then `read_twin` gives the same twin; `load_arm_params` reads the same
    file as its plain parameters."""
    params = ArmParams(torque_scale=(1.0, 0.25, 1.0, 1.0)).randomized(3)
    fit = FitMetadata(
        method="test",
        parameters={"armature[E]": Estimate(0.13, 1e-4), "delay_s": Estimate(0.004, 1e-4)},
        unidentifiable={
            "torque_scale[B]": Unidentified(1.0, "nothing anchors it"),
            "frictionloss[B]": Unidentified(
                0.3, "over the scale", Combination("frictionloss[B]/torque_scale[B]", 0.3, 0.01)
            ),
        },
        torque_scales={"B": {"status": "unidentifiable", "twin_value": 1.0}},
        identifiability={"B": {"parameters": ["frictionloss[B]"], "directions": []}},
        delay_s=0.0031,
        command_step_s=0.002,
        delay_offsets_ms={"E0-relay-P1": 0.25},
        quality_fitted={"validate/E": {"window": {"r2": 0.999, "rms_mrad": 0.5, "samples": 9}}},
        arm_seconds=None,
        log="arm.log.npz",
        fit_seconds=12.5,
        controller_gap=[{"controller": "pid", "episodes": 2}],
        other={"future_key": [1, 2]},
    )
    twin = FittedTwin(params, fit, {"_envelope": {"latency_periods": 1.5}})
    path = write_twin(twin, tmp_path / "twin.json")
    back = read_twin(path)
    assert back == twin
    assert back.delay_s == 0.0031
    assert back.fit is not None and back.fit.window_rms_mrad("validate/E") == 0.5
    assert back.fit.window_rms_mrad("validate/E", "nominal") is None
    assert load_arm_params(path) == params
    assert FittedTwin.from_json_dict(json.loads(path.read_text())) == twin
    assert read_twin(save_arm_params(params, tmp_path / "plain.json")) == FittedTwin(params)


def test_an_identification_file_loads_as_a_twin_and_writes_back_the_same() -> None:
    """A file tools/identify.py wrote (before the typed twin existed) reads as a `FittedTwin`
    whose fit has every figure of its ``_fit``, and writes back the same ``_fit``."""
    data = json.loads(IDENTIFIED.read_text())
    twin = read_twin(IDENTIFIED)
    assert twin.params == load_arm_params(IDENTIFIED)
    assert twin.fit is not None
    assert twin.delay_s == data["_fit"]["delay_s"]
    assert (
        twin.fit.parameters["armature[E]"].sigma
        == (data["_fit"]["parameters"]["armature[E]"]["sigma"])
    )
    assert twin.fit.controller_gap == data["_fit"]["controller_gap"]
    assert twin.to_json_dict()["_fit"] == data["_fit"]
    assert list(twin.to_json_dict()["_fit"]) == list(data["_fit"])


def test_a_twin_given_as_a_dict_keeps_its_fit_or_says_what_is_wrong(tmp_path: Path) -> None:
    twin = FittedTwin.from_json_dict({"damping": [1, 1, 1, 0.1], "_fit": {"delay_s": 0.002}})
    assert twin.params.damping == (1.0, 1.0, 1.0, 0.1) and twin.delay_s == 0.002
    assert twin.fit is not None and twin.fit.parameters == {}  # the rest: not known
    assert FittedTwin.from_json_dict({"_comment": "x"}).fit is None
    for fit, message in [
        ({"delay_s": "2 ms"}, r"_fit.delay_s must be a number"),
        ({"delay_s": -0.001}, r"delay_s must be a finite number >= 0"),
        ([0.002], r"_fit must be an object"),
        ({"parameters": {"armature[E]": {"value": 0.1}}}, r"armature\[E\].sigma"),
        ({"quality_fitted": {"validate/E": {"window": 1}}}, r"quality_fitted.validate/E"),
    ]:
        with pytest.raises(ParamsFileError, match=message):
            FittedTwin.from_json_dict({"_fit": fit}, where="arm.json")
    path = _write(tmp_path, {"_fit": {"delay_s": "2 ms"}})
    with pytest.raises(ParamsFileError, match=str(path)):
        read_twin(path)
    with pytest.raises(ValueError, match="metadata keys"):
        FittedTwin(metadata={"comment": "x"})


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"frictionlos": [1, 1, 1, 1]}, r"unknown key 'frictionlos'; did you mean 'frictionloss'"),
        ({"armatur": [1, 1, 1, 1]}, r"did you mean 'armature'"),
        ({"zzzz": 1}, r"unknown key 'zzzz'; known keys: armature"),
        ({"damping": [1, 2, 3]}, r"damping needs 4 values \(E D C B\), got 3"),
        ({"damping": 2.0}, r"damping must be a list of 4 numbers .* got the number 2.0"),
        ({"damping": [1, 2, "3", 4]}, r"damping\[2\] must be a number, got the string '3'"),
        ({"link_mass_kg": [True, 1, 1, 1]}, r"link_mass_kg\[0\] must be a number, got a boolean"),
        ({"gravity": [0, -9.81]}, r"gravity needs 3 values"),
        ({"water_density": "sea"}, r"water_density must be a number, got the string 'sea'"),
        ({"fluid_drag": 1}, r"fluid_drag must be true or false, got the number 1"),
        ({"motors": [1, 2]}, r"motors must be an object"),
        ({"motors": {"gear": [1, 1, 1, 1]}}, r"unknown key 'gear'; did you mean 'gear_ratio'"),
        ({"motors": {"efficiency": [1, 1, 1, 1.5]}}, r"efficiency is a fraction"),
        ({"frictionloss": [-0.1, 0.7, 0.7, 0.07]}, r"frictionloss must be >= 0"),
        ({"damping": [2, -1, 1, 1]}, r"damping must be >= 0"),
        ({"armature": [0.1, 0.0, 0.1, 0.01]}, r"armature must be > 0"),
        ({"link_mass_kg": [0.1, -0.3, 0.1, 0.3]}, r"link_mass_kg must be > 0"),
        ({"torque_scale": [1, 1, 1.2, 1]}, r"torque_scale must be in \[0, 1\]"),
        ({"torque_scale": [1, 0, 1, 1]}, r"torque_scale of D must be in \(0, 1\]"),
        ({"current_limits_mA": [600, 600, 0, 300]}, r"current_limits_mA of C must be > 0"),
        ({"supply_voltage": 0}, r"supply_voltage must be a finite number > 0"),
        ({"water_density": 1e6}, r"water_density is kg/m\^3"),
        ({"gravity": [0, 0, -98.1]}, r"not an Earth gravity"),
        ([1, 2, 3], r"expected a JSON object of ArmParams fields, got a list of 3"),
    ],
)
def test_errors_name_the_file_and_the_key(tmp_path: Path, data: Any, message: str) -> None:
    path = _write(tmp_path, data)
    with pytest.raises(ParamsFileError, match=message) as info:
        load_arm_params(path)
    assert str(path) in str(info.value)


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ParamsFileError, match="cannot read arm parameters"):
        load_arm_params(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{frictionloss: 1}")
    with pytest.raises(ParamsFileError, match="not valid JSON"):
        load_arm_params(bad)


def test_reach_sim_serves_the_arm_of_the_file(tmp_path: Path) -> None:
    friction = [1.4, 0.35, 0.9, 0.05]
    path = _write(tmp_path, {"frictionloss": friction, "torque_scale": [1, 1, 0.5, 1]})
    config = config_from_args(build_parser().parse_args(["--params", str(path)]))
    server = SimServer(config)
    assert isinstance(server.arm, Alpha5Arm)
    assert server.arm.params.frictionloss == tuple(friction)
    assert np.allclose(server.arm.model.dof_frictionloss[:4], friction)
    # --torque-scale multiplies the file's own torque scale
    config = config_from_args(
        build_parser().parse_args(["--params", str(path), "--torque-scale", "C=0.5"])
    )
    assert SimServer(config).arm.torque_scale.tolist() == [1.0, 1.0, 0.25, 1.0]
    # a power cycle brings back the same arm
    server.power_cycle()
    assert isinstance(server.arm, Alpha5Arm)
    assert server.arm.params.frictionloss == tuple(friction)


def test_reach_sim_perturbs_around_the_file_arm(tmp_path: Path) -> None:
    heavy = [3.0, 3.0, 3.0, 0.3]
    path = _write(tmp_path, {"frictionloss": heavy})
    args = ["--params", str(path), "--randomize-params", "4"]
    arm = SimServer(config_from_args(build_parser().parse_args(args))).arm
    assert isinstance(arm, Alpha5Arm)
    got = np.asarray(arm.params.frictionloss)
    assert np.all(got >= 0.8 * np.asarray(heavy) - 1e-9)
    assert np.all(got <= 1.2 * np.asarray(heavy) + 1e-9)
    assert not np.allclose(got, heavy)


def test_the_served_arm_moves_differently(tmp_path: Path) -> None:
    """The same current on E moves a high-friction arm from the file far less."""

    def travel(argv: list[str]) -> float:
        server = SimServer(config_from_args(build_parser().parse_args(argv)))
        arm = server.arm
        q0 = arm.q.copy()
        for _ in range(25):
            arm.step(np.array([80.0, 0.0, 0.0, 0.0]), n=10)
        return float(arm.q[0] - q0[0])

    path = _write(tmp_path, {"frictionloss": [1.5, 0.7, 0.7, 0.075]})
    nominal, sticky = travel([]), travel(["--params", str(path)])
    assert nominal > 0.05
    assert sticky < 0.2 * nominal


def test_reach_sim_rejects_a_bad_file_before_serving(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path, {"dampng": [1, 1, 1, 1]})
    with pytest.raises(SystemExit) as info:
        main(["--params", str(path)])
    assert info.value.code == 2
    assert "did you mean 'damping'" in capsys.readouterr().err


def test_evaluation_runs_on_the_file_arm(tmp_path: Path) -> None:
    class Push:
        def reset(self) -> None:
            pass

        def act(self, state: Any, target: np.ndarray) -> np.ndarray:
            return np.array([80.0, 0.0, 0.0, 0.0])

    episode = Episode(start=np.array([3.0, 1.5, 1.5, 1.5]), target=np.array([3.5, 1.5, 1.5, 1.5]))
    sticky = ArmParams(frictionloss=(1.5, 0.7, 0.7, 0.075))
    free = run_episode(Push(), episode, RunConfig(seconds=0.5))
    held = run_episode(Push(), episode, RunConfig(seconds=0.5, params=sticky))
    moved = free.trace.q[-1, 0] - 3.0
    assert moved > 0.05 and held.trace.q[-1, 0] - 3.0 < 0.2 * moved
    assert RunConfig(params=sticky).to_dict()["params"]["frictionloss"] == [1.5, 0.7, 0.7, 0.075]
    assert "params" not in RunConfig().to_dict()


def test_evaluate_and_train_take_params(tmp_path: Path) -> None:
    path = _write(tmp_path, {"frictionloss": [1.5, 0.7, 0.7, 0.075]})
    factory = params_arm_factory(path)
    arm = factory(EnvConfig())
    assert arm.params.frictionloss == (1.5, 0.7, 0.7, 0.075)
    assert params_arm_factory(None) is None
    bad = _write(tmp_path, {"frictionloss": [1, 1]}, "bad.json")
    with pytest.raises(SystemExit, match="--params: .*needs 4 values"):
        params_arm_factory(bad)
    # tools/evaluate.py takes --params, reads the file and refuses a bad one with exit 2
    argv = ["--controller", "pid", "--random", "1", "--out", str(tmp_path / "o.json")]
    evaluate = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "evaluate.py"), *argv, "--params", str(bad)]
        + ["--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert evaluate.returncode == 2, evaluate.stdout + evaluate.stderr
    assert "needs 4 values" in evaluate.stderr, evaluate.stderr
