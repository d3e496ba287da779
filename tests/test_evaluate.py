"""The evaluation runner and tools/evaluate.py (policy/campaigns/evaluate_command.py): what
the controller sees, what the arm gets, the JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import numpy as np
import pytest

from policy.campaigns.evaluate_command import Options, execute
from policy.campaigns.evaluation import (
    Episode,
    RunConfig,
    evaluate,
    load_controller,
    load_episodes,
    random_episodes,
    run_episode,
)
from policy.campaigns.paper.markdown import seed_lines
from policy.campaigns.paper.settings import BEGIN, END, write_generated
from policy.controllers.observation import WORKSPACE_HIGH, WORKSPACE_LOW
from policy.tasks import scenarios
from reach_driver.errors import DriverError
from reach_driver.metrics import ALL_METRIC_KEYS
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.sensors import SensorNoise

ROOT = Path(__file__).resolve().parents[1]
START = np.array([3.0, 1.5, 1.5, 1.5])


class Recorder:
    """Applies a fixed current and remembers every state it was shown."""

    def __init__(self, current: Any = (0.0, 0.0, 0.0, 0.0)) -> None:
        self.current = np.asarray(current, dtype=float)
        self.seen: list[Any] = []
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1
        self.seen.clear()

    def act(self, state: Any, target: np.ndarray) -> np.ndarray:
        self.seen.append(state)
        return self.current.copy()


def test_runner_holds_each_command_for_one_control_period() -> None:
    current = np.array([200.0, -150.0, 100.0, 50.0])
    cfg = RunConfig(seconds=0.5, rate_hz=20.0)
    result = run_episode(Recorder(current), Episode(START, START + 0.3), cfg)
    arm = Alpha5Arm()
    arm.reset(q=START)
    for k in range(cfg.n_steps):  # the same arm stepped by hand: 25 substeps per period
        arm.step(current, n=25)
        np.testing.assert_allclose(result.trace.q[k + 1], arm.q, atol=1e-12)
    np.testing.assert_allclose(result.currents_mA[1:], np.tile(current, (cfg.n_steps, 1)))
    assert result.trace.q.shape == (11, 4)


def test_controller_sees_true_state_without_noise_and_period_times() -> None:
    ctrl = Recorder([300.0, 0.0, 0.0, 0.0])
    result = run_episode(ctrl, Episode(START, START), RunConfig(seconds=1.0, rate_hz=10.0))
    assert ctrl.resets == 1
    assert [s.t for s in ctrl.seen] == pytest.approx([0.1 * k for k in range(10)])
    for k, s in enumerate(ctrl.seen):
        np.testing.assert_array_equal(s.q, result.trace.q[k])
        np.testing.assert_array_equal(s.qdot, result.trace.qdot[k])
    assert result.trace.q[-1, 0] > START[0] + 0.2  # 300 mA on the base yaw moved it


def test_sensor_noise_has_the_stated_spread_and_is_seeded() -> None:
    cfg = RunConfig(seconds=20.0, noise=SensorNoise(), seed=3)
    a, b = Recorder(), Recorder()
    res = run_episode(a, Episode(START, START), cfg, episode_seed=3)
    run_episode(b, Episode(START, START), cfg, episode_seed=3)
    dq = np.array([s.q for s in a.seen]) - res.trace.q[:-1]
    dv = np.array([s.qdot for s in a.seen]) - res.trace.qdot[:-1]
    assert 0.0018 < dq.std() < 0.0022
    assert 0.018 < dv.std() < 0.022
    np.testing.assert_array_equal([s.q for s in a.seen], [s.q for s in b.seen])


def test_torque_scale_is_applied_per_episode() -> None:
    push = [400.0, 0.0, 0.0, 0.0]
    weak = run_episode(
        Recorder(push),
        Episode(START, START, torque_scale=np.array([0.25, 1, 1, 1])),
        RunConfig(seconds=0.2),
    )
    full = run_episode(Recorder(push), Episode(START, START), RunConfig(seconds=0.2))
    moved_weak = weak.trace.q[-1, 0] - START[0]
    moved_full = full.trace.q[-1, 0] - START[0]
    assert 0 < moved_weak < 0.5 * moved_full


def test_parameter_perturbation_changes_the_arm_reproducibly() -> None:
    ep = Episode(START, START)
    push = [300.0, 300.0, 300.0, 100.0]
    nominal = run_episode(Recorder(push), ep, RunConfig(seconds=0.3))
    a = run_episode(Recorder(push), ep, RunConfig(seconds=0.3, param_spread=0.2), episode_seed=1)
    b = run_episode(Recorder(push), ep, RunConfig(seconds=0.3, param_spread=0.2), episode_seed=1)
    np.testing.assert_array_equal(a.trace.q, b.trace.q)
    assert np.abs(a.trace.q[-1] - nominal.trace.q[-1]).max() > 1e-3


def test_energy_integrates_power_at_the_physics_rate() -> None:
    result = run_episode(Recorder([500.0, 0, 0, 0]), Episode(START, START), RunConfig(seconds=1))
    arm = Alpha5Arm()
    arm.reset(q=START)
    energy = 0.0
    for _ in range(500):
        arm.step(np.array([500.0, 0, 0, 0]), n=1)
        energy += float(np.abs(arm.tau * arm.qdot).sum()) * 0.002
    assert result.metrics.energy_j == pytest.approx(energy, rel=1e-9)
    assert energy > 1.0


def test_bad_controller_output_and_bad_episodes_are_rejected() -> None:
    with pytest.raises(ValueError, match="expected 4 finite currents"):
        run_episode(Recorder([np.nan, 0, 0, 0]), Episode(START, START), RunConfig(seconds=0.1))
    with pytest.raises(ValueError, match="outside the arm's joint limits on D"):
        run_episode(
            Recorder(), Episode(START, np.array([3.0, 3.6, 1.5, 1.5])), RunConfig(seconds=0.1)
        )
    with pytest.raises(ValueError, match="torque_scale must be in"):
        Episode(START, START, torque_scale=np.array([2, 1, 1, 1]))
    with pytest.raises(ValueError, match="whole number of physics"):
        RunConfig(rate_hz=30.0)


def test_random_episodes_fill_the_workspace_reproducibly() -> None:
    eps = random_episodes(200, seed=5)
    starts = np.array([e.start for e in eps])
    targets = np.array([e.target for e in eps])
    for arr in (starts, targets):
        assert np.all(arr >= WORKSPACE_LOW) and np.all(arr <= WORKSPACE_HIGH)
        assert np.all(arr.max(axis=0) - arr.min(axis=0) > 0.9 * (WORKSPACE_HIGH - WORKSPACE_LOW))
    again = random_episodes(200, seed=5)
    np.testing.assert_array_equal(targets, [e.target for e in again])


def test_load_episodes_reports_where_the_file_is_wrong(tmp_path: Path) -> None:
    good = tmp_path / "good.json"
    good.write_text(
        json.dumps(
            [{"start": [1, 1, 1, 1], "target": [2, 2, 2, 2], "torque_scale": [0.25, 1, 1, 1]}]
        )
    )
    (ep,) = load_episodes(good)
    np.testing.assert_array_equal(ep.torque_scale, [0.25, 1, 1, 1])
    cases = {
        "[": "not valid JSON",
        "{}": "non-empty JSON list",
        '[{"start": [1, 1, 1, 1]}]': r"episode 0: missing \['target'\]",
        '[{"start": [1,1,1,1], "target": [1,1,1]}]': "target must be 4 finite numbers",
        '[{"start": [1,1,1,1], "target": [1,1,1,1], "speed": 3}]': "unknown keys",
    }
    for text, message in cases.items():
        bad = tmp_path / "bad.json"
        bad.write_text(text)
        with pytest.raises(ValueError, match=message):
            load_episodes(bad)
    with pytest.raises(ValueError, match="cannot read targets file"):
        load_episodes(tmp_path / "missing.json")


def test_unknown_controller_lists_the_installed_ones() -> None:
    with pytest.raises(DriverError, match=r"unknown controller 'nope'; registered: .*pid"):
        load_controller("nope")


def test_evaluation_json_has_exactly_the_metric_keys() -> None:
    eps = [Episode(START, START + 0.1), Episode(START, START - 0.1)]
    ev = evaluate(Recorder(), eps, RunConfig(seconds=0.5), name="idle")
    out = ev.to_dict()
    assert out["controller"] == "idle"
    assert len(out["episodes"]) == 2
    for episode in out["episodes"]:
        assert set(episode["metrics"]) == set(ALL_METRIC_KEYS)
        assert episode["reached"] is False  # an idle controller never gets there
        assert len(episode["final_error"]) == 4
        over = episode["overshoot"]  # how it came about, or None when nothing went past
        pct = episode["metrics"]["overshoot_pct"]
        assert (over is None and pct == 0.0) or over["pct"] == pytest.approx(pct)
    assert set(out["summary"]) == set(ALL_METRIC_KEYS) | {"rmse_floor"}
    assert out["summary"]["reached"] == 0.0


def test_cli_runs_pid_and_writes_json(tmp_path: Path) -> None:
    targets = tmp_path / "t.json"
    targets.write_text(
        json.dumps([{"start": [3.0, 1.5, 1.5, 1.5], "target": [3.2, 1.6, 1.4, 1.6]}])
    )
    out = tmp_path / "out.json"
    code = execute(Options(controller="pid", targets=targets, seconds=4.0, out=out, quiet=True))
    assert code == 0
    data = json.loads(out.read_text())
    assert data["controller"] == "pid" and data["config"]["seconds"] == 4
    assert data["episodes"][0]["reached"] is True
    assert data["summary"]["reached"] == 1.0


def test_cli_bad_input_exits_2_with_a_message(tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "o.json"
    assert execute(Options(controller="nope", random=1, out=out)) == 2
    assert "unknown controller 'nope'" in capsys.readouterr().err
    assert execute(Options(controller="pid", random=0, out=out)) == 2
    assert not out.exists()


def test_cli_help_explains_the_options() -> None:
    tool = [sys.executable, str(ROOT / "tools" / "evaluate.py"), "--help"]
    proc = subprocess.run(tool, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    for word in (
        "--controller",
        "--targets",
        "--random",
        "--noise",
        "--rate",
        "--via-driver",
        "--record",
        "E [0.4, 5.8]",
    ):
        assert word in text


def test_cli_record_writes_a_readable_recording(tmp_path: Path) -> None:
    from reach_driver.rrd_summary import read_recording

    rrd = tmp_path / "eval.rrd"
    options = Options(controller="pid", random=2, seed=1, seconds=1.0, out=tmp_path / "o.json")
    code = execute(replace(options, record=rrd, quiet=True))
    assert code == 0
    run = read_recording(rrd)
    assert run.q.shape == (2 * 21, 4)  # two episodes of 20 periods plus their initial states
    data = json.loads((tmp_path / "o.json").read_text())
    first = data["episodes"][0]
    np.testing.assert_allclose(run.target[0], first["target"])
    np.testing.assert_allclose(run.q[0], first["start"])


def test_paper_scenarios_map_inside_the_arm_limits() -> None:
    paper = scenarios
    limits = Alpha5Arm().position_limits
    for sc in paper.SCENARIOS:
        ep = sc.episode()
        for q in (ep.start, ep.target):
            assert np.all(q >= limits[:, 0]) and np.all(q <= limits[:, 1])
        np.testing.assert_allclose(paper.arm_to_paper(ep.target), sc.paper_target)
    assert paper.SCENARIOS[2].episode().torque_scale.tolist() == [0.25, 1, 1, 1]
    np.testing.assert_allclose(
        paper.paper_to_arm([2.64, 0.26, -1.47, 0.82]),
        [2.64 + np.pi, 0.26 + 1.71045, -1.47 + np.pi, 0.82 + np.pi],
    )


def test_paper_replaces_only_its_generated_block(tmp_path: Path) -> None:
    doc = tmp_path / "results.md"
    doc.write_text(f"intro\n{BEGIN}\nold table\n{END}\noutro\n")
    write_generated(doc, f"{BEGIN}\nnew table\n{END}")
    assert doc.read_text() == f"intro\n{BEGIN}\nnew table\n{END}\noutro\n"


def test_paper_counts_the_learned_policys_wins_over_mpc_across_seeds() -> None:
    keys = (*scenarios.TABLE_KEYS, "reached")

    def ev(*values: float) -> SimpleNamespace:
        return SimpleNamespace(summary=lambda: dict(zip(keys, values, strict=True)))

    mpc = ev(10.7, 0.23, 0.90, 0.0014, 1.9, 1.86, 1.0)
    table = {"mpc": mpc, "ddpg": ev(10.4, 0.22, 0.88, 0.0015, 0.3, 1.86, 1.0)}
    more = {2120: {"mpc": mpc, "ddpg": ev(10.9, 0.22, 0.88, 0.0010, 0.3, 1.80, 1.0)}}
    assert scenarios.wins(table["ddpg"].summary(), mpc.summary()) == {
        "energy_j": True,
        "rmse": True,
        "mie": True,
        "msse": False,
        "overshoot_pct": True,
        "settling_time_s": False,
    }  # a tie is not a win
    text = "\n".join(seed_lines(more, table, 2020, 20))
    assert "| 2020 | ddpg | 10.40 |" in text and "| 2120 | mpc | 10.70 |" in text
    assert (
        "on 2 seeds: energy 1/2, RMSE 2/2, MIE 2/2, MSSE 1/2, overshoot 2/2, settling time 1/2."
        in text
    )


def _select() -> ModuleType:
    """The selection rule tools/select_weights.py runs."""
    import policy.campaigns.selection

    return policy.campaigns.selection


def test_select_weights_rule_reaches_first_then_counts_wins() -> None:
    select = _select()
    keys = scenarios.TABLE_KEYS
    ref = dict(zip(keys, (10.0, 0.23, 0.90, 0.0014, 2.0, 1.9), strict=True))

    def row(name: str, scen: int, reached: float, *values: float) -> dict[str, Any]:
        summary = dict(zip(keys, values, strict=True), reached=reached)
        return {"candidate": name, "scenarios_reached": scen, "summary": summary}

    rows = [
        row("misses a scenario", 3, 1.0, 9.0, 0.20, 0.80, 0.0010, 0.1, 1.5),
        row("misses an episode", 4, 0.95, 9.0, 0.20, 0.80, 0.0010, 0.1, 1.5),
        row("5 of 6", 4, 1.0, 9.0, 0.20, 0.80, 0.0010, 0.1, 2.0),
        row("6 of 6, barely", 4, 1.0, 9.99, 0.229, 0.89, 0.00139, 1.9, 1.89),
        row("6 of 6, clearly", 4, 1.0, 9.5, 0.22, 0.85, 0.0012, 0.5, 1.8),
    ]
    assert select.choose(rows, ref)["candidate"] == "6 of 6, clearly"
    rows[-1]["restless"] = [17]  # chatters on one screened arm: never shipped
    assert select.choose(rows, ref)["candidate"] == "6 of 6, barely"
    assert select.choose(rows[:3], ref)["candidate"] == "5 of 6"
    assert select.choose(rows[:2], ref) is None
    with pytest.raises(FileNotFoundError, match="no actor"):
        select.weights_of(ROOT / "no-such-run")


def test_stability_screen_flags_a_chattering_policy() -> None:
    select = _select()

    class BangBang:  # full current, sign flipping every period: the failure the screen is for
        sign = 1.0

        def reset(self) -> None:
            pass

        def act(self, state: Any, target: np.ndarray) -> np.ndarray:
            self.sign = -self.sign
            return np.full(4, 600.0 * self.sign)

    shipped = ROOT / "policy" / "controllers" / "weights" / "ddpg_distilled_actor.npz"
    assert select.restless_episodes(
        shipped, 2, seed=3, perturb=0.2, factory=lambda _p: BangBang()
    ) == [0, 1]
    assert select.restless_episodes(shipped, 2, seed=3, perturb=0.2) == []  # shipped: at rest
