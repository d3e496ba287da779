"""Identification that is never confidently wrong (docs/identification.md, "What the data
cannot tell apart"): a joint's torque scale is fitted as a continuous parameter where a load
weighed at a known torque anchors it, and reported unidentifiable, with the combinations the
data do fix, where nothing does. The excitation runs in-process on a virtual arm
(`excite_virtual`), a few seconds of it."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from policy.campaigns.identification.cli import main as identify_main
from policy.campaigns.identification.virtual import excite_virtual
from policy.controllers.excitation import Wave
from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.fit import arm_fit, joint_fit
from reach_sim_bridge.fit.arm_fit import fit_arm, parameter_verdicts
from reach_sim_bridge.fit.identifiability import (
    Fisher,
    ScaleStatus,
    combination_value,
    marginal_information,
)
from reach_sim_bridge.fit.joint_fit import coarse_start, default_refs, equivalent
from reach_sim_bridge.fit.replay import Replay
from reach_sim_bridge.model.params import ArmParams, save_arm_params
from reach_sim_bridge.model.twin import read_twin

E, D, C, B = (JOINT_LETTERS.index(x) for x in "EDCB")

#: The arm the fit was confidently wrong on: friction 5 to 6 times nominal on E D C, D's drive
#: at 70 % torque. The old fit put E, D and C at a quarter torque with a quarter of their
#: friction (validation R^2 >= 0.99 on every joint), and its twin was 470-770 % off a PID's
#: energy on the arm.
REPRO = replace(ArmParams(), frictionloss=(3.5, 2.8, 4.2, 0.12), torque_scale=(1, 0.7, 1, 1))
TOL = 0.10  # the issue's: a parameter within 10 %, or the combination reported instead


def _short_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    """The coarse start's grid cut to the friction's decade (the scales kept), to keep the
    test short: the full grid is what docs/identification.md measured."""
    monkeypatch.setattr(joint_fit, "COARSE_GRID", {"frictionloss": (1.0, 3.0, 10.0)})


def test_a_drive_at_70_percent_is_fitted_at_its_scale(monkeypatch: pytest.MonkeyPatch) -> None:
    """C and D both carry the wrist, each over its own torque scale: the stronger (C) is the
    anchor, D's scale is fitted continuously against the wrist's weight as C weighed it. The
    old fit chose each scale from {1, 0.25} by a tie-break (D came out at 0.25, with a
    quarter of its friction)."""
    _short_grid(monkeypatch)
    waves = [
        Wave("relay", "P1", 4.0, "fit", speed=0.35),
        Wave("relay", "P2", 4.0, "fit", speed=0.25),
    ]
    segs = excite_virtual(REPRO, [C, D], waves, max_current_mA=600)
    fit = fit_arm(Replay(window_s=1.0), segs, quanta=(0.002,), max_iter=5, fit_starts=False)
    assert fit.scales[C].status is ScaleStatus.ANCHOR
    assert fit.params.torque_scale[C] == 1.0
    assert fit.params.frictionloss[C] == pytest.approx(4.2, rel=TOL)
    d = fit.scales[D]
    if d.status is ScaleStatus.IDENTIFIED:  # measured 0.736
        assert d.value == pytest.approx(0.7, rel=TOL)
        assert fit.params.frictionloss[D] == pytest.approx(2.8, rel=TOL)
        # a value of D's the data do not give to the bar is not claimed: what is reported is
        # the value over the fitted scale, within 10 % of the arm's
        monkeypatch.setattr(arm_fit, "IDENTIFIED_SIGMA", 1e-9)
        known, unknown = parameter_verdicts(fit)
        for name in ("armature", "damping", "frictionloss"):
            assert f"{name}[D]" not in known, name
            combo = unknown[f"{name}[D]"].known
            assert combo is not None and combo.name.endswith("/torque_scale[D]"), name
            assert combo.value == pytest.approx(combination_value(REPRO, combo.name), rel=TOL)
        assert "frictionloss[C]" in known  # the anchor's values are values still
    else:
        assert d.status is ScaleStatus.UNIDENTIFIABLE
        f = fit.params.frictionloss[D] / fit.params.torque_scale[D]
        assert f == pytest.approx(2.8 / 0.7, rel=TOL)


def test_a_scale_nothing_anchors_is_reported_unidentifiable(tmp_path: Path) -> None:
    """E carries no gravity load: a drive at 60 % torque with 3.5 N m of friction moves E
    exactly as a healthy one with 5.8 N m. The fit says so: no torque scale, armature, damping
    or friction for E in `_fit.parameters`; each in `_fit.unidentifiable` with the twin's
    value (the datasheet's torque) and the combination known, within 10 % of the arm's."""
    arm = replace(REPRO, torque_scale=(0.6, 1.0, 1.0, 1.0))
    hidden = save_arm_params(arm, tmp_path / "hidden.json")
    out = tmp_path / "arm.json"
    argv = ["--virtual", str(hidden), "--joints", "E", "--scale", "0.25", "--iterations", "6"]
    # 5.8 N m over E's scale needs 290 mA to break away: past 80 % of the default 300
    argv += ["--max-current", "600", "--out", str(out), "--no-report"]
    assert identify_main(argv) == 0
    fit = read_twin(out).fit
    assert fit is not None
    assert fit.torque_scales["E"]["status"] == "unidentifiable"
    for name in ("torque_scale", "armature", "damping", "frictionloss"):
        assert f"{name}[E]" not in fit.parameters, name
        assert f"{name}[E]" in fit.unidentifiable, name
    assert fit.unidentifiable["torque_scale[E]"].twin_value == 1.0
    assert fit.unidentifiable["torque_scale[E]"].known is None
    for name in ("armature", "damping", "frictionloss"):
        known = fit.unidentifiable[f"{name}[E]"].known
        assert known is not None and known.name.endswith("/torque_scale[E]")
        assert known.value == pytest.approx(combination_value(arm, known.name), rel=TOL), name
    friction = fit.unidentifiable["frictionloss[E]"].known
    assert friction is not None and friction.value == pytest.approx(3.5 / 0.6, rel=TOL)
    # the file is the twin all the same: a healthy E with what the data fix
    data = json.loads(out.read_text())
    assert data["torque_scale"][E] == 1.0
    assert data["frictionloss"][E] == pytest.approx(3.5 / 0.6, rel=TOL)


def test_the_coarse_start_spans_weak_drives_without_choosing_one() -> None:
    """A D at 25 % torque fights its own load with a quarter of its drive; from a grid at full
    torque alone its fit once put 12.6 N m of Coulomb friction there. The grid is tried at
    several torque scales, and the point found at another is given at the start's own scale,
    as the arm it moves like (its parameters and load over the scale), beside the own
    scale's: the fit starts from both, and no scale is chosen by the grid."""
    truth = replace(ArmParams(), torque_scale=(1.0, 0.25, 1.0, 1.0))
    segs = excite_virtual(truth, [D], [Wave("relay", "P1", 3.0, "fit", speed=0.35)])
    starts = coarse_start(Replay(window_s=1.0), segs, ArmParams(), default_refs(D, False))
    assert len(starts) == 2
    assert all(s.torque_scale == (1.0, 1.0, 1.0, 1.0) for s in starts)
    assert starts[1].frictionloss[D] == pytest.approx(0.7 / 0.25, rel=0.01)  # the grid's 1 x 0.7
    replay = Replay(window_s=1.0)
    cost = [float(r @ r) for r in (replay.residuals(s, 0.0, segs) for s in starts)]
    assert cost[1] < cost[0] / 10  # the weak drive's grid point, carried over, fits best


def test_an_equivalent_arm_moves_alike() -> None:
    """`equivalent`: a drive at half torque with its parameters and load halved moves its
    joint as the healthy one does (but for the links' own inertia, which does not scale)."""
    segs = excite_virtual(REPRO, [C], [Wave("relay", "P1", 2.0, "fit", speed=0.35)])
    replay = Replay(window_s=1.0, quantum_s=0.002)
    half = equivalent(REPRO, C, 0.5, [("link_mass_kg", B)])
    assert half.torque_scale[C] == 0.5
    assert half.frictionloss[C] == pytest.approx(2.1)
    net = [p.link_mass_kg[B] - p.buoyancy_kg()[B] for p in (REPRO, half)]
    assert net[1] == pytest.approx(net[0] / 2)
    r_true, r_half = (replay.residuals(p, 0.0, segs) for p in (REPRO, half))
    rms = [math.sqrt(float(r @ r) / r.size) for r in (r_true, r_half)]
    assert rms[1] < 5e-3  # mrad-level: the links' inertia is what differs
    nominal = replay.residuals(ArmParams(), 0.0, segs)
    assert rms[1] * 20 < math.sqrt(float(nominal @ nominal) / nominal.size)


def test_fisher_directions_name_the_scale_symmetry() -> None:
    """A regressor in which two log-parameters only ever appear as their difference (a
    friction over a torque scale) has one direction the data cannot see: its sigma is
    unbounded and it names both; their ratio is known to the residuals' precision."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 1))
    jac = np.hstack([a, -a, rng.normal(size=(200, 1))])  # f and s enter as f - s
    info = marginal_information(jac, 1e-4)
    refs = (("frictionloss", 0), ("torque_scale", 0), ("damping", 0))
    fisher = Fisher(refs, (1.0, 1.0, 1.0), info)
    worst = fisher.directions()[-1]
    assert worst.sigma > 1e3 or math.isinf(worst.sigma)
    assert worst.exponents[0] == pytest.approx(1.0) and worst.exponents[1] == pytest.approx(1.0)
    assert abs(worst.exponents[2]) < 1e-6
    ratio = fisher.sigma({refs[0]: 1.0, refs[1]: -1.0})
    assert ratio < 0.01
    # a start nuisance per window takes what it can explain
    nuisance = np.ones((200, 1))
    groups = np.repeat(np.arange(4), 50)
    assert np.all(np.diag(marginal_information(jac, 1e-4, None, nuisance, groups)) <= np.diag(info))


def test_a_known_load_in_the_jaws_weighs_es_scale(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """E at 60 % torque, which nothing else weighs (above): its fitting motions run again
    holding 1 kg in the jaws, whose inertia in kg m^2 does not scale with the drive. E's scale
    is fitted, not assumed; the twin's friction is the arm's, not the arm's over its scale."""
    _short_grid(monkeypatch)
    arm = replace(REPRO, torque_scale=(0.6, 1.0, 1.0, 1.0))
    hidden = save_arm_params(arm, tmp_path / "hidden.json")
    out = tmp_path / "arm.json"
    argv = ["--virtual", str(hidden), "--joints", "E", "--scale", "0.25", "--iterations", "6"]
    argv += ["--max-current", "600", "--out", str(out), "--no-report", "--payload", "1.0"]
    assert identify_main(argv) == 0
    fit = read_twin(out).fit
    assert fit is not None
    verdict = fit.torque_scales["E"]
    assert "known 1 kg load" in verdict["reason"]
    data = json.loads(out.read_text())
    scale, sigma = data["torque_scale"][E], verdict["sigma_relative"]
    # weighed (no load: nothing, the twin at 1), and the arm's scale inside what is stated
    # (measured on this short excitation: 0.538 +- 6.9 %, unidentifiable at the 3 % bar)
    assert sigma < 0.1 and abs(math.log(scale / 0.6)) < 2.5 * sigma
    assert data["frictionloss"][E] / scale == pytest.approx(3.5 / 0.6, rel=TOL)
    assert data["payload_kg"] == 0.0  # the twin is the arm, bare
    if verdict["status"] == "identified":
        assert scale == pytest.approx(0.6, rel=TOL)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--virtual", "{hidden}", "--payload", "3"], "at most 2"),
        (["--virtual", "{hidden}", "--payload", "1", "--joints", "D"], "must include E"),
        (["--port", "/nonexistent/arm", "--payload", "1"], "--joints E"),
        (["--fit-only", "{hidden}", "--payload", "1"], "a log keeps it"),
    ],
)
def test_a_load_that_cannot_weigh_e_is_refused_before_anything_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    hidden = save_arm_params(ArmParams(), tmp_path / "hidden.json")
    argv = [a.format(hidden=hidden) for a in args] + ["--out", str(tmp_path / "arm.json")]
    assert identify_main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "arm.json").exists()
