"""tools/robustness.py and policy/campaigns/robustness/: controllers over the uncertainty
envelope (policy/tasks/envelope.py).

Infeasible corners are left out and counted, each arm's episode depends on its own seed only,
serial and Ray runs agree episode for episode, the summary's intervals hold their means, and
--write-docs replaces a label's block in docs/robustness.md (or adds it at the marker)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from policy.campaigns.identify import fit_row
from policy.campaigns.robustness.arms import arm_episode, arm_twin, plan, subsample
from policy.campaigns.robustness.campaign import make_jobs, run_jobs
from policy.campaigns.robustness.command import Options, execute
from policy.campaigns.robustness.identification import identify_rows, verdict_table
from policy.campaigns.robustness.report import (
    COMPARISON,
    NEW_BLOCKS,
    anatomy_line,
    begin_marker,
    comparison_block,
    end_marker,
    overshoot_by_table,
)
from policy.campaigns.robustness.summary import (
    FACTOR_ORDER,
    METRICS,
    overshoot_by,
    overshoot_summary,
    summarize_rows,
)
from policy.tasks.envelope import corners
from reach_sim_bridge.model.params import ArmParams

ROOT = Path(__file__).resolve().parents[1]
SEED = 3
SECONDS = 3.0


def robustness(**options: Any) -> int:
    """What `tools/robustness.py` does with these options (its command line's values);
    the exit code."""
    return execute(Options(**options), command="tools/robustness.py")


@pytest.fixture(scope="module")
def corner_selection() -> Any:
    return corners()


def test_infeasible_corners_are_left_out_and_counted(corner_selection: Any) -> None:
    p = plan(SEED, True, None, corner_selection=corner_selection)
    n_in, n_out = len(p.arms), len(p.infeasible["corners"])
    assert n_in + n_out == 1280
    assert p.available["corners"] == n_in and n_out > 0
    left_out = {v.name for v, _ in p.infeasible["corners"]}
    assert left_out.isdisjoint(a.variant.name for a in p.arms)
    for v, why in p.infeasible["corners"]:
        assert "stall" in why  # the motor model's number
        assert v.factors["weak_joint"] >= 0  # only a weak joint makes an arm infeasible here


def test_an_arms_episode_and_noise_depend_on_its_own_seed(corner_selection: Any) -> None:
    small = subsample(896, 5, SEED)
    large = subsample(896, 50, SEED)
    assert set(small) <= set(large) and len(set(large)) == 50
    assert subsample(896, None, SEED) == list(range(896))
    a = arm_episode(SEED, "corners", 7)
    b = arm_episode(SEED, "corners", 7)
    np.testing.assert_array_equal(a.start, b.start)
    assert not np.array_equal(a.start, arm_episode(SEED, "draws", 7).start)
    p = plan(SEED, True, 4, max_corners=3, corner_selection=corner_selection)
    jobs = make_jobs("pid", {}, p.arms, SEED, SECONDS)
    for arm, job in zip(p.arms, jobs, strict=True):
        np.testing.assert_array_equal(job.episode.torque_scale, arm.variant.torque_scale)
        assert job.config.latency_periods == arm.variant.latency_periods
        assert job.config.noise is not None
        assert job.config.noise.position_std == pytest.approx(0.002 * arm.variant.noise_scale)
        assert job.index == arm.index


def test_twin_jobs_give_each_arm_its_own_parameters_and_latency(corner_selection: Any) -> None:
    """`--twin`: each arm's controller is told that arm (weak joint and latency included), as
    an identification would; `--twin-error` perturbs it reproducibly, within its bounds."""
    from reach_sim_bridge.model.params import ArmParams

    p = plan(SEED, True, 2, max_corners=3, corner_selection=corner_selection)
    jobs = make_jobs("lambda", {"lambda_factor": 4.0}, p.arms, SEED, SECONDS, twin_error=0.0)
    for arm, job in zip(p.arms, jobs, strict=True):
        params = json.loads(job.params_json)
        assert params["lambda_factor"] == 4.0
        assert params["latency_periods"] == arm.variant.latency_periods
        twin = ArmParams.from_json_dict(params["params"])
        assert twin.torque_scale == tuple(arm.variant.torque_scale)
        assert twin.frictionloss == arm.variant.params.frictionloss
        sensor = job.config.noise  # the arm's own noise, as a rest log would show it
        assert sensor is not None
        assert params["noise_q"] == pytest.approx(sensor.position_std)
        assert params["noise_v"] == pytest.approx(sensor.velocity_std)
        assert params["twin_error"] == 0.0
    assert arm_twin(p.arms[0], SEED, 0.05)["twin_error"] == 0.05
    off = [arm_twin(a, SEED, 0.05)["params"] for a in p.arms]
    assert off == [arm_twin(a, SEED, 0.05)["params"] for a in p.arms]  # seeded per arm
    for arm, twin in zip(p.arms, off, strict=True):
        ratio = np.asarray(twin["armature"]) / np.asarray(arm.variant.params.armature)
        assert np.all(np.abs(ratio - 1) <= 0.05) and np.any(ratio != 1)
        assert twin["torque_scale"] == list(arm.variant.torque_scale)
    plain = make_jobs("pid", {}, p.arms, SEED, SECONDS)
    assert {j.params_json for j in plain} == {"{}"}


def test_a_twin_campaign_records_how_its_twins_were_made(tmp_path: Path) -> None:
    """The tool as a user runs it: its options recorded in the results."""
    argv = ["--controller", "lambda", "--twin", "--twin-error", "0.02", "--draws", "1"]
    argv += ["--seconds", "2", "--out", str(tmp_path), "--quiet"]
    tool = [sys.executable, str(ROOT / "tools" / "robustness.py")]
    proc = subprocess.run([*tool, *argv], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    report = json.loads((tmp_path / "lambda.json").read_text())
    assert report["settings"]["twin_error"] == 0.02
    assert report["params"] == {}  # the twins are per arm, not the campaign's parameters
    assert "--twin-error 0.02" in report["command"]


def test_exported_arms_are_the_hidden_arms_and_fitted_twins_replace_them(
    tmp_path: Path,
) -> None:
    """`--export-arms` writes each planned arm (weak joint's torque scale, noise, latency) as a
    reach-sim parameter file; `--twin-from` gives the controller the fit found beside it and
    runs only the arms that have one."""
    from reach_sim_bridge.model.params import load_arm_params, save_arm_params

    argv: dict[str, Any] = {"draws": 3, "seed": SEED}
    assert robustness(**argv, export_arms=tmp_path / "arms") == 0
    p = plan(SEED, False, 3)
    for arm in p.arms:
        path = tmp_path / "arms" / f"draws-{arm.index}.json"
        hidden = load_arm_params(path)
        assert hidden.torque_scale == tuple(arm.variant.torque_scale)
        assert hidden.frictionloss == arm.variant.params.frictionloss
        meta = json.loads(path.read_text())["_envelope"]
        assert meta["latency_periods"] == arm.variant.latency_periods
        assert meta["sensor_noise"][0] == pytest.approx(0.002 * arm.variant.noise_scale)
    fit = replace(load_arm_params(tmp_path / "arms" / "draws-1.json"), damping=(1, 1, 1, 0.1))
    save_arm_params(fit, tmp_path / "fits" / "draws-1.json", {"_fit": {"note": "ignored"}})
    jobs = make_jobs(
        "lambda", {}, p.arms, SEED, SECONDS, twin_error=0.01, fitted={("draws", 1): fit}
    )
    told = [ArmParams.from_json_dict(json.loads(j.params_json)["params"]) for j in jobs]
    assert told[1] == fit  # as fitted, not spread by twin_error as an arm without a fit is
    assert told[0] == ArmParams.from_json_dict(arm_twin(p.arms[0], SEED, 0.01)["params"])
    assert json.loads(jobs[1].params_json)["twin_error"] == 0.01  # the trust, not a spread
    out = tmp_path / "out"
    run = {**argv, "controller": ["lambda"], "twin": True, "seconds": 1.0, "quiet": True}
    assert robustness(**run, twin_from=tmp_path / "fits", out=out) == 0
    report = json.loads((out / "lambda.json").read_text())
    assert [e["index"] for e in report["episodes"]] == [1]
    assert report["settings"]["twin_from"] == "fits"
    assert robustness(**run, twin_from=tmp_path / "arms" / "none") == 2
    assert robustness(**argv, controller=["lambda"], twin_from=tmp_path) == 2


def _small_plan(corner_selection: Any) -> Any:
    return plan(SEED, True, 2, max_corners=2, corner_selection=corner_selection)


def test_serial_and_ray_give_the_same_results(corner_selection: Any) -> None:
    pytest.importorskip("ray")
    jobs = make_jobs("pid", {}, _small_plan(corner_selection).arms, SEED, SECONDS)
    serial = run_jobs(jobs, None, None)
    seen: list[int] = []
    ray = run_jobs(jobs, 1, None, lambda pair: seen.append(pair[0]))
    assert sorted(seen) == sorted(j.index for j in jobs)
    for a, b in zip(serial, ray, strict=True):
        assert a.metrics == b.metrics
        np.testing.assert_array_equal(a.trace.q, b.trace.q)


def test_the_summary_holds_its_means_and_names_the_failures() -> None:
    rng = np.random.default_rng(0)
    rows: list[dict[str, Any]] = []
    for i in range(40):
        latency = [0.0, 2.0][i % 2]
        missed = latency > 1 and i % 4 == 1
        factors = dict.fromkeys(FACTOR_ORDER, 1.0)
        factors.update(weak_joint=-1.0, latency_periods=latency, coulomb_edc=6.6 * (i % 3 == 0))
        rows.append(
            {
                "set": "corners",
                "name": f"arm {i}",
                "factors": factors,
                "metrics": {
                    "reached": not missed,
                    "at_rest": True,
                    "overshoot_pct": float(rng.uniform(0, 5)),
                    "settling_time_s": float(rng.uniform(1, 6)),
                    "energy_j": float(rng.uniform(5, 20)),
                },
            }
        )
    s = summarize_rows(rows)
    for key, _, _ in METRICS:
        assert s[key]["low"] <= s[key]["mean"] <= s[key]["high"]
    assert s["missed"] == 10 and s["reached"]["mean"] == pytest.approx(0.75)
    assert s["worst"][0]["overshoot_pct"] == max(r["metrics"]["overshoot_pct"] for r in rows)
    by_latency = {c["level"]: c for c in s["by_factor"] if c["factor"] == "latency_periods"}
    assert by_latency["high"]["missed"] == 10 and by_latency["low"]["missed"] == 0
    assert s["shared"][0].startswith("latency_periods high: 50 % missed (10/20)")
    assert {c["latency_periods"] for c in s["worst_pair"]} == {"low", "high"}
    assert sum(c["missed"] for c in s["worst_pair"]) == 10


def test_the_summary_says_how_the_overshoots_came_about() -> None:
    """Arms over 2 %, split by their worst joint's crossing speed (an arrival carried through,
    or slowly across near the goal), with the median distance past and how many stayed
    within 3 sigma of their position noise; omitted for rows written before it existed."""
    factors = dict.fromkeys(FACTOR_ORDER, 1.0)

    def row(pct: float, joint: str, past: float, speed: float, noise: float = 1.0) -> dict:
        return {
            "name": "arm",
            "factors": {**factors, "noise": noise, "weak_joint": -1.0},
            "metrics": {"overshoot_pct": pct},
            "overshoot": {"joint": joint, "past_rad": past, "peak_s": 1.0, "crossing_speed": speed},
        }

    rows = [
        row(5.0, "B", 0.030, 1.1),
        row(3.0, "B", 0.050, 0.9),
        row(4.0, "C", 0.020, 0.01),
        row(6.0, "D", 0.005, 0.002, noise=1.0),  # 5 mrad: within 3 x 2 mrad
        row(1.0, "E", 0.040, 1.0),  # under 2 %: not counted
        {**row(0.0, "E", 0.0, 0.0), "overshoot": None},  # nothing past its goal
    ]
    a = overshoot_summary(rows)
    assert a is not None and a["over"] == 4
    assert a["arrival"]["arms"] == 2 and a["arrival"]["by_joint"]["B"] == 2
    assert a["arrival"]["median_past_mrad"] == pytest.approx(40.0)
    assert a["near_goal"]["arms"] == 2 and a["near_goal"]["within_noise"] == 1
    assert a["near_goal"]["by_joint"] == {"E": 0, "D": 1, "C": 1, "B": 0}
    line = anatomy_line(a)
    assert "(4 arms)" in line and "median 40 mrad past; B 2;" in line
    old = [{k: v for k, v in r.items() if k != "overshoot"} for r in rows]
    assert overshoot_summary(old) is None


def test_the_overshoot_is_grouped_by_the_levels_asked_for() -> None:
    """Per combination of levels: arms, arms over 2 %, those of them past the 20 mrad
    tolerance and those carried through by their approach, the medians; a factor the
    envelope does not have is a clear error."""
    factors = dict.fromkeys(FACTOR_ORDER, 1.0)

    def row(latency: float, coulomb: float, pct: float, past: float, speed: float) -> dict:
        f = {**factors, "weak_joint": -1.0, "latency_periods": latency, "coulomb_edc": coulomb}
        anatomy = {"joint": "C", "past_rad": past, "peak_s": 1.0, "crossing_speed": speed}
        return {"factors": f, "metrics": {"overshoot_pct": pct}, "overshoot": anatomy}

    rows = [
        row(2.0, 0.0, 40.0, 0.100, 1.1),  # latent, frictionless: carried through, far past
        row(2.0, 0.0, 3.0, 0.010, 0.05),  # over 2 % but within the tolerance, crept across
        row(2.0, 0.0, 1.0, 0.004, 0.02),  # under 2 %
        row(0.0, 6.6, 2.5, 0.030, 0.5),
        {**row(0.0, 6.6, 0.0, 0.0, 0.0), "overshoot": None},  # never past its goal
    ]
    groups = overshoot_by(rows, ["latency_periods", "coulomb_edc"])
    by = {(g["levels"]["latency_periods"], g["levels"]["coulomb_edc"]): g for g in groups}
    assert set(by) == {("high", "low"), ("low", "high")}
    latent = by[("high", "low")]
    assert (latent["arms"], latent["over"], latent["over_past_tolerance"]) == (3, 2, 1)
    assert latent["arrivals"] == 1
    assert latent["median_pct"] == pytest.approx(3.0)
    assert latent["median_past_mrad"] == pytest.approx(10.0)
    prompt = by[("low", "high")]
    assert (prompt["arms"], prompt["over"], prompt["over_past_tolerance"]) == (2, 1, 1)
    assert prompt["median_past_mrad"] == pytest.approx(15.0)
    table = overshoot_by_table(groups).splitlines()
    assert table[0].startswith("| latency_periods | coulomb_edc | arms |")
    assert table[2] == "| high | low | 3 | 2 | 1 | 1 | 3 | 10 |"
    with pytest.raises(ValueError, match="latency_periods"):
        overshoot_by(rows, ["lag"])


def test_a_run_writes_rows_a_summary_and_the_docs_block(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = tmp_path / "robustness.md"
    doc.write_text(f"# head\n\n{NEW_BLOCKS}\n\ntail\n", encoding="utf-8")
    argv = {"controller": ["pid"], "corners": True, "max_corners": 2, "draws": 2}
    argv |= {"seed": SEED, "seconds": SECONDS, "out": tmp_path}
    assert robustness(**argv, quiet=True, write_docs=True, doc=doc) == 0
    report = json.loads((tmp_path / "pid.json").read_text())
    assert [r["set"] for r in report["episodes"]] == ["corners"] * 2 + ["draws"] * 2
    assert report["infeasible"]["corners"] == 384 and report["available"]["corners"] == 896
    row = report["episodes"][0]
    assert set(FACTOR_ORDER) <= set(row["factors"]) and "at_rest" in row["metrics"]
    assert all("overshoot" in r for r in report["episodes"])
    text = doc.read_text()
    assert text.count(begin_marker("pid")) == 1 and text.endswith("tail\n")
    assert "| corners | 2 of 896 |" in text
    assert "reached" in capsys.readouterr().out
    # regenerated from the saved results: the block is replaced, not added again
    report["summary"] = {}
    report["label"] = "pid"
    (tmp_path / "pid.json").write_text(json.dumps(report))
    regenerate = {"from_files": [tmp_path / "pid.json"], "write_docs": True, "doc": doc}
    assert robustness(**regenerate) == 0
    again = doc.read_text()
    assert again.count(begin_marker("pid")) == 1 and "| draws | 2 |" in again
    # a run with other settings does not replace the block without --force
    report["settings"]["draws"] = 1000
    (tmp_path / "pid.json").write_text(json.dumps(report))
    capsys.readouterr()
    assert robustness(**regenerate) == 2
    assert "--force" in capsys.readouterr().err and doc.read_text() == again
    assert robustness(**regenerate, force=True) == 0
    assert '"draws": 1000' in doc.read_text()


def test_the_shipped_docs_have_the_markers_the_tool_writes() -> None:
    """The comparison on the page users read, each controller's block and the new-blocks marker
    on the tables page, once each across both."""
    page = (ROOT / "docs" / "robustness.md").read_text(encoding="utf-8")
    tables = (ROOT / "docs" / "robustness-tables.md").read_text(encoding="utf-8")
    assert NEW_BLOCKS in tables and NEW_BLOCKS not in page
    assert page.count(begin_marker(COMPARISON)) == 1 and page.count(end_marker(COMPARISON)) == 1
    for label in ("ddpg-distilled", "ddpg-distilled-pure", "pid", "mpc"):
        assert tables.count(begin_marker(label)) == 1, label
        assert tables.count(end_marker(label)) == 1, label
        assert begin_marker(label) not in page, label


def test_blocks_are_written_where_they_are_and_new_ones_at_the_marker(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`write_docs` over several files: a block is replaced in the file that holds it, a new
    label goes before the marker, the comparison stays where it is, and an untouched file is
    not rewritten. (The blocks' contents are tested above; here each is just its label.)"""
    import policy.campaigns.robustness.command as command

    def block(label: str) -> str:
        return f"{begin_marker(label)}\n**{label}**\n{end_marker(label)}"

    monkeypatch.setattr(command, "markdown_block", lambda report: block(report["label"]))
    monkeypatch.setattr(command, "comparison_block", lambda reports: block(COMPARISON))
    page, tables, other = tmp_path / "page.md", tmp_path / "tables.md", tmp_path / "other.md"
    page.write_text(f"{begin_marker(COMPARISON)}\nold\n{end_marker(COMPARISON)}\n")
    tables.write_text(f"{begin_marker('pid')}\nold\n{end_marker('pid')}\n{NEW_BLOCKS}\n")
    other.write_text("untouched\n")
    reports: list[dict[str, Any]] = [{"label": label, "settings": {}} for label in ("pid", "new")]
    assert command.write_docs([page, tables, other], reports, force=True) == [page, tables]
    text = tables.read_text()
    assert "old" not in text and text.index("**new**") < text.index(NEW_BLOCKS)
    assert page.read_text().count(f"**{COMPARISON}**") == 1 and "**new**" not in page.read_text()
    assert other.read_text() == "untouched\n"


@pytest.mark.parametrize(
    "argv, message",
    [
        ({"controller": ["pid"]}, "nothing to run"),
        ({"corners": True}, "--controller"),
        ({"controller": ["nope"], "draws": 1}, "nope"),
        ({"controller": ["pid", "ddpg-distilled"], "label": "x", "draws": 1}, "--label"),
        ({"controller": ["pid"], "max_corners": 3, "draws": 1}, "--corners"),
        ({"controller": ["pid"], "draws": 1, "workers": 0}, "--workers"),
        ({"controller": ["pid"], "draws": 1, "overshoot_by": ["lag"]}, "latency_periods"),
        ({"controller": ["lambda"], "draws": 1, "twin_error": 0.1}, "--twin"),
        ({"controller": ["lambda"], "draws": 1, "twin": True, "twin_error": 1.0}, "[0, 1)"),
        ({"controller": ["pid"], "draws": 1, "twin": True}, "latency_periods"),
    ],
)
def test_bad_arguments_are_clear_errors(
    argv: dict[str, Any], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert robustness(**argv, out=tmp_path, quiet=True) == 2
    assert message in capsys.readouterr().err


def test_the_comparison_uses_only_the_arms_every_run_shares() -> None:
    def report(label: str, indices: list[int], reached: bool) -> dict[str, Any]:
        factors = dict.fromkeys(FACTOR_ORDER, 1.0)
        factors["weak_joint"] = -1.0
        metrics = {"reached": reached, "at_rest": True, "overshoot_pct": 1.0}
        metrics.update(settling_time_s=2.0, energy_j=10.0)
        rows = [
            {"set": "draws", "index": i, "name": f"d{i}", "factors": factors, "metrics": metrics}
            for i in indices
        ]
        return {"label": label, "episodes": rows}

    runs = [report("a", [0, 1, 2, 3], True), report("b", [1, 3, 5], False)]
    block = comparison_block([*runs, report("c", [1], True)])
    assert "| draws | 2 | a | 100.0 % [100.0, 100.0] |" in block
    assert "| draws | 2 | b | 0.0 % [0.0, 0.0] |" in block
    assert "| draws | 1 | c |" in block and "| draws | 1 | b |" in block
    assert "| draws | 4 |" not in block  # a alone is no comparison
    assert "corners" not in block


def test_an_actor_file_runs_under_its_own_label(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    weights = ROOT / "policy" / "controllers" / "weights" / "ddpg_distilled_actor.npz"
    argv: dict[str, Any] = {"controller": ["ddpg-distilled"], "label": "robust"}
    argv |= {"param": [f"weights={weights}"]}
    argv |= {"draws": 1, "seconds": 2.0, "out": tmp_path, "quiet": True}
    assert robustness(**argv) == 0
    report = json.loads((tmp_path / "robust.json").read_text())
    assert report["label"] == "robust" and report["params"] == {"weights": str(weights)}
    assert robustness(**{**argv, "param": [f"weights={tmp_path / 'none.npz'}"]}) == 2
    assert "none.npz" in capsys.readouterr().err


def test_params_move_the_whole_envelope_and_are_recorded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--params FILE.json` is the arm the envelope spreads around (here friction that holds):
    every arm carries it, the results record what differs from the nominal arm, and a bad file
    is a clear error."""
    from reach_sim_bridge.model.params import ArmParams

    holds = ArmParams(friction_holds=True)
    p = plan(SEED, False, 3, base=holds)
    assert all(a.variant.params.friction_holds for a in p.arms)
    assert not any(a.variant.params.friction_holds for a in plan(SEED, False, 3).arms)
    params = tmp_path / "holds.json"
    params.write_text('{"friction_holds": true}')
    argv = {"controller": ["pid"], "draws": 1, "seed": SEED, "seconds": 1.0}
    assert robustness(**argv, params=params, out=tmp_path, quiet=True) == 0
    report = json.loads((tmp_path / "pid.json").read_text())
    assert report["settings"]["params"] == {"friction_holds": True}
    params.write_text('{"friction_hold": true}')
    capsys.readouterr()
    assert robustness(**argv, params=params, out=tmp_path, quiet=True) == 2
    assert "did you mean 'friction_holds'" in capsys.readouterr().err


def test_a_fit_is_scored_against_the_arm_its_currents_show() -> None:
    """A drive at torque scale s looks, from its currents, like an arm with armature, damping
    and Coulomb friction divided by s: a fit that finds that is exact, not 4x off."""
    from policy.campaigns.identify import fit_errors

    hidden = ArmParams(torque_scale=(1.0, 0.25, 1.0, 1.0)).to_json_dict()
    fitted = dict(hidden, torque_scale=[1.0] * 4)  # the weak drive found as a heavier joint
    fitted["armature"] = [
        hidden["armature"][0] * 1.1,
        hidden["armature"][1] * 4,
        *hidden["armature"][2:],
    ]
    fitted["frictionloss"] = [
        hidden["frictionloss"][0],
        hidden["frictionloss"][1] * 4 + 0.5,
        *hidden["frictionloss"][2:],
    ]
    fitted["_fit"] = {"quality_fitted": {"validate/D": {"window": {"rms_mrad": 3.0}}}}
    err = fit_errors(hidden, fitted)
    assert err["E"]["armature_ratio"] == pytest.approx(1.1)
    assert err["D"]["armature_ratio"] == pytest.approx(1.0)
    assert err["D"]["damping_ratio"] == pytest.approx(0.25)  # the fit left it nominal
    assert err["D"]["coulomb_error_nm"] == pytest.approx(0.5)
    assert err["D"]["validate_rms_mrad_fitted"] == 3.0
    assert err["D"]["validate_rms_mrad_nominal"] is None  # not in the fit's metadata
    as_scale = dict(hidden, _fit={})  # the weak drive found as its scale: the same arm
    assert fit_errors(hidden, as_scale)["D"]["armature_ratio"] == pytest.approx(1.0)
    assert fit_errors(hidden, as_scale)["D"]["torque_scale"] == 0.25


@pytest.mark.slow
def test_an_identification_campaign_fits_its_arms_through_the_driver_and_resumes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--identify DIR` serves each planned arm with reach-sim on a pty and identifies it
    with tools/identify.py through the driver (here one draw, its wrist B only, quarter-length
    segments): the fit in DIR predicts B's validation motions better than the nominal twin,
    a second run skips the fitted arm, and `--twin-from DIR` runs `lambda` on the fit."""
    from reach_sim_bridge.model.params import load_arm_params

    fits = tmp_path / "fits"
    quick = "--max-current 600 --watchdog 1.0 --joints B --scale 0.25 --iterations 4"
    argv = {"draws": 1, "seed": SEED, "identify": fits}
    assert robustness(**argv, identify_args=quick) == 0
    fitted = load_arm_params(fits / "draws-0.json")
    assert fitted != ArmParams()
    assert (fits / "draws-0.log.npz").exists()
    hidden = json.loads((fits / "draws-0.hidden.json").read_text())
    assert hidden["_envelope"]["index"] == 0
    (run,) = json.loads((fits / "identify-summary.json").read_text())
    assert run["arm"] == "draws-0" and run["returncode"] == 0 and run["wall_s"] > 10
    (row,) = identify_rows(plan(SEED, False, 1).arms, fits, {})
    b = row["joints"]["B"]
    assert b["validate_rms_mrad_fitted"] < b["validate_rms_mrad_nominal"]
    assert 0.5 < b["armature_ratio"] < 2.0  # the nominal twin is off by the arm's own spread
    assert "| draws-0 |" in capsys.readouterr().out
    assert robustness(**argv, identify_args=quick) == 0
    assert "(1 already fitted there, skipped)" in " ".join(capsys.readouterr().err.split())
    run = {"draws": 1, "seed": SEED, "controller": ["lambda"], "twin": True, "quiet": True}
    assert robustness(**run, twin_from=fits, seconds=1.0, out=tmp_path) == 0
    assert json.loads((tmp_path / "lambda.json").read_text())["settings"]["twin_from"] == "fits"


def test_an_identification_campaign_runs_no_controller(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = {"draws": 1, "identify": tmp_path, "controller": ["lambda"]}
    assert robustness(**argv) == 2
    assert "--twin-from DIR" in capsys.readouterr().err


def test_an_arm_the_simulator_refuses_is_reported_not_raised() -> None:
    """One bad arm file must not stop a campaign of hundreds: the job comes back failed,
    with reach-sim's own error in its tail."""
    from policy.campaigns.identify import SIM_FAILED, IdentifyJob, run_identify_job

    result = run_identify_job(IdentifyJob("bad", '{"armature": [0.1]}', (0.002, 0.02)))
    assert not result.ok and result.returncode == SIM_FAILED
    assert result.fitted_json is None
    assert "armature" in " ".join(result.tail)


def test_the_target_is_counted_per_parameter_and_names_what_is_confidently_wrong() -> None:
    """Issue 46's target over a campaign's fits: each parameter reported within 10 % of the
    arm's, or unidentifiable with its known combination within 10 %; a value or a combination
    claimed and off by more is confidently wrong, and named."""
    hidden = ArmParams(frictionloss=(2.0, 0.7, 0.7, 0.075), torque_scale=(0.5, 1, 1, 1))
    fitted = dict(hidden.to_json_dict(), torque_scale=[1.0] * 4)
    fitted["frictionloss"] = [4.0, 0.84, 0.7, 0.075]  # E: 2 / 0.5; D 20 % high, as a value
    fitted["_fit"] = {
        "torque_scales": {x: {"status": "anchor", "twin_value": 1.0} for x in "DCB"},
        "unidentifiable": {
            "torque_scale[E]": {"twin_value": 1.0, "reason": "nothing weighs it"},
            "frictionloss[E]": {
                "twin_value": 4.0,
                "reason": "over the scale",
                "known": {"name": "frictionloss[E]/torque_scale[E]", "value": 4.1, "sigma": 0.01},
            },
        },
        "controller_gap": [
            {"controller": "pid", "fitted": {"energy_error_max": 0.07}, "nominal": {}}
        ],
    }
    fitted["_fit"]["torque_scales"]["E"] = {"status": "unidentifiable", "twin_value": 1.0}
    table = verdict_table([fit_row("arm-1", hidden.to_json_dict(), fitted)])
    lines = {line.split(" | ")[0]: line.split(" | ")[1:] for line in table.splitlines()}
    # columns: value, combination, no value, wrong value, wrong combination
    assert lines["| frictionloss"] == ["2", "1", "0", "1", "0 |"]
    assert lines["| torque_scale"] == ["3", "0", "1", "0", "0 |"]
    assert "- arm-1 D: frictionloss[D] 0.84, true 0.7 (+20.0 %)" in table
    assert "PID energy within 5 % of the arm's on 0 of 1 fitted twins (worst 7.0 %)" in table
