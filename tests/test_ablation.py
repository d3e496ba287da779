"""The ablation: ingredients by name, every run's actor on the same held-out test episodes,
and intervals over seeds and episodes (policy.campaigns.ablation, tools/ablation.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import run_tool

from policy.campaigns import ablation
from policy.campaigns.ablation import (
    BASELINE,
    INGREDIENTS,
    HeldOutSets,
    ingredient,
    markdown,
    score_root,
    summarize,
)
from policy.campaigns.stats import interval, seed_episode_bootstrap
from policy.controllers.weights import LEARNED_WEIGHTS
from policy.rl.config import DDPGConfig
from policy.rl.overrides import apply_overrides


def test_every_ingredient_is_a_valid_override_of_the_recipe() -> None:
    recipe = DDPGConfig.scratch()
    for item in INGREDIENTS:
        changed = apply_overrides(recipe, list(item.overrides))
        assert (changed == recipe) == (item.name == BASELINE), item.name
    assert ingredient("no-away").overrides == ("env.reward.away_weight=0",)
    with pytest.raises(ValueError, match="unknown ingredient 'salt'"):
        ingredient("salt")


def test_two_level_bootstrap_counts_the_spread_between_seeds() -> None:
    rng = np.random.default_rng(3)
    alike = rng.normal(0.0, 1.0, size=(3, 50))
    apart = alike + np.array([[-5.0], [0.0], [5.0]])  # the same episodes, seeds far apart
    low_a, high_a = interval(seed_episode_bootstrap(alike, 2000))
    low_b, high_b = interval(seed_episode_bootstrap(apart, 2000))
    assert high_b - low_b > 5 * (high_a - low_a)
    assert low_a < alike.mean() < high_a
    # constant runs: every resample is that constant
    assert np.all(seed_episode_bootstrap(np.full((2, 4), 7.0), 100) == 7.0)
    with pytest.raises(ValueError, match="seeds, episodes"):
        seed_episode_bootstrap(np.ones(5))


def _runs(reached: list[list[float]], overshoot: float) -> dict[int, dict[str, list]]:
    out: dict[int, dict[str, list]] = {}
    for seed, row in enumerate(reached):
        episodes = [
            {"reached": r, "at_rest": 1.0, "overshoot_pct": overshoot, "msse": 0.001, "energy_j": 1}
            for r in row
        ]
        out[seed] = {"standard": episodes, "envelope": episodes}
    return out


def test_summary_resolves_a_clear_loss_and_not_a_tie() -> None:
    scores = {
        BASELINE: _runs([[1, 1, 1, 1]] * 3, 1.0),
        "no-away": _runs([[0, 0, 0, 0]] * 3, 1.0),
        "no-fine": _runs([[1, 0, 1, 0], [0, 1, 0, 1], [1, 1, 0, 0]], 5.0),
    }
    summary = summarize(scores, resamples=2000)
    assert list(summary) == [BASELINE, "no-away", "no-fine"]  # the ingredients' order
    lost = summary["no-away"]["figures"]["standard reached %"]
    assert lost.mean == 0.0 and lost.diff == -100.0 and lost.resolved
    half = summary["no-fine"]["figures"]["standard reached %"]
    assert half.mean == 50.0 and half.low < 50.0 < half.high
    small = summary["no-fine"]["figures"]["envelope overshoot < 2 %"]
    assert small.mean == 0.0 and small.diff == -100.0
    assert summary[BASELINE]["figures"]["standard reached %"].diff is None
    table = markdown(summary)
    assert table.count("\n") == 2 + 3
    assert "| no-away | 0, 1, 2 | 0.0 [0.0, 0.0]<br>**-100.0 [-100.0, -100.0]**" in table


def test_score_root_runs_each_actor_on_the_test_sets_once(tmp_path: Path) -> None:
    for seed in (0, 1):
        run = tmp_path / BASELINE / f"seed-{seed}"
        run.mkdir(parents=True)
        shutil.copy(LEARNED_WEIGHTS, run / "best_actor.npz")
        shutil.copy(LEARNED_WEIGHTS.with_suffix(".json"), run / "best_actor.json")
    (tmp_path / BASELINE / "seed-x").mkdir()  # not a run: ignored
    sets = HeldOutSets(standard=2, envelope=1, seed=123)
    scored: list[str] = []
    scores = score_root(tmp_path, sets, scored.append)
    assert scored == ["baseline seed 0", "baseline seed 1"]
    assert sorted(scores[BASELINE]) == [0, 1]
    first = scores[BASELINE][0]
    assert [len(first["standard"]), len(first["envelope"])] == [2, 1]
    assert set(first["standard"][0]) == set(ablation.EPISODE_KEYS)
    # the same actor on the same episodes: the same figures
    assert scores[BASELINE][0] == scores[BASELINE][1]
    again: list[str] = []
    assert score_root(tmp_path, sets, again.append) == scores
    assert again == []  # kept beside each actor
    other = HeldOutSets(standard=1, envelope=1, seed=123)
    assert len(score_root(tmp_path, other, again.append)[BASELINE][0]["standard"]) == 1
    assert again == ["baseline seed 0", "baseline seed 1"]


def test_tool_lists_ingredients_and_refuses_what_it_cannot_score(tmp_path: Path) -> None:
    listed = run_tool("ablation.py", "--list")
    assert listed.returncode == 0
    assert "no-memory" in listed.stdout and "env.reward.away_weight=0" in listed.stdout
    missing = run_tool("ablation.py", str(tmp_path / "nowhere"))
    assert missing.returncode == 2 and "no directory" in missing.stderr
    empty = run_tool("ablation.py", str(tmp_path))
    assert empty.returncode == 2 and "best_actor.npz" in empty.stderr
