"""The lambda controller: a model-based law whose gains come from the arm's twin and latency.

What it must do: predict the arm exactly through the commands in flight when its twin is the
arm, drive a frictionless arm with two periods of latency to its goal without overshoot where
the distilled actor overshoots, refuse bad settings, and take its twin from a file, a dict or a
campaign (`tools/robustness.py --twin`).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from policy.campaigns.direct import DirectArm
from policy.controllers.ddpg_distilled import make_controller as make_distilled
from policy.controllers.lambda_control import LambdaConfig, LambdaController, make_controller
from policy.tasks.envelope import corners
from policy.tasks.episodes import Episode, EpisodeResult, RunConfig
from reach_driver.controllers import ControlState, load_controller
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams, ParamsFileError
from reach_sim_bridge.model.sensors import SensorNoise
from reach_sim_bridge.model.twin import FittedTwin, read_twin

T = 0.05
ROOT = Path(__file__).resolve().parents[1]


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="noise_q"):
        LambdaConfig(noise_q=0.0)
    with pytest.raises(ValueError, match="lambda_factor"):
        LambdaConfig(lambda_factor=-1.0)
    with pytest.raises(ValueError, match="rate_hz"):
        LambdaConfig(rate_hz=0.0)
    with pytest.raises(ValueError, match="unknown lambda options.*lamda"):
        make_controller(lamda=2.0)
    with pytest.raises(ValueError, match="frictionlos"):
        make_controller(params={"frictionlos": [0, 0, 0, 0]})


def test_the_twin_comes_from_a_file_a_dict_or_the_registry(tmp_path: Path) -> None:
    path = tmp_path / "arm.json"
    path.write_text(json.dumps({"frictionloss": [0.0, 0.1, 0.2, 0.01]}))
    from_file = make_controller(params=str(path), latency_periods=1.5)
    np.testing.assert_allclose(from_file.friction, [0.0, 0.1, 0.2, 0.01])
    assert from_file.config.latency_periods == 1.5
    from_dict = make_controller(params={"torque_scale": [1.0, 0.5, 1.0, 1.0]})
    nominal = make_controller()
    np.testing.assert_allclose(from_dict.torque_per_mA[1], 0.5 * nominal.torque_per_mA[1])
    assert isinstance(load_controller("lambda", latency_periods=2.0), LambdaController)
    identified = ROOT / "tests" / "data" / "identified_seed11.json"  # delay 2.5 ms
    assert make_controller(params=str(identified)).config.latency_periods == pytest.approx(
        0.0499, abs=1e-4
    )
    assert make_controller(params=str(identified), latency_periods=1.0).config.latency_periods == 1


def test_the_measured_delay_reaches_lambda_however_the_twin_is_given() -> None:
    """A fitted twin's delay is the latency whether the twin comes as a file, as the file's
    dict (its ``_fit`` with it) or as a `FittedTwin`; an explicit latency wins."""
    identified = ROOT / "tests" / "data" / "identified_seed11.json"
    twin = read_twin(identified)
    assert twin.delay_s is not None
    expected = twin.delay_s * LambdaConfig().rate_hz
    given = {
        "file": make_controller(params=identified),
        "dict": make_controller(params=json.loads(identified.read_text())),
        "twin": make_controller(params=twin),
    }
    for how, ctrl in given.items():
        assert ctrl.config.latency_periods == pytest.approx(expected, rel=1e-12), how
        assert ctrl.params == twin.params, how
    assert make_controller(params=twin, latency_periods=0.5).config.latency_periods == 0.5
    assert make_controller(params=FittedTwin()).config.latency_periods == 0.0
    with pytest.raises(ParamsFileError, match=r"_fit.delay_s must be a number"):
        make_controller(params={"_fit": {"delay_s": "2 ms"}})


def test_the_prediction_through_the_commands_in_flight_is_the_arms_own() -> None:
    """With the arm as its twin, the state the controller predicts for when its command lands
    is the state the arm reaches under the commands still in flight (2 periods of latency)."""
    params = replace(ArmParams(), frictionloss=(0.0, 0.0, 0.0, 0.0))
    ctrl = LambdaController(params, LambdaConfig(latency_periods=2.0))
    sent = [np.array([300.0, -200.0, 150.0, 80.0]), np.array([-100.0, 250.0, -50.0, -60.0])]
    ctrl._sent.extend(sent)  # sent two periods and one period ago
    q0, v0 = np.array([2.0, 1.5, 1.2, 1.0]), np.array([0.3, -0.2, 0.1, 0.5])
    q_pred, v_pred = ctrl._run_twin(q0, v0, 0.0, 2 * T)
    arm = Alpha5Arm(params=params)
    arm.reset(q=q0, qdot=v0)
    arm.step(sent[0], n=25)  # the older command is in force for the first period
    arm.step(sent[1], n=25)
    np.testing.assert_allclose(q_pred, arm.q, atol=1e-9)
    np.testing.assert_allclose(v_pred, arm.qdot, atol=1e-9)


@pytest.mark.parametrize("latency", [1.5, 0.5, 2.5, 3.5])
def test_a_latency_of_half_periods_is_predicted_through(latency: float) -> None:
    """A latency whose horizon falls on the middle of a physics step (1.5 periods: 37.5 steps
    of 2 ms) runs the twin up to it, not into the command being computed: the controller acts
    (it raised on its first prediction) and drives the arm towards its goal."""
    ctrl = make_controller(latency_periods=latency)
    arm = Alpha5Arm()
    target = arm.q + np.array([0.2, -0.2, 0.2, 0.3])
    for k in range(40):
        command = ctrl.act(ControlState(arm.q, arm.qdot, k * T), target)
        assert np.all(np.isfinite(command))
        arm.step(command, n=25)
    assert np.max(np.abs(arm.q - target)) < 0.05


def _latent_frictionless_corner() -> tuple[ArmParams, tuple[float, float, float, float], float]:
    for v in corners().variants:
        f = v.factors
        if f["coulomb_edc"] == 0 and f["latency_periods"] == 2 and f["weak_joint"] < 0:
            return v.params, v.torque_scale, v.latency_periods
    raise AssertionError("the envelope has no frictionless corner at two periods of latency")


def test_a_latent_frictionless_arm_is_reached_without_the_overshoot_of_the_actor() -> None:
    """No Coulomb friction and two periods of latency: the distilled actor (trained on 0.7 N m and
    no latency) carries joints well through their goals; the lambda controller, told the
    arm, arrives without going 2 % past."""
    params, scale, latency = _latent_frictionless_corner()
    episode = Episode(
        start=np.array([1.0, 1.2, 2.4, 0.8]),
        target=np.array([3.0, 2.2, 1.4, 2.3]),
        torque_scale=np.asarray(scale),
    )
    config = RunConfig(seconds=8.0, params=params, latency_periods=latency)
    twin = replace(params, torque_scale=scale)
    lam = DirectArm().run(
        LambdaController(twin, LambdaConfig(latency_periods=latency)), episode, config, 0
    )
    distilled = DirectArm().run(make_distilled(), episode, config, 0)
    assert lam.metrics.reached and lam.metrics.at_rest
    assert lam.metrics.overshoot_pct < 2.0
    assert np.all(np.abs(lam.final_error) < 0.005)
    assert distilled.metrics.overshoot_pct > 5.0  # what the twin is worth here


def _noisy_small_step(
    standoff: float, seed: int = 0
) -> tuple[EpisodeResult, np.ndarray, LambdaController]:
    """A frictionless arm, its exact twin, three times the sensor's noise (6 mrad, 0.06
    rad/s) and a 0.06 rad step of C: a 2 % overshoot is 1.2 mrad, a fifth of the noise."""
    params = replace(ArmParams(), frictionloss=(0.0, 0.0, 0.0, 0.0))
    start = np.array([2.0, 1.5, 1.5, 1.5])
    episode = Episode(start=start, target=start + np.array([0.0, 0.0, 0.06, 0.0]))
    config = RunConfig(seconds=10.0, params=params, noise=SensorNoise(0.006, 0.06))
    ctrl = LambdaController(
        params, LambdaConfig(noise_q=0.006, noise_v=0.06, twin_error=0.0, standoff=standoff)
    )
    estimates: list[np.ndarray] = []
    act = ctrl.act

    def recording_act(state: ControlState, target: np.ndarray) -> np.ndarray:
        out = act(state, target)
        assert ctrl._q is not None
        estimates.append(ctrl._q.copy())
        return out

    ctrl.act = recording_act  # type: ignore[method-assign]
    result = DirectArm().run(ctrl, episode, config, seed)
    return result, np.array(estimates), ctrl


def test_at_rest_the_filter_averages_the_readings_noise_away() -> None:
    """With the arm as its twin the Kalman filter trusts the prediction: over the last 5 s
    its estimate of C is off by under a third of the readings' 6 mrad, and it says so."""
    result, estimates, ctrl = _noisy_small_step(standoff=5.0)
    n = min(len(estimates), result.trace.q.shape[0])
    off = estimates[100:n, 2] - result.trace.q[100:n, 2]
    assert off.std() < 0.002
    assert ctrl.estimate_std[2] < 0.002


def test_a_small_step_under_heavy_noise_stops_short_instead_of_crossing() -> None:
    """Aimed at the goal itself, the wander the noise leaves carries C 2 % past a small step;
    with the standoff (5 estimate deviations less the 2 % allowance, at most 0.6 of the 10
    mrad settling band) it stays on its own side, reached and settled."""
    head_on, _, _ = _noisy_small_step(standoff=0.0)
    short, _, _ = _noisy_small_step(standoff=5.0)
    assert head_on.metrics.overshoot_pct > 2.0
    m = short.metrics
    assert m.overshoot_pct < 2.0 and m.reached and m.at_rest
    final = short.final_error[2]
    assert 0.0 < final <= 0.0075  # short of the goal, by at most the standoff and some wander
    assert m.settling_time_s < 2.0


def test_on_the_bravo_the_twin_is_its_mjcf_and_every_joint_arrives_without_overshoot() -> None:
    """The same law on the Bravo 7's six joints (G F E D C B), its twin the Bravo's MJCF:
    each joint of the arm, read through the sensor's noise, ends within 10 mrad of its goal,
    none 2 % past it, at rest."""
    from protocol.models import BRAVO7
    from reach_sim_bridge.model.bravo7 import Bravo7Arm

    ctrl = load_controller("lambda", arm=BRAVO7)
    assert isinstance(ctrl, LambdaController) and ctrl.params == Bravo7Arm.nominal()
    arm = Bravo7Arm(seed=0)
    rng = np.random.default_rng(0)
    start = arm.q
    step = np.array([0.25, -0.3, 0.3, -0.35, 0.2, 0.45])
    target = start + step
    past = np.zeros(6)  # how far each joint went beyond its goal (rad)
    for k in range(int(6.0 / T)):
        state = ControlState(
            arm.q + rng.normal(0.0, 0.002, 6), arm.qdot + rng.normal(0.0, 0.02, 6), k * T
        )
        command = ctrl.act(state, target)
        assert command.shape == (6,)
        assert np.all(np.abs(command) <= np.array(BRAVO7.current_limits_mA))
        arm.step(command, n=int(round(T / arm.dt)))
        past = np.maximum(past, np.sign(step) * (arm.q - target))
    assert np.all(np.abs(arm.q - target) < 0.01), arm.q - target
    assert np.all(past < 0.02 * np.abs(step)), past / np.abs(step)
    assert np.all(np.abs(arm.qdot) < 0.01), arm.qdot


def test_on_the_bravo_an_alpha_arm_file_and_four_angles_are_refused() -> None:
    from protocol.models import BRAVO7

    with pytest.raises(
        ValueError, match=r"4 joints \(E D C B: a Reach Alpha 5\), not a Reach Bravo"
    ):
        make_controller(params={"frictionloss": [0.7, 0.7, 0.7, 0.075]}, model=BRAVO7)
    ctrl = make_controller(model=BRAVO7)
    with pytest.raises(ValueError, match=r"6 values \(G F E D C B\)"):
        ctrl.act(ControlState(np.zeros(4), np.zeros(4), 0.0), np.zeros(4))
