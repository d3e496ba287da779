"""tools/train.py tells the truth: progress that does not swallow the evaluation lines, `--set`
on `--resume` applied or refused by name, and Ctrl-C exits 130 after its checkpoint."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import wait_until

from policy.rl.config import DDPGConfig
from policy.rl.overrides import resume_overrides

ROOT = Path(__file__).resolve().parents[1]
TRAIN = str(ROOT / "tools" / "train.py")
#: a training run cut to a few hundred steps that evaluates twice: seconds, not minutes
TINY_STEPS = [
    "--set",
    "num_envs=2",
    "--set",
    "eval_every=200",
    "--set",
    "eval_episodes=2",
    "--set",
    "learning_starts=100",
    "--set",
    "buffer_size=5000",
    "--set",
    "hidden=[16,16]",
    "--set",
    "batch_size=32",
    "--set",
    "env.episode_s=5.0",
]
#: the distilled stack's recipe so cut, with two demonstration episodes
TINY = ["--config", "ours", *TINY_STEPS, "--set", "demo_episodes=2"]
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def _train(*argv: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, TRAIN, *argv],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})},
    )


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """One finished tiny run (400 steps), its stdout drawn as on a terminal."""
    run = tmp_path_factory.mktemp("train") / "run"
    out = _train(
        "--run",
        str(run),
        "--steps",
        "400",
        *TINY,
        env={"TTY_COMPATIBLE": "1", "TTY_INTERACTIVE": "1", "COLUMNS": "160"},
    )
    assert out.returncode == 0, out.stderr
    return run, out.stdout


def _checkpoint_config(run: Path) -> dict[str, object]:
    return torch.load(run / "checkpoint.pt", weights_only=False)["config"]  # type: ignore[no-any-return]


def test_evaluation_lines_are_lines_of_their_own_beside_the_bar(tiny_run) -> None:
    _run, stdout = tiny_run
    assert "\r" in stdout or "\x1b[" in stdout  # the bar was drawn (live, on a "terminal")
    # every piece between line breaks and carriage returns, without colour and cursor codes
    pieces = [ANSI.sub("", p) for p in re.split(r"[\r\n]", stdout)]
    evals = [p for p in pieces if "eval @" in p]
    assert len(evals) == 2, stdout
    for line in evals:
        assert re.match(r"^\[\d\d:\d\d:\d\d\] eval @ \d+: reached", line), repr(line)
        assert "━" not in line and "training" not in line, repr(line)
    assert any("demonstrations" in p and "2/2" in p for p in pieces), stdout  # its own bar
    assert any("training" in p and "400/400" in p for p in pieces), stdout


def test_resume_applies_a_batch_size_and_learning_rate(tiny_run, tmp_path) -> None:
    run, _ = tiny_run
    copy = tmp_path / "run"
    subprocess.run(["cp", "-r", str(run), str(copy)], check=True)
    out = _train(
        "--run",
        str(copy),
        "--resume",
        "--steps",
        "600",
        "--set",
        "batch_size=64",
        "--set",
        "actor_lr=0.0001",
        "--no-progress",
    )
    assert out.returncode == 0, out.stderr
    assert "--set on resume: batch_size 32 -> 64" in out.stdout, out.stdout
    assert "actor_lr 0.0003 -> 0.0001" in out.stdout
    saved = _checkpoint_config(copy)
    assert saved["batch_size"] == 64 and saved["actor_lr"] == 0.0001
    assert saved["total_steps"] == 600
    assert json.loads((copy / "config.json").read_text())["batch_size"] == 64
    assert "resumed at 400 env steps" in out.stdout


@pytest.mark.parametrize(
    ("override", "field"),
    [("hidden=[32,32]", "hidden"), ("env.episode_s=4.0", "env"), ("num_envs=4", "num_envs")],
)
def test_resume_refuses_what_cannot_change_naming_the_field(
    tiny_run, tmp_path, override, field
) -> None:
    run, _ = tiny_run
    copy = tmp_path / "run"
    subprocess.run(["cp", "-r", str(run), str(copy)], check=True)
    commands = (copy / "commands.txt").read_text()
    before = _checkpoint_config(copy)
    out = _train("--run", str(copy), "--resume", "--set", override, "--no-progress")
    assert out.returncode != 0
    assert f"--resume --set: {field} cannot change on a resumed run" in out.stderr, out.stderr
    assert "batch_size" in out.stderr  # it says what can change
    assert (copy / "commands.txt").read_text() == commands  # a refused command is not recorded
    assert _checkpoint_config(copy) == before


def test_resume_with_an_unchanged_fixed_field_is_fine(tiny_run, tmp_path) -> None:
    config = DDPGConfig.from_dict(_checkpoint_config(tiny_run[0]))
    new, changes = resume_overrides(config, ["hidden=[16,16]", "batch_size=48"])
    assert changes == ["batch_size 32 -> 48"] and new.hidden == (16, 16)


def test_ctrl_c_saves_a_checkpoint_and_exits_130(tmp_path) -> None:
    run = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, TRAIN, "--run", str(run), "--steps", "200000", *TINY, "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        # training proper has begun once an episode is in train.csv
        csv = run / "train.csv"
        assert wait_until(lambda: csv.exists() and csv.read_text().count("\n") >= 2, 120)
        time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (proc.returncode, out, err)
    assert "interrupted (SIGINT): saving a checkpoint" in out
    assert "checkpoint saved at" in out
    steps = torch.load(run / "checkpoint.pt", weights_only=False)["state"]["env_steps"]
    assert 0 < steps < 200000


def test_the_best_actor_records_how_it_was_trained(tiny_run: tuple[Path, str]) -> None:
    """tools/train.py's command (from commands.txt) reaches the exported actor's provenance."""
    run, _ = tiny_run
    provenance = json.loads((run / "best_actor.json").read_text())["provenance"]
    command = (run / "commands.txt").read_text().splitlines()[0]
    assert provenance["command"] == command and f"--run {run}" in command
    assert provenance["algorithm"].startswith("TD3 + behaviour cloning")
    assert provenance["demonstrations"] == "2 episodes of a privileged PD expert"
    assert provenance["teacher"].startswith("PDExpert (privileged")
    assert provenance["stages"][0]["run"] == "run" and provenance["stages"][0]["init_actor"] is None


#: the scratch recipe cut to a few hundred steps (its collector process kept)
TINY_SCRATCH = TINY_STEPS


def test_arm_bravo7_trains_the_scratch_recipe_on_the_bravos_six_joints(tmp_path) -> None:
    run = tmp_path / "bravo"
    out = _train("--arm", "bravo7", "--run", str(run), "--steps", "400", *TINY_SCRATCH)
    assert out.returncode == 0, out.stderr
    assert (
        "Reach Bravo 7: 6 joints G F E D C B; envelope arms 0, param perturbation 0 (the "
        "Alpha 5's parameters only)"
    ) in out.stdout
    config = json.loads((run / "config.json").read_text())
    assert config["name"] == "scratch" and config["collector_process"] is True
    assert config["env"]["arm"] == "bravo7" and config["eval_envelope_episodes"] == 0
    assert config["env"]["torque_scale_low"] == [0.25, 1, 1, 1, 1, 1]
    best = json.loads((run / "best_actor.json").read_text())
    assert best["arm"] == "bravo7" and best["provenance"]["env_steps"] > 0
    assert "G25%" in out.stdout  # the weak checkpoint set: the base joint at 25 %
    # the run is the Bravo's: resumed as such, never as an Alpha's
    wrong = _train("--arm", "alpha5", "--run", str(run), "--resume", "--no-progress")
    assert wrong.returncode != 0
    assert "--arm alpha5: the run in" in wrong.stderr and "Reach Bravo 7" in wrong.stderr
    # and its actor is not shipped over the Alpha 5's `ddpg`
    shipped = _train("--run", str(run), "--ship")
    assert shipped.returncode != 0 and "give --ship-as FILE.npz" in shipped.stderr


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--config", "ours"], "--arm bravo7: config 'ours' learns from the Alpha 5's PD"),
        (["--evaluate", "shipped"], "--arm bravo7: --params and --evaluate are the Alpha 5's"),
    ],
)
def test_arm_bravo7_refuses_what_is_the_alpha_5s_in_one_line(tmp_path, argv, expected) -> None:
    out = _train("--arm", "bravo7", "--run", str(tmp_path / "run"), *argv, "--no-progress")
    assert out.returncode != 0
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(expected), out.stderr
    assert "Traceback" not in out.stderr and not (tmp_path / "run" / "checkpoint.pt").exists()
