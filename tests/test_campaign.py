"""Campaigns on Ray (policy/campaigns/parallel.py, tools/evaluate.py --workers): the serial run's
results, episode for episode, and a clear message when Ray is not installed."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from policy.campaigns import parallel as campaign
from policy.campaigns.evaluate_command import Options, execute
from policy.campaigns.evaluation import RunConfig, evaluate, load_controller, random_episodes
from reach_sim_bridge.model.sensors import SensorNoise

ROOT = Path(__file__).resolve().parents[1]
SEED = 31
CONFIG = RunConfig(seconds=3.0, noise=SensorNoise(), seed=SEED, param_spread=0.2)
COMMON: dict[str, Any] = {"controller": "pid", "random": 4, "seed": SEED, "seconds": 3.0}
COMMON |= {"noise": True, "perturb": 0.2, "quiet": True}


def evaluate_cli(**options: Any) -> int:
    """What `tools/evaluate.py` does with these options; the exit code."""
    return execute(Options(**COMMON, **options))


@pytest.fixture(scope="module")
def ray_local() -> Iterator[Any]:
    """One local Ray with 2 CPUs for the module (campaigns reuse it and leave it up)."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def test_two_workers_give_the_serial_results_episode_for_episode(ray_local: Any) -> None:
    episodes = random_episodes(4, SEED)
    serial = evaluate(load_controller("pid"), episodes, CONFIG, name="pid")
    seen: list[int] = []
    parallel = campaign.evaluate_parallel(
        "pid", {}, episodes, CONFIG, workers=2, on_episode=lambda i, r: seen.append(i)
    )
    assert sorted(seen) == [0, 1, 2, 3]
    assert parallel.summary() == serial.summary()
    for a, b in zip(serial.results, parallel.results, strict=True):
        assert a.metrics == b.metrics
        np.testing.assert_array_equal(a.trace.q, b.trace.q)
        np.testing.assert_array_equal(a.currents_mA, b.currents_mA)
    assert parallel.controller_stats["engine"] == "ray"


def test_cli_workers_2_writes_the_serial_json(ray_local: Any, tmp_path: Path) -> None:
    serial, parallel = tmp_path / "serial.json", tmp_path / "parallel.json"
    assert evaluate_cli(out=serial) == 0
    assert evaluate_cli(workers=2, out=parallel) == 0
    a, b = json.loads(serial.read_text()), json.loads(parallel.read_text())
    assert a["episodes"] == b["episodes"] and a["summary"] == b["summary"]


def test_without_ray_workers_name_the_extra(
    tmp_path: Path, capsys: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    out = tmp_path / "o.json"
    assert evaluate_cli(workers=2, out=out) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "needs Ray" in err and "pip install -e '.[scale]'" in err
    assert not out.exists()
    with pytest.raises(campaign.RayUnavailable, match=r"\.\[scale\]"):
        campaign.evaluate_parallel("pid", {}, random_episodes(1, 0), CONFIG, workers=1)


def test_workers_with_via_driver_or_below_one_are_refused(tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "o.json"
    assert evaluate_cli(workers=2, via_driver=True, out=out) == 2
    assert evaluate_cli(workers=0, out=out) == 2
    err = capsys.readouterr().err
    assert "--via-driver" in err and "at least 1" in err


def test_the_stability_screen_on_ray_gives_the_serial_metrics(ray_local: Any) -> None:
    from policy.campaigns.selection import screen

    shipped = ROOT / "policy" / "controllers" / "weights" / "ddpg_distilled_actor.npz"
    serial = screen(shipped, 2, seed=3, perturb=0.2)
    assert screen(shipped, 2, seed=3, perturb=0.2, workers=2) == serial
    assert all(m.at_rest for m in serial)
    with pytest.raises(ValueError, match="factory"):
        screen(shipped, 1, seed=3, perturb=0.2, factory=lambda _p: None, workers=2)


def test_the_code_fingerprint_follows_every_file_but_caches(tmp_path: Path) -> None:
    """`fingerprint` (what `code_fingerprint` takes of the packages) hashes the names and
    contents of their files, weights too, but not Python's byte-code caches."""
    pkg = tmp_path / "pkg"
    (pkg / "__pycache__").mkdir(parents=True)
    (pkg / "a.py").write_text("x = 1\n")
    (pkg / "w.npz").write_bytes(b"\x00\x01")
    first = campaign.fingerprint([pkg])
    (pkg / "__pycache__" / "a.cpython-311.pyc").write_bytes(b"cache")
    assert campaign.fingerprint([pkg]) == first
    (pkg / "w.npz").write_bytes(b"\x00\x02")
    assert campaign.fingerprint([pkg]) != first
    (pkg / "w.npz").write_bytes(b"\x00\x01")
    (pkg / "a.py").rename(pkg / "b.py")
    assert campaign.fingerprint([pkg]) != first


def test_a_worker_with_other_code_refuses_the_job() -> None:
    """A worker whose packages differ from the driver's (a campaign started inside one
    checkout with another on PYTHONPATH: Ray puts the starting directory first on its
    workers' path) fails the job with `CodeMismatch`, naming where it imported `policy` from;
    with the driver's fingerprint it runs the job."""
    code, where = campaign.code_fingerprint()
    assert campaign.checked_call(str, code, 7) == "7"
    with pytest.raises(campaign.CodeMismatch, match=f"policy from {where}"):
        campaign.checked_call(str, "0" * 64, 7)
