"""The PID baseline (policy/controllers/pid.py): its rules on a toy plant, its entry point, and
reaching targets on the virtual arm in current mode without large overshoot."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import LOOPBACK, udp_url

from policy.controllers.pid import PIDController, PIDGains, make_controller
from protocol.models import BRAVO7
from reach_driver import (
    ArmClient,
    ControlLoop,
    ControlState,
    DriverError,
    StepRecord,
    load_controller,
    open_transport,
)

LIMITS = np.array([600.0, 600.0, 600.0, 300.0])


def state(q, qdot=(0, 0, 0, 0), t=0.0) -> ControlState:
    return ControlState(np.asarray(q, float), np.asarray(qdot, float), t)


def test_output_is_clamped_to_each_joints_current_limit() -> None:
    pid = make_controller()
    out = pid.act(state([1, 1, 1, 1]), np.array([3.0, -1.0, 1.0, 4.0]))
    np.testing.assert_array_equal(out, [600.0, -600.0, 0.0, 300.0])


def test_derivative_acts_on_the_measurement_so_a_new_target_gives_no_kick() -> None:
    gains = PIDGains(kp=np.full(4, 100.0), ki=np.zeros(4), kd=np.full(4, 50.0))
    pid = PIDController(gains, current_limits_mA=1e6)
    a = pid.act(state([1, 1, 1, 1], qdot=[0.1, 0, 0, 0], t=0.0), np.ones(4))
    b = pid.act(state([1, 1, 1, 1], qdot=[0.1, 0, 0, 0], t=0.05), np.full(4, 1.2))
    np.testing.assert_allclose(b - a, np.full(4, 100.0 * 0.2))
    assert a[0] == pytest.approx(-5.0)


def test_integral_does_not_wind_up_while_saturated_or_far_from_the_target() -> None:
    pid = make_controller(kp=20000.0, ki=1000.0, kd=0.0, integral_zone=0.1)
    for k in range(100):  # inside the zone but saturated: no growth
        pid.act(state([1.0, 1.0, 1.0, 1.0], t=0.05 * k), np.full(4, 1.05))
    np.testing.assert_array_equal(pid.integral, 0.0)
    pid = make_controller(kp=1.0, ki=1000.0, kd=0.0, integral_zone=0.1)
    for k in range(100):  # far from the target: no integration at all
        pid.act(state([1.0, 1.0, 1.0, 1.0], t=0.05 * k), np.full(4, 2.0))
    np.testing.assert_array_equal(pid.integral, 0.0)


def test_a_late_state_adds_at_most_two_periods_to_the_integral() -> None:
    pid = make_controller(kp=0.0, ki=1.0, kd=0.0, integral_zone=1.0)
    pid.act(state(np.zeros(4), t=0.0), np.full(4, 0.5))
    pid.act(state(np.zeros(4), t=10.0), np.full(4, 0.5))
    np.testing.assert_allclose(pid.integral, 0.5 * 0.05 + 0.5 * 0.1)
    pid.reset()
    np.testing.assert_array_equal(pid.integral, 0.0)


def test_the_integral_cancels_a_constant_load_like_gravity() -> None:
    # A unit-inertia, damped joint with a constant 40 mA-equivalent load pulling it down.
    pid = make_controller(kp=800.0, ki=1500.0, kd=300.0, integral_zone=0.2)
    q, qd, dt, target = np.zeros(4), np.zeros(4), 0.05, np.full(4, 0.3)
    for k in range(400):
        u = pid.act(state(q, qd, t=k * dt), target)
        for _ in range(25):  # 2 ms physics under a 50 ms zero-order hold
            acc = (u - 40.0 - 200.0 * qd) / 100.0
            qd = qd + acc * 0.002
            q = q + qd * 0.002
    np.testing.assert_allclose(q, target, atol=1e-3)


def test_parameters_are_validated() -> None:
    with pytest.raises(TypeError, match="unknown PID parameters: kq"):
        make_controller(kq=1.0)
    with pytest.raises(ValueError, match="joint order"):
        make_controller(kp=[1.0, 2.0])
    with pytest.raises(ValueError, match="negative"):
        make_controller(kd=-1.0)
    with pytest.raises(ValueError, match="positive"):
        make_controller(current_limits_mA=[600, 0, 600, 300])


def test_the_entry_point_builds_a_pid_and_unknown_names_are_listed() -> None:
    pid = load_controller("pid", kp=[1000, 1000, 1000, 300])
    assert isinstance(pid, PIDController)
    np.testing.assert_array_equal(pid.gains.kp, [1000, 1000, 1000, 300])
    with pytest.raises(DriverError, match="registered: .*pid"):
        load_controller("no-such-controller")
    with pytest.raises(DriverError, match="rejected its parameters"):
        load_controller("pid", bogus=1)


def test_the_entry_point_builds_the_bravos_pid_with_its_own_gains_and_limits() -> None:
    from policy.controllers.pid import DEFAULT_GAINS

    pid = load_controller("pid", arm=BRAVO7)
    assert isinstance(pid, PIDController)
    np.testing.assert_array_equal(pid.gains.kp, DEFAULT_GAINS["bravo7"].kp)
    np.testing.assert_array_equal(pid.limits, [2000, 2000, 1500, 1500, 1500, 1000])
    q = np.full(6, 1.0)
    out = pid.act(ControlState(q, np.zeros(6), 0.0), q + np.array([3.0, -3.0, 3.0, 0.0, 0.0, 3.0]))
    np.testing.assert_array_equal(out, [2000, -2000, 1500, 0, 0, 1000])
    with pytest.raises(ValueError, match=r"kp needs one value or 6 \(joint order G F E D C B\)"):
        load_controller("pid", arm=BRAVO7, kp=[1000, 1000, 1000, 300])
    alpha = load_controller("pid")  # the Alpha 5's, as before
    assert isinstance(alpha, PIDController) and alpha.limits.tolist() == [600, 600, 600, 300]


@pytest.mark.slow
def test_pid_reaches_targets_on_the_virtual_arm_without_large_overshoot(sim_factory) -> None:
    sim = sim_factory(speed=4.0, pty=False, udp=LOOPBACK)
    with ArmClient(open_transport(udp_url(sim))) as client:
        q0 = client.read_joints().q
        for step in ([0.9, -0.7, 0.8, 1.5], [-1.2, 0.5, -0.9, -1.8]):
            start = client.read_joints().q
            target = q0 + np.array(step)
            records: list[StepRecord] = []
            summary = ControlLoop(client, make_controller(), 0.05, on_step=records.append).run(
                target, 5.0
            )
            assert summary.ok, summary.error
            q = np.array([r.q for r in records])
            direction = np.sign(target - start)
            overshoot = np.max((q - target) * direction, axis=0) / np.abs(target - start)
            assert np.all(overshoot < 0.06), overshoot
            assert np.max(np.abs(summary.final_error)) < 0.015, summary.final_error
            # Within 2 cm-ish of every target after 3 s of the 5 s run (the first step at
            # or after 3 s of arm time: a late loop may have skipped the one at 3 s).
            at_3s = next(r.q for r in records if r.t >= 3.0 - 1e-9)
            assert np.max(np.abs(target - at_3s)) < 0.05
