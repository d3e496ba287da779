"""The MPC baseline: its model, its constraints, and closed-loop behaviour on the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from policy.campaigns.evaluation import DirectArm, Episode, RunConfig, evaluate, run_episode
from policy.controllers.mpc import MPCConfig, MPCController, make_controller, zoh_coefficients
from reach_driver.controllers import ControlState
from reach_sim_bridge.model.arm import Alpha5Arm, ArmParams
from reach_sim_bridge.model.motor import MotorModel


@pytest.fixture(scope="module")
def mpc() -> MPCController:
    return MPCController(MPCConfig(horizon=10))


def test_zoh_coefficients_match_a_fine_integration() -> None:
    inertia = np.array([0.14, 0.13, 0.12, 0.007])
    damping = np.array([2.4, 2.24, 0.82, 0.36])
    tau = np.array([3.0, -2.0, 1.0, 0.5])
    v0 = np.array([0.5, 0.0, -1.0, 0.2])
    phi_v, gam_v, phi_q, gam_q = zoh_coefficients(inertia, damping, 0.05)
    q, v, h = np.zeros(4), v0.copy(), 1e-6
    for _ in range(50_000):
        acc = (tau - damping * v) / inertia
        q += h * v + 0.5 * h * h * acc
        v += h * acc
    np.testing.assert_allclose(phi_v * v0 + gam_v * tau, v, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(phi_q * v0 + gam_q * tau, q, rtol=1e-4, atol=1e-8)


def test_options_are_checked() -> None:
    with pytest.raises(ValueError, match="unknown MPC options"):
        make_controller(horizn=10)
    with pytest.raises(ValueError, match="q_weight needs 4"):
        MPCConfig(q_weight=(1.0, 2.0))  # type: ignore[arg-type]  # wrong length on purpose
    with pytest.raises(ValueError, match="solver must be one of"):
        MPCConfig(solver="cplex")


def test_plan_respects_current_limits_and_back_emf_envelope(mpc: MPCController) -> None:
    mpc.reset()
    start = np.array([1.0, 1.0, 1.0, 1.0])
    mpc.act(ControlState(start, np.zeros(4), 0.0), np.array([5.0, 2.8, 2.8, 2.7]))
    plan = mpc.prediction
    assert plan is not None and plan.success
    motor = MotorModel()
    limit = motor.current_limits_mA / 1000
    assert np.all(np.abs(plan.u) <= limit + 1e-6)
    emf = motor.resistance * plan.u + motor.backemf_per_speed * plan.qdot
    assert np.all(np.abs(emf) <= motor.supply_voltage + 1e-4)
    # a long move on E: the plan runs at the top speed the supply allows, on the envelope
    assert emf[-1, 0] == pytest.approx(motor.supply_voltage, rel=1e-4)
    assert 1.10 < plan.qdot[-1, 0] < motor.no_load_speed()[0]


@pytest.mark.slow
def test_reaches_targets_near_the_speed_floor(mpc: MPCController) -> None:
    episodes = [
        Episode(np.array([1.0, 2.5, 0.8, 2.0]), np.array([4.5, 1.0, 2.2, 0.8])),
        Episode(np.array([5.0, 0.9, 2.6, 0.9]), np.array([2.0, 2.6, 0.7, 2.5])),
    ]
    ev = evaluate(mpc, episodes, RunConfig(seconds=8.0))
    for r in ev.results:
        assert r.metrics.reached
        assert r.metrics.rmse <= 1.5 * r.rmse_floor
        assert r.metrics.overshoot_pct < 5.0
        assert np.abs(r.final_error).max() < 0.005


@pytest.mark.slow
def test_offset_free_estimate_learns_an_unmodelled_torque() -> None:
    """The simulated arm is in air, the MPC's model in water: the estimate must converge to the
    missing gravity torque (up to what static friction takes, at most 0.7 N m but small when
    the arm arrives slowly) and the steady-state error vanish."""
    ctrl = MPCController(MPCConfig(horizon=10))
    target = np.array([3.5, 2.0, 1.0, 1.5])
    result = run_episode(
        ctrl,
        Episode(np.array([3.0, 2.5, 0.6, 1.0]), target),
        RunConfig(seconds=8.0),
        backend=DirectArm(lambda seed: Alpha5Arm(params=ArmParams().in_air())),
    )
    missing = Alpha5Arm(params=ArmParams().in_air()).gravity_torque(
        target
    ) - Alpha5Arm().gravity_torque(target)
    assert abs(missing[1]) > 0.1  # the test means something: a real mismatch on D
    np.testing.assert_allclose(ctrl.disturbance, missing, atol=0.05)
    assert np.abs(result.final_error).max() < 1e-3


@pytest.mark.slow
def test_does_not_press_into_a_joint_limit(mpc: MPCController) -> None:
    """Target beyond D's upper limit: the soft bound keeps the plan at the limit, so the arm
    rests there holding gravity instead of driving full current into the end stop."""
    mpc.reset()
    arm = Alpha5Arm()
    arm.reset(q=np.array([3.0, 3.0, 1.5, 1.5]))
    target = np.array([3.0, 3.7, 1.5, 1.5])
    for k in range(60):
        u = mpc.act(ControlState(arm.q, arm.qdot, 0.05 * k), target)
        arm.step(u, n=25)
    upper = arm.position_limits[1, 1]
    assert arm.q[1] == pytest.approx(upper, abs=0.01)
    assert abs(u[1]) < 100.0  # vs 600 mA if it pushed
    assert mpc.prediction is not None
    assert np.all(mpc.prediction.q[:, 1] <= upper + 0.005)


def test_solve_time_statistics_are_recorded(mpc: MPCController) -> None:
    n_before = len(mpc.solve_times)
    mpc.reset()
    mpc.act(ControlState(np.ones(4), np.zeros(4), 0.0), np.full(4, 1.2))
    stats = mpc.solve_time_stats()
    assert stats["n"] == n_before + 1
    assert 0 < stats["p50"] <= stats["p99"] <= stats["max"]


def test_on_the_bravo_every_joint_arrives_with_the_bravos_weights() -> None:
    """The same cost on the Bravo 7's six joints (G F E D C B), its model the Bravo's MJCF
    and motors: each joint of the arm, read through the sensor's noise, ends within 10 mrad
    of its goal and under 5 % past it, every command within the current limits."""
    from protocol.models import BRAVO7
    from reach_driver.controllers import load_controller
    from reach_sim_bridge.model.bravo7 import Bravo7Arm

    ctrl = load_controller("mpc", arm=BRAVO7)
    assert isinstance(ctrl, MPCController)
    assert ctrl.config.qdot_weight == (30.0,) * 6  # the Bravo's, not the Alpha's
    arm = Bravo7Arm(seed=0)
    rng = np.random.default_rng(0)
    step = np.array([0.25, -0.3, 0.3, -0.35, 0.2, 0.45])
    target = arm.q + step
    past = np.zeros(6)
    for k in range(120):  # 6 s at 20 Hz
        state = ControlState(
            arm.q + rng.normal(0.0, 0.002, 6), arm.qdot + rng.normal(0.0, 0.02, 6), k * 0.05
        )
        command = ctrl.act(state, target)
        assert np.all(np.abs(command) <= np.array(BRAVO7.current_limits_mA) + 1e-6)
        arm.step(command, n=25)
        past = np.maximum(past, np.sign(step) * (arm.q - target))
    assert np.all(np.abs(arm.q - target) < 0.01), arm.q - target
    assert np.all(past < 0.05 * np.abs(step)), past / np.abs(step)


def test_on_the_bravo_alpha_parameters_weights_and_angles_of_four_are_refused() -> None:
    from protocol.models import BRAVO7

    with pytest.raises(ValueError, match="describe a Reach Alpha 5"):
        make_controller(model=BRAVO7, params=ArmParams(frictionloss=(0.5, 0.5, 0.5, 0.05)))
    with pytest.raises(ValueError, match=r"r_weight needs 6 .*\(G F E D C B\)"):
        make_controller(model=BRAVO7, r_weight=(1.0, 1.0, 1.0, 1.0))
    ctrl = make_controller(model=BRAVO7, horizon=5)
    with pytest.raises(ValueError, match=r"6 values \(G F E D C B\)"):
        ctrl.act(ControlState(np.zeros(4), np.zeros(4), 0.0), np.zeros(4))
