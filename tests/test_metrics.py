"""Each metric on synthetic signals whose answer is known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from reach_driver.metrics import (
    ALL_METRIC_KEYS,
    Metrics,
    Trace,
    compute_metrics,
    energy,
    ideal_trajectory,
    mean_integral_error,
    mean_steady_state_error,
    overshoot_anatomy,
    overshoot_pct,
    reached,
    rmse,
    rmse_floor,
    settling_time,
    summarize,
)


def _trace(q: np.ndarray, target, dt: float = 0.1, qdot=None, tau=None) -> Trace:
    q = np.asarray(q, dtype=float)
    return Trace(
        dt=dt,
        q=q,
        qdot=np.zeros_like(q) if qdot is None else np.asarray(qdot, dtype=float),
        tau=np.zeros_like(q) if tau is None else np.asarray(tau, dtype=float),
        target=np.asarray(target, dtype=float),
    )


def test_energy_sums_absolute_mechanical_power() -> None:
    n, dt = 10, 0.1
    qdot = np.full((n + 1, 4), 0.5)
    tau = np.full((n + 1, 4), 2.0)
    tau[:, 1] = -2.0  # braking power counts as spent, not recovered
    tau[0] = 100.0  # row 0 is the initial state: no period ends there
    tr = _trace(np.zeros((n + 1, 4)), np.zeros(4), dt, qdot, tau)
    assert energy(tr) == pytest.approx(4 * n * 1.0 * dt)


def test_rmse_of_constant_and_mixed_errors() -> None:
    e = np.full((5, 4), 0.1)
    e[0] = 9.0  # t = 0 is excluded
    assert rmse(e) == pytest.approx(0.1)
    e2 = np.zeros((3, 4))
    e2[1:, 0] = 0.4  # one joint of four off by 0.4: sqrt(0.16 / 4)
    assert rmse(e2) == pytest.approx(0.2)


def test_mie_integrates_each_joint_then_averages() -> None:
    dt = 0.1
    e = np.zeros((31, 4))
    e[1:11, 0] = 1.0  # 1 rad for 1 s -> 1 rad s
    e[1:21, 1] = -0.5  # 0.5 rad for 2 s -> 1 rad s
    e[1:31, 2] = 0.2  # 0.2 rad for 3 s -> 0.6 rad s
    assert mean_integral_error(e, dt) == pytest.approx((1.0 + 1.0 + 0.6 + 0.0) / 4)


def test_msse_uses_only_the_last_two_seconds() -> None:
    dt = 0.05
    e = np.full((201, 4), 1.0)  # 10 s
    e[-40:] = np.array([0.03, -0.01, 0.0, 0.02])  # last 2 s = 40 samples
    assert mean_steady_state_error(e, dt) == pytest.approx(0.015)
    e[-41] = 50.0  # just outside the window
    assert mean_steady_state_error(e, dt) == pytest.approx(0.015)


def test_overshoot_relative_to_step_signed_by_direction() -> None:
    t = np.linspace(0, 5, 101)
    q = np.zeros((101, 4))
    q[:, 0] = 1.0 - np.exp(-t) * np.cos(3 * t) * 1.0  # 0 -> 1, overshoots
    q[:, 1] = 2.0 - 0.9 * np.minimum(t, 1.0) - 0.2 * np.sin(np.pi * np.clip(t - 1, 0, 1))
    target = np.array([1.0, 1.1, 0.0, 0.0])
    expected0 = (q[:, 0].max() - 1.0) * 100
    expected1 = ((2.0 - q[:, 1].min()) / 0.9 - 1.0) * 100  # downward step of 0.9
    assert overshoot_pct(q, target) == pytest.approx(max(expected0, expected1))
    assert expected1 == pytest.approx(0.2 / 0.9 * 100, rel=1e-3)


def test_overshoot_ignores_small_steps_and_wrong_way_motion() -> None:
    q = np.zeros((4, 4))
    q[:, 0] = [0.0, 0.2, 0.5, 0.04]  # step 0.04 < 0.05: excluded despite 1150 % "overshoot"
    q[:, 1] = [1.0, 1.5, 0.5, 0.0]  # step -1: moved +0.5 first (not overshoot), peak at target
    target = np.array([0.04, 0.0, 0.0, 0.0])
    assert overshoot_pct(q, target) == 0.0
    q[3, 1] = -0.3  # now 30 % past the target
    assert overshoot_pct(q, target) == pytest.approx(30.0)


def test_the_overshoot_anatomy_tells_an_arrival_from_a_creep() -> None:
    """The worst joint as overshoot_pct picks it, how far past its goal it went (rad), when,
    and how fast it first crossed: an arrival carried through at speed, or a creep."""
    dt = 0.05
    t = np.arange(0, 10.0 + dt / 2, dt)
    q = np.zeros((t.size, 4))
    qdot = np.zeros_like(q)
    # E: 0 -> 1 rad at 1 rad/s, 30 mrad through and back by t = 1.1 s (3 %)
    q[:, 0] = np.minimum(t, 1.03)
    q[t > 1.1, 0] = 1.0
    qdot[:, 0] = np.where(t < 1.06, 1.0, 0.0)  # still at speed at the first sample past
    # D: 0 -> -0.2 rad, stops 5 mrad short, creeps through at 2 mrad/s to 10 mrad past (5 %)
    q[:, 1] = -np.minimum(t, 0.195) - np.clip(t - 2.0, 0.0, 7.5) * 0.002
    qdot[:, 1] = np.where(t < 0.195, -1.0, np.where((t > 2.0) & (t < 9.5), -0.002, 0.0))
    target = np.array([1.0, -0.2, 0.0, 0.0])
    a = overshoot_anatomy(q, qdot, target, dt)
    assert a is not None and a.joint == 1 and a.pct == pytest.approx(overshoot_pct(q, target))
    assert a.past_rad == pytest.approx(0.010, abs=1e-9) and not a.arrival
    assert a.crossing_speed == pytest.approx(0.002) and a.peak_s == pytest.approx(9.5)
    q[:, 1] = -np.minimum(t, 0.2)  # D now stops on its goal: E's arrival is the worst
    a = overshoot_anatomy(q, qdot, target, dt)
    assert a is not None and a.joint == 0 and a.arrival and a.crossing_speed == 1.0
    assert a.past_rad == pytest.approx(0.03) and a.pct == pytest.approx(3.0)
    q[:, 0] = np.minimum(t, 1.0)  # nothing past its goal
    assert overshoot_anatomy(q, qdot, target, dt) is None


def test_settling_time_is_the_last_entry_into_the_band() -> None:
    dt = 0.1
    q = np.zeros((101, 4))  # 10 s, target 1 on joint 0: band 0.02
    q[30:, 0] = 0.99  # inside from t = 3.0
    q[50, 0] = 0.97  # one excursion at t = 5.0
    target = np.array([1.0, 0.0, 0.0, 0.0])
    assert settling_time(q, target, dt) == pytest.approx(5.1)
    q[50, 0] = 0.985
    assert settling_time(q, target, dt) == pytest.approx(3.0)


def test_settling_time_uses_absolute_band_for_small_steps_and_never() -> None:
    dt = 0.1
    q = np.zeros((21, 4))
    target = np.array([0.2, 0.0, 0.0, 0.0])  # 2 % would be 0.004: band is 0.01 rad
    q[10:, 0] = 0.191
    assert settling_time(q, target, dt) == pytest.approx(1.0)
    q[-1, 0] = 0.18  # outside at the end: never settled
    assert settling_time(q, target, dt) == pytest.approx(2.0)
    assert settling_time(np.zeros((21, 4)), np.zeros(4), dt) == 0.0  # no step: settled at once


def test_reached_checks_every_final_error() -> None:
    e = np.zeros((3, 4))
    e[-1] = [0.019, -0.019, 0.0, 0.0]
    assert reached(e)
    e[-1, 3] = -0.02
    assert not reached(e)


def test_compute_metrics_on_a_ramp_response() -> None:
    dt, n = 0.05, 400  # 20 s
    start, target = np.zeros(4), np.array([1.0, -0.5, 0.0, 0.25])
    q = ideal_trajectory(start, target, np.full(4, 0.5), dt, n)
    m = compute_metrics(_trace(q, target, dt))
    assert m.reached and m.overshoot_pct == 0.0 and m.msse == 0.0
    # joint 0 enters its 0.02 band at t = 1.96 and joint 1 its 0.01 band at t = 1.98:
    # the first sample with both inside is t = 2.00
    assert m.settling_time_s == pytest.approx(2.0)
    # joint 0: e = 1 - 0.5 t for 2 s -> integral 1.0 minus the right-rectangle bias
    assert m.mie == pytest.approx(
        (
            sum(max(0, 1 - 0.025 * k) for k in range(1, n + 1))
            + sum(max(0, 0.5 - 0.025 * k) for k in range(1, n + 1))
            + sum(max(0, 0.25 - 0.025 * k) for k in range(1, n + 1))
        )
        * dt
        / 4
    )
    assert set(m.as_dict()) == set(ALL_METRIC_KEYS)


def test_rmse_floor_closed_form() -> None:
    # 1.18 rad at 1.18 rad/s, 20 Hz, 20 s: errors 1.18 (1 - k/20) for k = 1..20, then 0.
    speed = np.full(4, 1.18)
    target = np.full(4, 1.18)
    floor = rmse_floor(np.zeros(4), target, speed, 0.05, 400)
    squares = sum((m / 20) ** 2 for m in range(20))  # = 6.175
    assert floor == pytest.approx(1.18 * math.sqrt(squares / 400))


@settings(max_examples=60, deadline=None)
@given(
    start=st.lists(st.floats(0.0, 3.0), min_size=4, max_size=4),
    target=st.lists(st.floats(0.0, 3.0), min_size=4, max_size=4),
    slowdown=st.lists(st.floats(0.1, 1.0), min_size=4, max_size=4),
)
def test_no_speed_limited_motion_beats_the_floor(start, target, slowdown) -> None:
    speed = np.array([1.18, 1.18, 1.18, 1.3])
    s, g = np.array(start), np.array(target)
    floor = rmse_floor(s, g, speed, 0.05, 100)
    slower = ideal_trajectory(s, g, speed * np.array(slowdown), 0.05, 100)
    assert rmse(g[None, :] - slower) >= floor - 1e-12


def test_summarize_means_and_reached_fraction() -> None:
    a = Metrics(1.0, 0.2, 3.0, 0.01, 5.0, 2.0, True)  # built as before the rest metric
    b = Metrics(3.0, 0.4, 1.0, 0.03, 15.0, 4.0, False, False, 1.0, 30, 40.0)
    s = summarize([a, b])
    assert s == pytest.approx(
        {
            "energy_j": 2.0,
            "rmse": 0.3,
            "mie": 2.0,
            "msse": 0.02,
            "overshoot_pct": 10.0,
            "settling_time_s": 3.0,
            "reached": 0.5,
            "at_rest": 0.5,
            "rest_speed_rms": 0.5,
            "command_reversals": 15.0,
            "energy_after_settling_j": 20.0,
        }
    )
    with pytest.raises(ValueError, match="no episodes"):
        summarize([])


def test_trace_rejects_mismatched_shapes() -> None:
    q = np.zeros((5, 4))
    with pytest.raises(ValueError, match="qdot has shape"):
        Trace(0.1, q, np.zeros((4, 4)), np.zeros((5, 4)), np.zeros(4))
    with pytest.raises(ValueError, match="dt must be positive"):
        Trace(0.0, q, q, q, np.zeros(4))
    with pytest.raises(ValueError, match="N >= 1"):
        Trace(0.1, np.zeros((1, 4)), np.zeros((1, 4)), np.zeros((1, 4)), np.zeros(4))
    with pytest.raises(ValueError, match="speeds must be positive"):
        rmse_floor(np.zeros(4), np.ones(4), np.zeros(4), 0.1, 10)
