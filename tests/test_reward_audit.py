"""The reward audit pays every controller the actor's own reward on the same episodes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import still_actor

from policy.campaigns.reward_audit import audit, render
from policy.rl.env import REWARD_TERMS
from protocol.models import BRAVO7

SHIPPED = Path(__file__).resolve().parents[1] / "policy/controllers/weights/ddpg_actor.npz"


@pytest.fixture(scope="module")
def result():  # type: ignore[no-untyped-def]
    return audit(SHIPPED, episodes=3, seed=40_000)


def test_terms_sum_to_the_return_and_discounting_shrinks_a_cost(result) -> None:  # type: ignore[no-untyped-def]
    assert set(result.returns) == {"actor", "pid", "pd-expert"}
    for returns in result.returns.values():
        summed = sum(returns.terms[name] for name in REWARD_TERMS)
        np.testing.assert_allclose(summed, returns.total, rtol=1e-9, atol=1e-9)
        assert np.all(returns.total < 0)  # the shaped reward is a cost
        assert np.all(returns.discounted > returns.total)  # gamma < 1 on costs


def test_the_references_run_the_actors_episodes_and_the_privileged_pd_arrives_calmly(
    result,
) -> None:  # type: ignore[no-untyped-def]
    # the same episodes: differences are paired per episode
    assert result.actor_minus["pid"].n == 3
    assert result.actor_minus["pd-expert"].estimate == pytest.approx(
        float(np.mean(result.returns["actor"].discounted - result.returns["pd-expert"].discounted))
    )
    assert np.all(result.returns["pd-expert"].overshoot_pct < 2.0)
    rows = render(result)
    assert [r[0] for r in rows[1:]] == ["actor", "pid", "pd-expert"]
    assert all(len(r) == len(rows[0]) for r in rows)


def test_the_hold_column_is_the_last_seconds_and_the_pid_holds_the_goal(result) -> None:  # type: ignore[no-untyped-def]
    for returns in result.returns.values():
        assert np.all(returns.hold <= 0) and np.all(returns.hold >= returns.total)
    # at rest at the goal a step costs ~nothing: over the last 2 s the PID earns more than
    # a hundredth of what it earned over the whole episode
    pid = result.returns["pid"]
    assert np.all(pid.hold > 0.01 * pid.total)
    assert result.hold_minus["pid"].n == 3


def test_an_actor_of_another_arm_is_audited_on_its_arm_without_the_alpha_expert(
    tmp_path: Path,
) -> None:
    """A Bravo actor (one that asks for no current: the plumbing, not a policy) runs in the
    Bravo's env against the Bravo's PID; the PD expert, the Alpha 5's, sits out."""
    weights = still_actor(tmp_path / "bravo_actor.npz", BRAVO7)
    bravo = audit(weights, episodes=2, seed=7020)
    assert set(bravo.returns) == {"actor", "pid"}
    # the PID moves the Bravo's six joints to the goal; an actor that commands nothing does not
    assert bravo.returns["pid"].discounted.mean() > bravo.returns["actor"].discounted.mean()
    assert bravo.hold_minus["pid"].estimate < 0
    assert [r[0] for r in render(bravo)[1:]] == ["actor", "pid"]
