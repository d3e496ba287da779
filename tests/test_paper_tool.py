"""tools/paper.py writes docs only when asked, and its defaults are the committed table's."""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "results.md"


def _paper() -> ModuleType:
    spec = importlib.util.spec_from_file_location("paper_tool", ROOT / "tools" / "paper.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["paper_tool"] = module
    spec.loader.exec_module(module)
    return module


paper = _paper()
# a tiny run: one controller, one 1-second episode, no other seeds
QUICK = ["--controllers", "pid", "--n", "1", "--seconds", "1", "--more-seeds"]


@pytest.fixture
def docs(tmp_path: Path) -> Path:
    """A copy of the repository's docs/results.md in a scratch docs folder."""
    d = tmp_path / "docs"
    d.mkdir()
    shutil.copyfile(DOC, d / "results.md")
    return d


def _run(tmp_path: Path, docs: Path, *extra: str) -> int:
    rc: int = paper.main([*QUICK, "--runs", str(tmp_path / "runs"), "--docs", str(docs), *extra])
    return rc


def test_without_write_docs_nothing_under_docs_changes(tmp_path: Path, docs: Path) -> None:
    before = (docs / "results.md").read_bytes()
    assert _run(tmp_path, docs, "--skip-scenarios") == 0
    assert (docs / "results.md").read_bytes() == before
    assert sorted(p.name for p in docs.iterdir()) == ["results.md"]
    runs = tmp_path / "runs"
    assert (runs / "table_pid.json").exists()
    block = (runs / "results_block.md").read_text()
    assert block.startswith(paper.BEGIN) and block.rstrip().endswith(paper.END)
    assert "| pid |" in block and "95 % confidence intervals" in block


def test_write_docs_refuses_other_settings(
    tmp_path: Path, docs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = (docs / "results.md").read_bytes()
    assert _run(tmp_path, docs, "--skip-scenarios", "--write-docs") == 2
    out = capsys.readouterr().out
    assert "refusing" in out and "--force" in out and "n: 1 here, 20 there" in out
    assert (docs / "results.md").read_bytes() == before
    assert not (tmp_path / "runs").exists()  # refused before anything ran


def test_write_docs_refuses_a_different_bootstrap(tmp_path: Path, docs: Path) -> None:
    args = ["--write-docs", "--runs", str(tmp_path / "runs"), "--docs", str(docs)]
    assert paper.main([*args, "--resamples", "100"]) == 2
    assert paper.main([*args, "--ci-seed", "3"]) == 2
    assert not (tmp_path / "runs").exists()


def test_write_docs_force_replaces_only_the_block(tmp_path: Path, docs: Path) -> None:
    before = (docs / "results.md").read_text()
    assert _run(tmp_path, docs, "--write-docs", "--force") == 0
    after = (docs / "results.md").read_text()
    head, rest = before.split(paper.BEGIN, 1)
    tail = rest.split(paper.END, 1)[1]
    assert after.startswith(head + paper.BEGIN) and after.endswith(paper.END + tail)
    block = after[len(head) : len(after) - len(tail)]
    assert block != before[len(head) : len(before) - len(tail)]
    assert "1 random targets" in block and "| pid |" in block
    for n in range(1, 5):
        assert (docs / "figures" / f"scenario{n}.png").stat().st_size > 0
        assert f"](figures/scenario{n}.png)" in block
    recorded = paper.recorded_settings(docs / "results.md")
    assert recorded is not None and recorded.n == 1 and recorded.controllers == ("pid",)
    # the same settings again: no --force needed, the table there was made with them
    assert _run(tmp_path, docs, "--write-docs", "--skip-scenarios") == 2  # differs: no scenarios
    assert _run(tmp_path, docs, "--write-docs", "--reuse") == 0


def test_defaults_are_the_committed_tables_settings() -> None:
    args = paper.build_parser().parse_args([])
    assert paper.settings_from(args) == paper.COMMITTED
    assert args.write_docs is False
    assert paper.recorded_settings(DOC) == paper.COMMITTED
    block = DOC.read_text().split(paper.BEGIN, 1)[1].split(paper.END, 1)[0]
    assert (
        "### Table I: 20 random targets (seed 2020, sensor noise sigma 0.002 rad / 0.02 rad/s, "
        "arm parameters degraded by U(1 +- 0.2), 20 s at 20 Hz)" in block
    )


def test_reuse_only_takes_a_matching_run(tmp_path: Path, docs: Path) -> None:
    assert _run(tmp_path, docs, "--skip-scenarios") == 0
    path = tmp_path / "runs" / "table_pid.json"
    run = json.loads(path.read_text())
    episodes = paper.random_episodes(1, 2020)
    config = paper.RunConfig(
        seconds=1.0, noise=paper.SensorNoise(0.002, 0.02), seed=2020, param_spread=0.2
    )
    assert paper.load_table(path, "pid", config, episodes) == run
    assert paper.load_table(path, "mpc", config, episodes) is None
    assert paper.load_table(path, "pid", config, paper.random_episodes(1, 7)) is None
    other = paper.RunConfig(seconds=1.0, seed=2020, param_spread=0.2)  # no noise
    assert paper.load_table(path, "pid", other, episodes) is None


def test_new_metric_fields_do_not_change_table_i() -> None:
    """A metrics module that gains fields (numeric or not) leaves the six columns alone."""
    base = {"energy_j": 1.0, "rmse": 0.2, "mie": 0.9, "msse": 0.001}
    base |= {"overshoot_pct": 2.0, "settling_time_s": 1.5, "reached": True}
    plain = {"episodes": [{"metrics": dict(base), "rmse_floor": 0.19}] * 2}
    extra = {"episodes": [{"metrics": base | {"at_rest": None, "rest_s": 3.0}, "rmse_floor": 0.19}]}
    extra["episodes"] *= 2
    s0, s1 = paper.summary(plain), paper.summary(extra)
    assert "at_rest" not in s1 and s1["rest_s"] == 3.0
    assert paper._fmt_row("x", s0) == paper._fmt_row("x", s1)
    assert {k: s1[k] for k in s0} == s0
