"""The Bravo 7's Table I set: its episodes, the direct runner on its twin, six-joint scores,
and tools/table1_line.py's --arm bravo7 (a table, and actors of the other arm refused)."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from policy.campaigns import table1_line
from policy.campaigns.direct import DirectArm
from policy.campaigns.evaluation import RunConfig, evaluate, load_controller
from policy.controllers.observation import Workspace
from policy.tasks.arm import nominal_arm
from policy.tasks.episodes import random_episodes
from protocol.models import ALPHA5, BRAVO7
from reach_driver.metrics import (
    REACHED_TOL_RAD,
    REST_ENERGY_AFTER_SETTLING_MAX_J,
    compute_metrics,
    rest_energy_limit_j,
)
from reach_sim_bridge.model.bravo7 import Bravo7Arm

ROOT = Path(__file__).resolve().parents[1]


def tool() -> ModuleType:
    """tools/table1_line.py as a module (it is a script, not a package)."""
    spec = importlib.util.spec_from_file_location("table1_line_tool", ROOT / "tools/table1_line.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bravo_episodes_are_drawn_in_the_bravos_workspace() -> None:
    episodes = random_episodes(50, 7020, model=BRAVO7)
    low, high = (np.asarray(v) for v in (Workspace.of(BRAVO7).low, Workspace.of(BRAVO7).high))
    q = np.array([[e.start, e.target] for e in episodes]).reshape(-1, 6)
    assert all(e.model is BRAVO7 and e.torque_scale.tolist() == [1.0] * 6 for e in episodes)
    assert np.all(q >= low) and np.all(q <= high)
    # over the whole of it: D and B (4th and 6th) turn a whole turn on the Bravo, past 2.9 rad
    assert q[:, 3].max() > 5.0 and q[:, 5].max() > 5.0 and q.min() < 0.6


def test_the_pid_brings_a_bravo_episode_to_its_target_on_all_six_joints() -> None:
    episode = random_episodes(1, 7020, model=BRAVO7)[0]
    assert np.all(np.abs(episode.target - episode.start) > 0.03)  # every joint has to move
    config = RunConfig(seconds=8.0)
    result = DirectArm(model=BRAVO7).run(load_controller("pid", arm=BRAVO7), episode, config, 0)
    steps = config.n_steps + 1
    assert result.trace.q.shape == (steps, 6) and result.trace.qdot.shape == (steps, 6)
    assert result.currents_mA.shape == (steps, 6) and result.trace.tau.shape == (steps, 6)
    np.testing.assert_allclose(result.trace.q[0], episode.start)
    final = result.trace.q[-1]
    assert np.all(np.abs(final - episode.target) < REACHED_TOL_RAD), final - episode.target
    assert result.final_error.shape == (6,)
    out = result.to_dict()
    assert len(out["final_error"]) == 6 and len(out["start"]) == 6
    anatomy = result.overshoot
    assert anatomy is None or out["overshoot"]["joint"] in BRAVO7.joint_letters
    # at rest by the Bravo's own bound: holding its heavier links spends more than the
    # Alpha's 0.5 J after settling, with no chatter (no reversal, no speed)
    still = compute_metrics(result.trace)
    assert still.command_reversals == 0 and still.rest_speed_rms < 0.01
    assert REST_ENERGY_AFTER_SETTLING_MAX_J < still.energy_after_settling_j
    assert still.energy_after_settling_j <= rest_energy_limit_j(BRAVO7) and still.at_rest


def test_table_conditions_degrade_the_bravo_twin_and_score_six_joints() -> None:
    arms: list[Any] = []

    def keep(seed: int) -> Any:
        arms.append(nominal_arm(seed, model=BRAVO7))
        return arms[-1]

    episodes = random_episodes(2, 7020, model=BRAVO7)
    config = dataclasses.replace(table1_line.table_config(7020), seconds=2.0)
    ev = evaluate(
        load_controller("pid", arm=BRAVO7), episodes, config, backend=DirectArm(keep, BRAVO7)
    )
    nominal = Bravo7Arm.nominal()
    for arm in arms:  # each episode's arm is its own +-20 % draw around the nominal Bravo
        ratio = np.asarray(arm.params.damping) / np.asarray(nominal.damping)
        assert ratio.shape == (6,) and np.all(np.abs(ratio - 1.0) <= 0.2)
        assert np.any(np.abs(ratio - 1.0) > 0.01)
    assert not np.allclose(arms[0].params.link_mass_kg, arms[1].params.link_mass_kg)
    summary = ev.summary()
    assert all(len(e["final_error"]) == 6 for e in ev.to_dict()["episodes"])
    assert all(np.isfinite(summary[k]) for k in ("energy_j", "rmse", "mie", "msse"))


def test_a_bravo_episode_on_an_alpha_runner_is_refused() -> None:
    episode = random_episodes(1, 7020, model=BRAVO7)[0]
    with pytest.raises(ValueError, match="episode of the Reach Bravo 7 on a runner of the Reach"):
        DirectArm().run(load_controller("pid"), episode, RunConfig(seconds=1.0), 0)
    # the default backend is the episodes' own arm's
    assert evaluate(load_controller("pid", arm=BRAVO7), [episode], RunConfig(seconds=0.5)).results


def test_the_tool_prints_the_bravos_table_as_markdown(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(table1_line, "EPISODES_PER_SEED", 2)
    monkeypatch.setattr(
        table1_line,
        "table_config",
        lambda seed: RunConfig(seconds=3.0, seed=seed, param_spread=0.2),
    )
    code = tool().main(["--arm", "bravo7", "--controllers", "pid", "--runs", str(tmp_path)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "Table I on the Reach Bravo 7: 2 episodes (seeds 7020)" in out
    rows = [line for line in out.splitlines() if line.startswith("|")]
    assert rows[0].startswith("| controller | reached | at rest | energy [J] | RMSE [rad]")
    assert rows[2].startswith("| pid | ") and rows[2].count("[") == 8  # 8 intervals
    kept = list(tmp_path.glob("pid-*-seed7020.json"))
    assert len(kept) == 1 and kept[0].name != table1_line._cache_name("pid", {}, 7020)


@pytest.mark.parametrize("arm", ["bravo7", "alpha5"])
def test_an_actor_of_the_other_arm_is_refused_in_one_line(
    arm: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if arm == "bravo7":
        actor, theirs = "shipped", ALPHA5
    else:
        sys.path.insert(0, str(ROOT / "tests"))
        from test_learned_policy import bravo_actor_file

        actor, theirs = str(bravo_actor_file(tmp_path)), BRAVO7
    code = tool().main(["--arm", arm, actor, "--runs", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("error: ")
    assert f"an actor for the {theirs.title}, not the" in err and f"--arm {theirs.name}" in err
    assert not (tmp_path / "runs").exists()  # refused before anything ran


def test_evaluate_runs_bravo_targets_and_keeps_the_other_backends_to_the_alpha(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from policy.campaigns.evaluate_command import Options, execute

    episode = random_episodes(1, 7020, model=BRAVO7)[0]
    targets = tmp_path / "t.json"
    targets.write_text(json.dumps([episode.to_dict()]))
    out = tmp_path / "out.json"
    options = Options(
        controller="pid", targets=targets, seconds=8.0, out=out, quiet=True, arm="bravo7"
    )
    assert execute(options) == 0
    data = json.loads(out.read_text())
    assert np.all(np.abs(data["episodes"][0]["final_error"]) < REACHED_TOL_RAD)
    assert len(data["episodes"][0]["final_error"]) == 6
    # the same six angles as an Alpha's episode: refused, naming the joints it wants
    assert execute(dataclasses.replace(options, arm="alpha5")) == 2
    assert "start must be 4 finite numbers (E D C B)" in capsys.readouterr().err
    assert execute(dataclasses.replace(options, via_driver=True)) == 2
    assert "run the Alpha 5 only" in capsys.readouterr().err
