"""The rest metric (docs/metrics.md, "Rest"): chatter around the goal is not rest, and an
episode that does not come to rest is not reached."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from policy.campaigns.direct import DirectArm
from policy.campaigns.evaluation import RunConfig, load_controller, random_episodes
from protocol.alpha5 import TORQUE_PER_AMP_NM
from reach_driver.metrics import (
    REST_ENERGY_AFTER_SETTLING_MAX_J,
    REST_KEYS,
    REST_REVERSALS_MAX,
    REST_SPEED_RMS_MAX,
    Metrics,
    Trace,
    command_reversals,
    compute_metrics,
    energy_after,
    energy_after_clocks,
    energy_clocks,
    rest,
    rest_window,
    settling_time,
)
from reach_sim_bridge.model.sensors import SensorNoise

DT = 0.05
N = 400  # 20 s at 20 Hz
KT = np.asarray(TORQUE_PER_AMP_NM)  # N m per A
TARGET = np.array([3.0, 1.5, 2.0, 1.5])
START = np.array([2.0, 1.0, 1.5, 1.0])


def _settled_then(chatter_from: float | None, seed: int = 0) -> Trace:
    """Joints ramp to the target at 1 rad/s and hold (gravity-holding command on D and C,
    sensor-size noise); from ``chatter_from`` C bang-bangs +-8 mrad at the no-load speed
    with +-260 mA reversing every period, as the degraded-arm distilled-actor episode does."""
    rng = np.random.default_rng(seed)
    t = np.arange(N + 1) * DT
    step = TARGET - START
    q = START + np.sign(step) * np.minimum(np.abs(step), t[:, None] * 1.0)
    qdot = np.where(np.abs(TARGET - q) > 1e-9, np.sign(step), 0.0) + rng.normal(0, 1e-3, q.shape)
    command = np.tile([0.0, 150.0, 90.0, 0.0], (N + 1, 1)) + rng.normal(0, 10.0, q.shape)
    if chatter_from is not None:
        k0 = int(chatter_from / DT)
        sign = np.where(np.arange(N + 1 - k0) % 2 == 0, 1.0, -1.0)
        q[k0:, 2] = TARGET[2] + 0.008 * sign
        qdot[k0:, 2] = 1.15 * sign
        command[k0:, 2] = 260.0 * sign
    tau = command * 1e-3 * KT
    power = np.abs(tau * qdot)
    return Trace(DT, q, qdot, tau, TARGET, power=power, command_mA=command)


def test_a_settled_trace_is_at_rest_and_reached() -> None:
    m = compute_metrics(_settled_then(None))
    assert m.at_rest and m.reached
    assert m.rest_speed_rms < 0.01
    assert m.command_reversals == 0
    assert m.energy_after_settling_j < 0.1


def test_a_chattering_trace_is_not_at_rest_and_not_reached() -> None:
    m = compute_metrics(_settled_then(5.0))
    assert np.all(np.abs(_settled_then(5.0).errors[-1]) < 0.02)  # final error alone passes
    assert not m.at_rest and not m.reached
    assert m.rest_speed_rms > REST_SPEED_RMS_MAX
    assert m.command_reversals > REST_REVERSALS_MAX
    assert m.energy_after_settling_j > REST_ENERGY_AFTER_SETTLING_MAX_J


def test_a_burst_of_chatter_after_settling_is_not_rest() -> None:
    """A 0.8 s burst that dies out: the last 2 s are clean, the energy after settling is not."""
    trace = _settled_then(3.0)
    command = np.asarray(trace.command_mA).copy()
    qdot = trace.qdot.copy()
    q = trace.q.copy()
    command[76:, 2] = 90.0
    qdot[76:, 2] = 0.0
    q[76:, 2] = TARGET[2]
    tau = command * 1e-3 * KT
    quiet = Trace(DT, q, qdot, tau, TARGET, power=np.abs(tau * qdot), command_mA=command)
    r = rest(quiet)
    assert r.speed_rms < REST_SPEED_RMS_MAX and r.reversals == 0
    assert r.energy_after_settling_j > REST_ENERGY_AFTER_SETTLING_MAX_J and not r.at_rest


def test_a_long_step_finishing_behind_friction_is_rest() -> None:
    """E steps 5 rad behind 6.6 N m of Coulomb friction and comes straight to rest, last of
    the joints. Its settling band is 100 mrad, and finishing the approach inside it costs
    6.6 x 0.1 = 0.66 J: counted from the settling time, a clean arrival failed the 0.5 J
    test. A joint still finishing a straight approach is counted from inside 20 mrad instead
    (`energy_clocks`), where the same approach costs 0.13 J; the same joint turning back
    once inside its band counts from the turn."""
    target = np.array([5.4, 1.5, 2.0, 1.5])
    start = np.array([0.4, 1.5, 2.0, 1.5])
    speed = np.zeros(N + 1)  # 1 rad/s, then in exponentially (0.2 s) over the last 0.2 rad
    e_q = np.full(N + 1, start[0])
    for k in range(N):
        speed[k] = min(1.0, (target[0] - e_q[k]) / 0.2)
        e_q[k + 1] = e_q[k] + speed[k] * DT
    q = np.tile(start, (N + 1, 1))
    q[:, 0] = e_q
    qdot = np.zeros_like(q)
    qdot[1:, 0] = speed[:-1]  # the speed over the period that ends at each sample
    tau = np.zeros_like(q)
    tau[:, 0] = np.where(qdot[:, 0] > 1e-3, 6.6, 0.0)
    command = tau / KT * 1000.0
    trace = Trace(DT, q, qdot, tau, target, power=np.abs(tau * qdot), command_mA=command)
    settled = settling_time(q, target, DT)
    assert abs(q[-1, 0] - target[0]) < 0.01
    assert energy_after(trace, settled) > REST_ENERGY_AFTER_SETTLING_MAX_J  # the old clock
    clocks = energy_clocks(q, target, DT, settled)
    assert clocks[0] > settled and np.all(clocks[1:] == settled)
    m = compute_metrics(trace)
    assert m.energy_after_settling_j == pytest.approx(energy_after_clocks(trace, clocks))
    assert 0.05 < m.energy_after_settling_j < 0.2
    assert m.at_rest and m.reached
    # the same approach, but E swings back 30 mrad three times from 40 mrad out (inside its
    # 100 mrad band): all of it after the first turn counts
    k = int(np.argmax(np.abs(target[0] - q[:, 0]) < 0.04))
    swing = q.copy()
    back = 0.03 * np.abs(np.sin(np.linspace(0.0, 3 * np.pi, 30)))
    swing[k : k + 30, 0] -= back
    swing_qdot = qdot.copy()
    swing_qdot[k : k + 30, 0] -= np.gradient(back, DT)
    swing_tau = tau.copy()
    swing_tau[k : k + 30, 0] = 6.6 * np.sign(swing_qdot[k : k + 30, 0])
    swung = Trace(
        DT,
        swing,
        swing_qdot,
        swing_tau,
        target,
        power=np.abs(swing_tau * swing_qdot),
        command_mA=swing_tau / KT * 1000.0,
    )
    r = rest(swung)
    turn = energy_clocks(swing, target, DT, settling_time(swing, target, DT))[0]
    assert k * DT < turn < (k + 8) * DT  # as it turns back, 30 mrad out
    assert r.energy_after_settling_j > REST_ENERGY_AFTER_SETTLING_MAX_J and not r.at_rest


def test_small_commands_around_zero_are_not_reversals() -> None:
    rng = np.random.default_rng(1)
    noise = rng.normal(0, 20.0, (41, 4))  # below 10 % of 600 / 300 mA most of the time
    noise[:, 3] = rng.normal(0, 8.0, 41)
    assert command_reversals(noise, 40) <= 1
    big = np.where(np.arange(41) % 2 == 0, 100.0, -100.0)[:, None] * np.ones(4)
    assert command_reversals(big, 40) == 39  # the last 2 s: 40 samples, 39 changes


def test_without_commands_the_torque_stands_in() -> None:
    trace = _settled_then(5.0)
    bare = Trace(trace.dt, trace.q, trace.qdot, trace.tau, trace.target)
    assert rest(bare).reversals > REST_REVERSALS_MAX


def test_a_short_episode_is_judged_from_its_settling_on() -> None:
    """A 2 s episode's last 2 s hold its motion: only the part after settling counts, unless
    it never settled."""
    assert rest_window(41, DT, settling_time_s=1.2) == 17  # samples 24..40
    assert rest_window(401, DT, settling_time_s=1.2) == 40
    assert rest_window(41, DT, settling_time_s=2.0) == 40  # never settled: the last 2 s
    t = np.arange(41) * DT
    q = np.minimum(START + t[:, None] * 1.0, TARGET)  # all joints there by 1 s
    qdot = np.where(q < TARGET, 1.0, 0.0)
    m = compute_metrics(Trace(DT, q, qdot, np.zeros_like(q), TARGET, command_mA=np.zeros_like(q)))
    assert m.settling_time_s <= 1.0 and m.at_rest and m.reached


def test_rest_keys_are_metrics_fields() -> None:
    fields = set(Metrics(0, 0, 0, 0, 0, 0, True).as_dict())
    assert set(REST_KEYS) <= fields


SEED_12000 = 12000
CHATTERING = 33  # docs/metrics.md, "Rest": 63.7 J where its neighbours spend about 12 J


@pytest.mark.slow
def test_the_degraded_arm_distilled_actor_chatter_is_flagged_and_its_neighbours_are_not() -> None:
    """`tools/evaluate.py --controller ddpg-distilled --param settle=0 --random 60 --seed 12000
    --noise --perturb 0.2`, episodes 32-34, through the direct backend (about 0.5 s each): the actor
    with its reference integral, without the settle supervisor that now ships around it."""
    episodes = random_episodes(60, SEED_12000)
    config = RunConfig(noise=SensorNoise(), seed=SEED_12000, param_spread=0.2)
    controller = load_controller("ddpg-distilled", settle=False)
    backend = DirectArm()
    metrics = {
        i: backend.run(controller, episodes[i], config, SEED_12000 + i).metrics
        for i in (CHATTERING - 1, CHATTERING, CHATTERING + 1)
    }
    bad = metrics.pop(CHATTERING)
    assert bad.energy_j > 40.0
    assert not bad.at_rest and not bad.reached
    assert bad.rest_speed_rms > 1.0 and bad.command_reversals > 30
    for m in metrics.values():
        assert m.at_rest and m.reached
        assert m.rest_speed_rms < 0.01 and m.command_reversals == 0


@pytest.mark.slow
def test_a_real_burst_on_the_stability_screen_is_flagged() -> None:
    """Screen seed 12 (tools/select_weights.py's), episode 43: C bang-bangs for about 0.8 s
    after settling and stops; episode 44 settles cleanly."""
    from policy.campaigns.selection import _screen, _shipped

    shipped = (
        Path(__file__).resolve().parents[1]
        / "policy"
        / "controllers"
        / "weights"
        / "ddpg_distilled_actor.npz"
    )
    burst, clean = (r.metrics for r in _screen(shipped, [43, 44], 12, 0.2, _shipped))
    assert burst.rest_speed_rms < REST_SPEED_RMS_MAX and burst.command_reversals == 0
    assert burst.energy_after_settling_j > 2 * REST_ENERGY_AFTER_SETTLING_MAX_J
    assert not burst.at_rest and not burst.reached
    assert clean.at_rest and clean.reached
    assert clean.energy_after_settling_j < REST_ENERGY_AFTER_SETTLING_MAX_J / 2
