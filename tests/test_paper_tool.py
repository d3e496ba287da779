"""tools/paper.py (policy/campaigns/paper/) writes docs only when asked, and its defaults are
the committed table's."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from policy.campaigns.evaluation import RunConfig, random_episodes
from policy.campaigns.paper.command import Options, execute, settings_from
from policy.campaigns.paper.markdown import _fmt_row
from policy.campaigns.paper.settings import BEGIN, COMMITTED, END, recorded_settings
from policy.campaigns.paper.table import load_table, summary
from reach_sim_bridge.model.sensors import SensorNoise

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "results.md"
# a tiny run: one controller, one 1-second episode, no other seeds
QUICK: dict[str, Any] = {"controllers": ["pid"], "n": 1, "seconds": 1.0, "more_seeds": []}


@pytest.fixture
def docs(tmp_path: Path) -> Path:
    """A copy of the repository's docs/results.md in a scratch docs folder."""
    d = tmp_path / "docs"
    d.mkdir()
    shutil.copyfile(DOC, d / "results.md")
    return d


def _run(tmp_path: Path, docs: Path, **extra: Any) -> int:
    """What `tools/paper.py` does with these options; the exit code."""
    return execute(Options(**QUICK, runs=tmp_path / "runs", docs=docs, **extra))


def test_without_write_docs_nothing_under_docs_changes(tmp_path: Path, docs: Path) -> None:
    before = (docs / "results.md").read_bytes()
    assert _run(tmp_path, docs, skip_scenarios=True) == 0
    assert (docs / "results.md").read_bytes() == before
    assert sorted(p.name for p in docs.iterdir()) == ["results.md"]
    runs = tmp_path / "runs"
    assert (runs / "table_pid.json").exists()
    block = (runs / "results_block.md").read_text()
    assert block.startswith(BEGIN) and block.rstrip().endswith(END)
    assert "| pid |" in block and "95 % confidence intervals" in block


def test_write_docs_refuses_other_settings(
    tmp_path: Path, docs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = (docs / "results.md").read_bytes()
    assert _run(tmp_path, docs, skip_scenarios=True, write_docs=True) == 2
    out = capsys.readouterr().out
    assert "refusing" in out and "--force" in out and "n: 1 here, 20 there" in out
    assert (docs / "results.md").read_bytes() == before
    assert not (tmp_path / "runs").exists()  # refused before anything ran


def test_write_docs_refuses_a_different_bootstrap(tmp_path: Path, docs: Path) -> None:
    args: dict[str, Any] = {"write_docs": True, "runs": tmp_path / "runs", "docs": docs}
    assert execute(Options(**args, resamples=100)) == 2
    assert execute(Options(**args, ci_seed=3)) == 2
    assert not (tmp_path / "runs").exists()


def test_write_docs_force_replaces_only_the_block(tmp_path: Path, docs: Path) -> None:
    before = (docs / "results.md").read_text()
    assert _run(tmp_path, docs, write_docs=True, force=True) == 0
    after = (docs / "results.md").read_text()
    head, rest = before.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    assert after.startswith(head + BEGIN) and after.endswith(END + tail)
    block = after[len(head) : len(after) - len(tail)]
    assert block != before[len(head) : len(before) - len(tail)]
    assert "1 random targets" in block and "| pid |" in block
    for n in range(1, 5):
        assert (docs / "figures" / f"scenario{n}.png").stat().st_size > 0
        assert f"](figures/scenario{n}.png)" in block
    recorded = recorded_settings(docs / "results.md")
    assert recorded is not None and recorded.n == 1 and recorded.controllers == ("pid",)
    # the same settings again: no --force needed, the table there was made with them
    assert _run(tmp_path, docs, write_docs=True, skip_scenarios=True) == 2  # differs: no scenarios
    assert _run(tmp_path, docs, write_docs=True, reuse=True) == 0


def test_defaults_are_the_committed_tables_settings(tmp_path: Path, docs: Path) -> None:
    args = Options()
    assert settings_from(args) == COMMITTED
    assert args.write_docs is False
    assert recorded_settings(DOC) == COMMITTED
    # the tool's own defaults, as a user runs it: only the bootstrap asked for differs from
    # the table in the docs (refused before anything runs)
    tool = [sys.executable, str(ROOT / "tools" / "paper.py"), "--write-docs", "--resamples"]
    argv = [*tool, "100", "--runs", str(tmp_path / "runs"), "--docs", str(docs)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    out = " ".join(proc.stdout.split())  # the settings' differences would come first
    assert "of the table there: bootstrap: 100 resamples, seed 0 here" in out, out
    assert not (tmp_path / "runs").exists()
    block = DOC.read_text().split(BEGIN, 1)[1].split(END, 1)[0]
    assert (
        "### Table I: 20 random targets (seed 2020, sensor noise sigma 0.002 rad / 0.02 rad/s, "
        "arm parameters degraded by U(1 +- 0.2), 20 s at 20 Hz)" in block
    )


def test_reuse_only_takes_a_matching_run(tmp_path: Path, docs: Path) -> None:
    assert _run(tmp_path, docs, skip_scenarios=True) == 0
    path = tmp_path / "runs" / "table_pid.json"
    run = json.loads(path.read_text())
    episodes = random_episodes(1, 2020)
    config = RunConfig(seconds=1.0, noise=SensorNoise(0.002, 0.02), seed=2020, param_spread=0.2)
    assert load_table(path, "pid", config, episodes) == run
    assert load_table(path, "mpc", config, episodes) is None
    assert load_table(path, "pid", config, random_episodes(1, 7)) is None
    other = RunConfig(seconds=1.0, seed=2020, param_spread=0.2)  # no noise
    assert load_table(path, "pid", other, episodes) is None


def test_new_metric_fields_do_not_change_table_i() -> None:
    """A metrics module that gains fields (numeric or not) leaves the six columns alone."""
    base = {"energy_j": 1.0, "rmse": 0.2, "mie": 0.9, "msse": 0.001}
    base |= {"overshoot_pct": 2.0, "settling_time_s": 1.5, "reached": True}
    plain = {"episodes": [{"metrics": dict(base), "rmse_floor": 0.19}] * 2}
    extra = {"episodes": [{"metrics": base | {"at_rest": None, "rest_s": 3.0}, "rmse_floor": 0.19}]}
    extra["episodes"] *= 2
    s0, s1 = summary(plain), summary(extra)
    assert "at_rest" not in s1 and s1["rest_s"] == 3.0
    assert _fmt_row("x", s0) == _fmt_row("x", s1)
    assert {k: s1[k] for k in s0} == s0
