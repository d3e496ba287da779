"""The energy-aware demonstrator: slower cruise where the way is short, same arrival."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from policy.rl.env import NO_LOAD_SPEEDS, EnvConfig, ReachAlphaEnv
from policy.rl.expert import PDExpert

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import tune_expert  # noqa: E402

START = np.array([1.0, 1.0, 1.5, 1.0])
# E has 3 rad to go; D and C little (their profile caps them); B, with little friction, runs
TARGET = np.array([4.0, 1.25, 1.4, 1.5])


def _run(expert: PDExpert, seconds: float = 6.0) -> dict[str, np.ndarray]:
    env = ReachAlphaEnv(EnvConfig(episode_s=seconds))
    env.reset(seed=0, options={"start": START, "target": TARGET})
    q, qdot, energy = [env.arm.q.copy()], [], np.zeros(4)
    for _ in range(env.config.steps_per_episode):
        a = expert(env)
        for _ in range(env.n_substeps):  # the metric's way: |tau qdot| at the physics rate
            env.arm.step(a * env.current_limits_mA, n=1)
            energy += np.abs(env.arm.tau * env.arm.qdot) * env.config.physics_dt
        q.append(env.arm.q.copy())
        qdot.append(env.arm.qdot.copy())
    return {"q": np.array(q), "qdot": np.array(qdot), "energy": energy}


def _arrival(q: np.ndarray, joint: int, tol: float = 0.01) -> int:
    err = np.abs(q[:, joint] - TARGET[joint])
    outside = np.flatnonzero(err > tol)
    return int(outside[-1]) + 1 if outside.size else 0


def test_cruise_speed_keeps_the_slowest_joint_flat_out() -> None:
    expert = PDExpert(energy_lambda=6.0)
    e = np.abs(TARGET - START)
    v = expert.cruise_speed(e)
    assert np.isinf(v[0])  # E has the longest remaining time: full speed
    assert np.isinf(v[3])  # B's friction is small: its profile allows full speed
    assert np.all(v[1:3] < 0.8 * NO_LOAD_SPEEDS[1:3])
    # never slower than arriving together with E, and zero at the target
    np.testing.assert_array_less(e[1:3] / (e[0] / NO_LOAD_SPEEDS[0]) - 1e-9, v[1:3])
    assert expert.cruise_speed(np.zeros(4))[1] == 0.0


def test_energy_aware_expert_saves_energy_and_arrives_as_soon() -> None:
    plain, saver = _run(PDExpert()), _run(PDExpert(energy_lambda=6.0))
    for run in (plain, saver):
        assert np.all(np.abs(run["q"][-1] - TARGET) < 0.005)
    # D, which has little way to go and much friction, takes its time and spends less ...
    assert _arrival(saver["q"], 1) > _arrival(plain["q"], 1) + 4
    assert saver["energy"][1] < 0.8 * plain["energy"][1]
    assert saver["energy"].sum() < plain["energy"].sum() - 0.2
    # ... while E, which sets the settling time, still runs flat out and arrives on time
    peak_plain, peak_saver = np.abs(plain["qdot"]).max(0), np.abs(saver["qdot"]).max(0)
    assert peak_saver[0] == pytest.approx(peak_plain[0], rel=0.01)
    assert saver["energy"][0] == pytest.approx(plain["energy"][0], rel=0.01)
    assert _arrival(saver["q"], 0) <= _arrival(plain["q"], 0) + 1
    for j in range(4):  # no joint is left arriving after E
        assert _arrival(saver["q"], j) <= _arrival(saver["q"], 0) + 1
    step = TARGET - START
    progress = (saver["q"] - START) / step
    assert progress.max() < 1.01  # under 1 % overshoot


def test_tuning_rule_takes_the_least_energy_within_tolerance() -> None:
    def row(
        lam: float | None, energy: float, mie: float, rmse: float = 0.2, st: float = 2.0
    ) -> dict[str, object]:
        return {
            "energy_lambda": lam,
            "summary": {
                "energy_j": energy,
                "mie": mie,
                "rmse": rmse,
                "settling_time_s": st,
                "reached": 1.0,
            },
        }

    rows = [
        row(None, 10.0, 1.0),
        row(2.0, 8.0, 1.10),
        row(4.0, 9.0, 1.01),
        row(6.0, 9.5, 1.005),
        row(8.0, 8.5, 1.0, st=2.1),
    ]
    best = tune_expert.choose(rows, mie_tol=0.015, rmse_tol=0.005)
    assert best is not None and best["energy_lambda"] == 4.0
    assert tune_expert.choose(rows[:2], mie_tol=0.015, rmse_tol=0.005) is None
