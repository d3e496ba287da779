"""Reselection: a run keeps every checkpoint's actor, and `policy.campaigns.reselect` scores
them all on a validation set of its own and picks one by its fixed rule."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import run_tool, still_actor, tiny

from policy.campaigns.ablation import HeldOutSets
from policy.campaigns.reselect import (
    RESELECTED,
    CheckpointFigures,
    checkpoint_actors,
    choose,
    figures,
    reselect,
    write,
)
from policy.controllers.weights import (
    CHECKPOINT_ACTORS,
    LEARNED_WEIGHTS,
    ActorWeights,
    CheckpointActor,
)
from policy.rl.config import DDPGConfig
from policy.rl.trainer import Trainer
from protocol.models import ALPHA5, BRAVO7

#: a few validation episodes: enough to tell an actor that reaches from one that never moves
SMALL = HeldOutSets(standard=3, envelope=2, seed=60_000)


def _row(steps: int, good: float, reached: float, overshoot: float) -> CheckpointFigures:
    return CheckpointFigures(
        env_steps=steps,
        path=f"actor-{steps}.npz",
        standard_good=good,
        envelope_good=good,
        standard_reached=reached,
        envelope_reached=reached,
        standard_overshoot_pct=overshoot,
        standard_msse=0.001,
        standard_energy_j=5.0,
    )


def test_a_run_keeps_every_checkpoints_actor_each_the_one_its_record_scored(
    tmp_path: Path,
) -> None:
    cfg = tiny(
        DDPGConfig.scratch(hidden=(16, 16), batch_size=8, num_envs=2),
        eval_envelope_episodes=0,
        collector_process=False,
        eval_every=200,
        eval_episodes=2,
        actor_average_tau=0.25,
    )
    run = tmp_path / "run"
    trainer = Trainer(cfg, run, log=lambda _: None)
    try:
        trainer.run()
    finally:
        trainer.close()
    records = [json.loads(line) for line in (run / "eval.jsonl").open()]
    assert len(records) == 2
    kept = checkpoint_actors(run)
    online = checkpoint_actors(run, CheckpointActor.ONLINE)
    assert [steps for steps, _ in kept] == [r["env_steps"] for r in records]
    assert [steps for steps, _ in online] == [r["env_steps"] for r in records]
    for record, (_, path), (_, online_path) in zip(records, kept, online, strict=True):
        assert ActorWeights.load(path).metadata["eval"]["score"] == record["score"]
        assert (
            ActorWeights.load(online_path).metadata["eval"]["score"] == (record["online"]["score"])
        )
    # the last files hold the agent's weights now: the averaged actor and the online one
    obs = np.random.default_rng(1).normal(size=(4, trainer.obs_dim)).astype(np.float32)
    np.testing.assert_allclose(
        ActorWeights.load(kept[-1][1]).forward(obs), trainer.agent.act_average(obs), atol=1e-5
    )
    np.testing.assert_allclose(
        ActorWeights.load(online[-1][1]).forward(obs), trainer.agent.act(obs), atol=1e-5
    )


def test_an_episode_is_good_only_reached_at_rest_and_under_2_pct_overshoot() -> None:
    def episode(reached: bool, overshoot: float) -> dict[str, float]:
        return {
            "reached": float(reached),
            "at_rest": 1.0,
            "overshoot_pct": overshoot,
            "msse": 0.002,
            "energy_j": 4.0,
        }

    row = figures(
        100,
        Path("a.npz"),
        {
            "standard": [episode(True, 1.9), episode(True, 2.0), episode(False, 0.0)],
            "envelope": [episode(True, 0.5), episode(True, 0.1)],
        },
    )
    assert row.standard_good == pytest.approx(1 / 3)
    assert row.envelope_good == 1.0
    assert row.merit == pytest.approx(4 / 3)
    assert row.standard_reached == pytest.approx(2 / 3)
    assert row.standard_overshoot_pct == pytest.approx(3.9 / 3)
    # an arm without an envelope set: its share adds nothing
    assert figures(1, Path("b.npz"), {"standard": [episode(True, 0.0)], "envelope": []}).merit == 1


def test_the_rule_picks_the_most_good_episodes_then_reaching_then_the_lower_overshoot() -> None:
    assert choose([_row(1, 0.5, 0.9, 1.0), _row(2, 0.6, 0.8, 9.0)]).env_steps == 2
    # equally good: the one that reaches more, though it overshoots more
    assert choose([_row(1, 0.0, 0.0, 0.0), _row(2, 0.0, 0.5, 30.0)]).env_steps == 2
    # equally good and reaching: the lower overshoot
    assert choose([_row(1, 0.5, 0.9, 3.0), _row(2, 0.5, 0.9, 2.5)]).env_steps == 2
    with pytest.raises(ValueError, match="no checkpoint"):
        choose([])


def _two_checkpoint_run(run: Path) -> Path:
    """A run folder with two checkpoint actors: one that never moves (50k), the shipped
    `ddpg` (100k)."""
    folder = run / CHECKPOINT_ACTORS
    folder.mkdir(parents=True)
    still_actor(folder / "actor-00050000.npz", ALPHA5)
    shutil.copyfile(LEARNED_WEIGHTS, folder / "actor-00100000.npz")
    shutil.copyfile(LEARNED_WEIGHTS.with_suffix(".json"), folder / "actor-00100000.json")
    return folder


def test_reselection_scores_every_checkpoint_picks_one_and_writes_it(tmp_path: Path) -> None:
    folder = _two_checkpoint_run(tmp_path / "run")
    told: list[str] = []
    result = reselect(tmp_path / "run", sets=SMALL, progress=told.append)
    assert len(told) == 2  # both scored
    still, shipped = result.rows
    assert still.standard_reached == 0.0 and still.merit == 0.0
    assert shipped.standard_reached > 0.0
    assert result.chosen is shipped and result.chosen.env_steps == 100_000
    # the figures are cached beside each actor: a second call scores nothing
    told.clear()
    again = reselect(tmp_path / "run", sets=SMALL, progress=told.append)
    assert told == [] and again.rows == result.rows
    target = write(result)
    assert target == tmp_path / "run" / RESELECTED
    assert target.read_bytes() == (folder / "actor-00100000.npz").read_bytes()
    report = json.loads((tmp_path / "run" / "reselection.json").read_text())
    assert report["chosen"]["env_steps"] == 100_000 and len(report["rows"]) == 2
    assert report["sets"] == SMALL.to_dict()


def test_the_tool_prints_the_choice_and_refuses_a_run_without_checkpoint_actors(
    tmp_path: Path,
) -> None:
    _two_checkpoint_run(tmp_path / "run")
    done = run_tool(
        "reselect.py", str(tmp_path / "run"), "--standard", "3", "--envelope", "2", "--dry-run"
    )
    assert done.returncode == 0, done.stderr
    assert "reselected the actor at 100,000 env steps" in done.stdout
    assert not (tmp_path / "run" / RESELECTED).exists()  # --dry-run writes nothing
    (tmp_path / "old").mkdir()
    refused = run_tool("reselect.py", str(tmp_path / "old"))
    assert refused.returncode == 2
    assert "no actor-STEPS.npz in checkpoint-actors/" in refused.stderr


def test_an_actor_of_an_arm_without_an_envelope_is_refused_plainly(tmp_path: Path) -> None:
    folder = tmp_path / "bravo" / CHECKPOINT_ACTORS
    folder.mkdir(parents=True)
    still_actor(folder / "actor-00050000.npz", BRAVO7)
    with pytest.raises(ValueError, match="Bravo 7; the held-out sets draw arms around"):
        reselect(tmp_path / "bravo", sets=SMALL)
    refused = run_tool("reselect.py", str(tmp_path / "bravo"))
    assert refused.returncode == 2 and "held-out sets draw arms" in refused.stderr
