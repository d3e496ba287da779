"""tools/sweep.py: training seed sweeps on Ray Tune, each trial the trainer's Python API.

The trial itself (`policy.campaigns.parallel.run_trial`) is checked without Tune: a tiny run
reports each checkpoint evaluation and leaves its run directory. The sweep on Tune (two seeds, both
trials reporting) needs Ray Tune, whose requirements (pandas) the extra ``ray[tune]`` brings."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from policy.campaigns import parallel as campaign
from policy.campaigns.sweep import run_sweep, sweep_config

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "eval_every=150",
    "eval_episodes=2",
    "learning_starts=100",
    "batch_size=32",
    "buffer_size=2000",
    "env.episode_s=5",
]


def _sweep(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """tools/sweep.py run as a user runs it."""
    return subprocess.run(
        [sys.executable, str(ROOT / "tools" / "sweep.py"), *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


def _tune_available() -> bool:
    try:
        campaign.import_tune()
    except campaign.RayUnavailable:
        return False
    return True


def test_a_trial_trains_and_reports_every_evaluation(tmp_path: Path) -> None:
    config = sweep_config("paper", 300, TINY)
    reports: list[dict[str, Any]] = []
    campaign.run_trial(
        {"seed": 5, "training": config.to_dict(), "root": str(tmp_path)}, reports.append
    )
    assert [r["env_steps"] for r in reports] == [150, 300]
    assert all(r["seed"] == 5 for r in reports)
    assert reports[-1]["best_score"] == max(r["score"] for r in reports)
    run_dir = tmp_path / "seed-5"
    assert (run_dir / "best_actor.npz").exists() and (run_dir / "checkpoint.pt").exists()
    assert json.loads((run_dir / "config.json").read_text())["seed"] == 5
    with pytest.raises(ValueError, match="already holds a run"):
        campaign.run_trial({"seed": 5, "training": config.to_dict(), "root": str(tmp_path)}, print)


def test_bad_settings_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--steps"):
        sweep_config("ours", 0, [])
    with pytest.raises(ValueError, match="no_such_key"):
        sweep_config("ours", 10, ["no_such_key=1"])
    with pytest.raises((ValueError, campaign.CampaignError), match="distinct|Ray Tune"):
        run_sweep(sweep_config("ours", 10, []), [1, 1], tmp_path)
    # the command line says so on stderr, with exit status 2
    out = _sweep("--seeds", "0", "1", "--out", str(tmp_path), "--steps", "0")
    assert out.returncode == 2, out.stdout + out.stderr
    assert "--steps" in out.stderr


@pytest.mark.skipif(_tune_available(), reason="Ray Tune is installed")
def test_without_tune_the_message_names_the_extra(tmp_path: Path) -> None:
    argv = [
        "--seeds",
        "0",
        "1",
        "--steps",
        "300",
        "--out",
        str(tmp_path),
        *sum((["--set", s] for s in TINY), []),
    ]
    out = _sweep(*argv)
    assert out.returncode == 2
    assert "ray[tune]" in out.stderr


@pytest.mark.slow
@pytest.mark.skipif(not _tune_available(), reason="needs Ray Tune: pip install 'ray[tune]'")
def test_a_two_seed_sweep_on_tune_reports_both_trials(tmp_path: Path) -> None:
    argv = ["--config", "paper", "--seeds", "0", "1", "--steps", "300", "--workers", "1"]
    argv += ["--out", str(tmp_path), "--quiet", *sum((["--set", s] for s in TINY), [])]
    out = _sweep(*argv, timeout=900)
    assert out.returncode == 0, out.stdout + out.stderr
    result = json.loads((tmp_path / "sweep.json").read_text())
    trials = result["trials"]
    assert [t["seed"] for t in trials] == [0, 1]
    for t in trials:
        assert t["error"] is None
        assert [r["env_steps"] for r in t["reports"]] == [150, 300]
        assert t["final"]["seed"] == t["seed"]
        assert (tmp_path / f"seed-{t['seed']}" / "best_actor.npz").exists()
    assert trials[0]["final"]["score"] != trials[1]["final"]["score"]  # two seeds, two runs


def test_ablate_names_an_ingredient_or_is_refused(tmp_path: Path) -> None:
    bad = _sweep("--ablate", "salt", "--seeds", "0", "--steps", "10", "--out", str(tmp_path))
    assert bad.returncode == 2
    assert "unknown ingredient 'salt'" in bad.stderr
    assert not any(tmp_path.iterdir())  # refused before anything ran
