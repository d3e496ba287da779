"""What a viewer is told to show, read back from the blueprints recordings carry (no pixels:
no browser is opened here). The 3D eye frames every pose the arm can take, in the driver's and
the simulator's recordings; every plot spans the whole recording with its legend hidden; the
diagnostics are on the arm's time line in seconds; a live viewer's time panel follows."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import mujoco
import numpy as np
import pyarrow as pa
import pytest

from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINTS
from protocol.viewer_layout import EYE_FOV_Y_RAD, MIN_VIEW_ASPECT, ArmBody, Ball, reach
from reach_driver.arm_geometry import GEOMS, LinkGeom
from reach_driver.kinematics import TCP_OFFSET_M, link_poses
from reach_driver.recording import (
    DIAGNOSTIC_VIEWS,
    TIMELINE_TIME,
    RunRecorder,
    StepSample,
    default_blueprint,
)
from reach_driver.rrd_summary import BlueprintEye, read_blueprint, read_recording
from reach_driver.state import JointState, Reading
from reach_sim_bridge.emulator.recording import SimRecorder, _geoms
from reach_sim_bridge.emulator.server import SimConfig, SimServer
from reach_sim_bridge.model.arm import Alpha5Arm

LIMITS = [FACTORY_POSITION_LIMITS[d] for d in JOINTS]
# The jaw (A) slides; the simulator draws its fingers where they are.
JAW_RANGE = (0.0013, 0.0133)


def _poses() -> list[np.ndarray]:
    """Every corner of the joints' envelope, and a grid through it (the arm's reach is not at
    the corners only: straight up is D and C inside their ranges)."""
    corners = [np.array(c) for c in itertools.product(*LIMITS)]
    grid = [
        np.array([e, d, c, b])
        for e in np.linspace(*LIMITS[0], 5)
        for d in np.linspace(*LIMITS[1], 13)
        for c in np.linspace(*LIMITS[2], 13)
        for b in (0.0, math.pi / 2)
    ]
    return corners + grid


def _rotation(quat_xyzw: tuple[float, float, float, float]) -> np.ndarray:
    x, y, z, w = quat_xyzw
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.array([w, x, y, z]))
    return out.reshape(3, 3)


def _surface(g: LinkGeom) -> np.ndarray:
    """Points on a geom's outline (link frame): a cylinder's two rims, a box's corners."""
    rot, center = _rotation(g.quat_xyzw), np.asarray(g.center)
    if g.shape == "cylinder":
        r, length = g.size
        local = np.array(
            [
                (r * math.cos(a), r * math.sin(a), s * length / 2)
                for s in (-1, 1)
                for a in np.linspace(0, 2 * math.pi, 16, endpoint=False)
            ]
        )
    else:
        local = _signs() * np.asarray(g.size)
    return center + local @ rot.T


def _signs() -> np.ndarray:
    """The eight corners of a unit box, (8, 3)."""
    return np.array(list(itertools.product((-1, 1), repeat=3)), dtype=float)


def _driver_points(q: np.ndarray) -> np.ndarray:
    """Every drawn point of the driver's arm at angles `q` (world, m)."""
    poses = dict(zip(("m2_1_1", "m2", "m2_1_3", "m1"), link_poses(q), strict=True))
    poses["m3_inline"] = (np.zeros(3), np.eye(3))
    out = [poses[g.link][0] + _surface(g) @ poses[g.link][1].T for g in GEOMS]
    pos, rot = poses["m1"]
    out.append((pos + rot @ np.array([0.0, 0.0, TCP_OFFSET_M]))[None])
    return np.vstack(out)


def _sim_points(arm: Alpha5Arm, q: np.ndarray, jaw: float) -> np.ndarray:
    """Every drawn point of the simulator's arm (its MuJoCo geoms) at `q` and the jaw's `jaw`."""
    m, d = arm.model, arm.data
    d.qpos[:4] = q
    d.qpos[4] = jaw
    mujoco.mj_kinematics(m, d)
    drawn = _geoms(m)  # the geoms the simulator's recording draws
    out = []
    for g in [*drawn.cylinders, *drawn.boxes]:
        rot, center, size = d.geom_xmat[g].reshape(3, 3), d.geom_xpos[g], m.geom_size[g]
        if g in drawn.cylinders:
            local = np.array(
                [
                    (size[0] * math.cos(a), size[0] * math.sin(a), s * size[1])
                    for s in (-1, 1)
                    for a in np.linspace(0, 2 * math.pi, 16, endpoint=False)
                ]
            )
        else:
            local = _signs() * size
        out.append(center + local @ rot.T)
    return np.vstack(out)


def _in_view(eye: BlueprintEye, points: np.ndarray, aspect: float) -> np.ndarray:
    """Each point's (horizontal, vertical) place in a view of rerun's field of view and
    `aspect` (width / height) from `eye`: within [-1, 1] both is on screen."""
    pos, target, up = (np.asarray(v) for v in (eye.position, eye.look_target, eye.eye_up))
    fwd = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    rel = points - pos
    depth = rel @ fwd
    assert np.all(depth > 0.01), "behind the eye or inside its near plane"
    tan_y = math.tan(EYE_FOV_Y_RAD / 2)
    return np.stack([(rel @ right) / depth / (tan_y * aspect), (rel @ true_up) / depth / tan_y], 1)


def _assert_frames(eye: BlueprintEye | None, clouds: list[np.ndarray]) -> None:
    assert eye is not None, "the 3D view's eye is left to the viewer"
    every = np.vstack(clouds)
    for aspect in (MIN_VIEW_ASPECT, 1.0, 16 / 9):
        place = np.abs(_in_view(eye, every, aspect))
        assert place.max() <= 1.0, f"a point off screen in a {aspect:.2f} view: {place.max():.3f}"
    # ...and not from so far that the arm is a speck: its reach fills most of a narrow view.
    assert np.abs(_in_view(eye, every, MIN_VIEW_ASPECT)).max() >= 0.7


def _write_run(path: Path, steps: int = 20, diagnostics_at: float | None = 0.0) -> None:
    target = np.array([2.0, 1.6, 1.0, 0.9])
    with RunRecorder(path, metadata={"controller": "synthetic"}) as rec:
        for k in range(steps):
            t = 0.1 * k
            rec.log_step(StepSample(t, k, target - 0.1, np.zeros(4), target, np.zeros(4)))
            if diagnostics_at is not None and math.isclose(t, diagnostics_at):
                joint = JointState(int(JOINTS[1]), voltage=Reading(24.0, t))
                assert rec.log_diagnostics(t, k, {int(JOINTS[1]): joint})


# -- the 3D eye ------------------------------------------------------------------------------


def test_the_reach_bound_holds_every_pose_and_is_tight() -> None:
    """`reach` (the chain-of-pivots bound) holds every drawn point of every pose, and is
    within 1 cm of the farthest one found: the eye is placed from it."""
    from reach_driver.recording import arm_bodies

    ball = reach(arm_bodies())
    far = max(
        float(np.max(np.linalg.norm(_driver_points(q) - ball.center, axis=1))) for q in _poses()
    )
    assert far <= ball.radius <= far + 0.01


def test_reach_needs_a_jointed_body() -> None:
    with pytest.raises(ValueError, match="jointed"):
        reach([ArmBody(None, None, None, (Ball((0.0, 0.0, 0.0), 0.1),))])


def test_a_run_recordings_eye_frames_every_pose_of_the_arm_and_its_ghost(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    _write_run(path, steps=3)
    (view,) = [v for v in read_blueprint(path).views if v.kind == "3D"]
    # The ghost is the same links at the target: the same envelope.
    _assert_frames(view.eye, [_driver_points(q) for q in _poses()])


def test_a_simulator_recordings_eye_frames_every_pose(tmp_path: Path) -> None:
    path = tmp_path / "sim.rrd"
    with SimServer(SimConfig(pty=False, udp=("127.0.0.1", 0))) as srv:
        SimRecorder(srv, path).stop()
    (view,) = [v for v in read_blueprint(path).views if v.kind == "3D"]
    arm = Alpha5Arm()
    clouds = [_sim_points(arm, q, jaw) for q in _poses()[::3] for jaw in JAW_RANGE]
    _assert_frames(view.eye, clouds)


# -- the plots -------------------------------------------------------------------------------


def test_every_plot_spans_the_whole_recording_with_its_legend_hidden(tmp_path: Path) -> None:
    run, sim = tmp_path / "run.rrd", tmp_path / "sim.rrd"
    _write_run(run, steps=3)
    with SimServer(SimConfig(pty=False, udp=("127.0.0.1", 0))) as srv:
        SimRecorder(srv, sim).stop()
    for path in (run, sim):
        plots = [v for v in read_blueprint(path).views if v.kind == "TimeSeries"]
        assert plots
        for v in plots:
            assert v.legend_visible is False, (path.name, v.origin)
            # Infinite ends: the recording's whole time line, not the plot's own data span
            assert v.time_range == ("Infinite", "Infinite"), (path.name, v.origin)


def test_diagnostics_logged_once_are_in_seconds_on_a_plot_over_the_run(tmp_path: Path) -> None:
    """Monitor readings read once, at the start (as `run` does), are one point at t = 0 s on
    the arm's time line, a duration; their plot spans the run, not that one instant (which the
    viewer drew as +-1 ns, labelled '-0.000001 ms')."""
    from rerun.chunk import RrdReader

    path = tmp_path / "run.rrd"
    _write_run(path, steps=20, diagnostics_at=0.0)
    volts = read_recording(path).diagnostics["voltage_v"]
    assert volts.t.tolist() == [0.0]
    chunks = RrdReader(path).stream().to_chunks()
    (column,) = [
        c.to_record_batch().schema.field(TIMELINE_TIME).type
        for c in chunks
        if str(c.entity_path) == "/diagnostics/voltage_v" and not c.is_static
    ]
    assert column == pa.duration("ns")  # a duration: the viewer shows seconds
    by_origin = {v.origin: v for v in read_blueprint(path).views}
    for entity, _ in DIAGNOSTIC_VIEWS:
        assert by_origin[f"/{entity}"].time_range == ("Infinite", "Infinite")


# -- the time panel --------------------------------------------------------------------------


def test_a_live_viewer_follows_and_a_file_plays_from_its_start(tmp_path: Path) -> None:
    import rerun as rr

    path = tmp_path / "run.rrd"
    _write_run(path, steps=3)
    assert read_blueprint(path).play_state is None  # a file: the viewer plays it from 0
    live = tmp_path / "live.rrd"
    rec = rr.RecordingStream("reach-stack", recording_id="live-blueprint")
    rec.save(str(live), default_blueprint=default_blueprint(live=True))
    rec.flush(timeout_sec=5.0)
    rec.disconnect()
    bp = read_blueprint(live)
    assert bp.play_state == "Following" and bp.timeline == TIMELINE_TIME
