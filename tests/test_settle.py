"""The settle supervisor around the DDPG actor (policy/settle.py): it stops a limit cycle the
plain actor keeps up on a latent arm, and leaves a nominal episode to the actor."""

from __future__ import annotations

import numpy as np
import pytest

from policy.ddpg_controller import make_controller
from policy.direct import DirectArm
from policy.envelope import draws
from policy.observation import WORKSPACE_HIGH, WORKSPACE_LOW
from policy.rollout import Episode, RunConfig
from policy.settle import SettleLaw
from reach_sim_bridge.faults import SensorNoise


def test_settle_parameter_is_off_by_default_and_validated() -> None:
    assert make_controller().settle is None
    assert SettleLaw.from_param(0) is None and SettleLaw.from_param(False) is None
    assert SettleLaw.from_param(1) == SettleLaw()
    assert SettleLaw.from_param({"band": 0.1}).band == 0.1  # type: ignore[union-attr]
    with pytest.raises(ValueError):
        SettleLaw.from_param({"nonsense": 1})
    with pytest.raises(ValueError):
        SettleLaw(kp=-1.0)


@pytest.mark.slow
def test_settle_turns_a_latent_arms_limit_cycle_into_rest() -> None:
    # Draw 10 of tools/robustness.py --draws N --seed 1 (its episode and noise seed): 2.7 N m
    # of Coulomb friction, 1.59 periods of latency; the plain actor keeps B in a limit cycle
    # (+-0.1 rad at 1.2 rad/s) to the end.
    variant = draws(11, 1).variants[10]
    rng = np.random.default_rng([1, 1, 10])
    episode = variant.episode(
        Episode(
            start=rng.uniform(WORKSPACE_LOW, WORKSPACE_HIGH),
            target=rng.uniform(WORKSPACE_LOW, WORKSPACE_HIGH),
        )
    )
    config = variant.run_config(RunConfig(seconds=20.0, noise=SensorNoise(), seed=100_001))
    plain = DirectArm().run(make_controller(), episode, config, 100_011)
    assert not plain.metrics.at_rest and not plain.metrics.reached
    ctrl = make_controller(settle=True)
    settled = DirectArm().run(ctrl, episode, config, 100_011)
    assert settled.metrics.at_rest and settled.metrics.reached
    assert ctrl.settle is not None and ctrl.settle.engaged[3]  # B was handed over
    assert ctrl.settle.reasons[3] == "cycling"


@pytest.mark.slow
def test_settle_changes_nothing_on_a_nominal_episode() -> None:
    episode = Episode(start=np.array([0.5, 1.2, 1.0, 0.5]), target=np.array([1.5, 1.8, 0.6, 1.5]))
    config = RunConfig(seconds=10.0, noise=SensorNoise(), seed=3)
    plain = DirectArm().run(make_controller(), episode, config, 3)
    ctrl = make_controller(settle=True)
    settled = DirectArm().run(ctrl, episode, config, 3)
    assert ctrl.settle is not None and not ctrl.settle.engaged.any()
    np.testing.assert_array_equal(plain.trace.q, settled.trace.q)
    assert plain.metrics.reached and settled.metrics.reached
