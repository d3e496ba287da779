"""What a run recording shows: its entities, timelines and default views, and an arm drawn from
the MJCF's geoms where the simulator has them. Behaviour read back from the file, not pixels."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import mujoco
import numpy as np
import pyarrow as pa
from rerun.chunk import RrdReader

from reach_driver.arm_geometry import GEOMS
from reach_driver.kinematics import link_poses
from reach_driver.recording import (
    DIAGNOSTIC_VIEWS,
    LINK_VIEWS,
    TIMELINE_STEP,
    TIMELINE_TIME,
    RunRecorder,
    StepSample,
)
from reach_driver.rrd_summary import read_blueprint, read_recording
from reach_sim_bridge.model import geometry
from reach_sim_bridge.model.arm import MODEL_PATH, Alpha5Arm

ROOT = Path(__file__).resolve().parents[1]
DT = 0.05


def _write(path: Path, n: int = 40) -> None:
    target = np.array([2.0, 1.6, 1.0, 0.9])
    with RunRecorder(path, metadata={"controller": "synthetic"}) as rec:
        rec.log_event("start")
        for k in range(n):
            q = np.array([1.0, 1.0, 1.5, 0.5]) + (target - [1.0, 1.0, 1.5, 0.5]) * k / n
            rec.log_step(
                StepSample(k * DT, k, q, np.zeros(4), target, np.full(4, 100.0), np.full(4, 90.0))
            )
            rec.log_link(k * DT, k, good=10 * k, bad=k // 10, state_age_s=0.004, latency_s=0.0015)
        rec.log_summary({"reached": True})


def _chunks(path: Path) -> list:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RrdReader(path).stream().to_chunks()


# -- the geometry ----------------------------------------------------------------------------


def test_arm_geometry_is_the_mjcfs() -> None:
    """reach_driver/arm_geometry.py is what tools/gen_arm_geometry.py makes of alpha5.xml
    (reach_sim_bridge.model.geometry)."""
    fresh = geometry.extract(MODEL_PATH)
    assert len(fresh) == len(GEOMS)
    for g, f in zip(GEOMS, fresh, strict=True):
        assert (g.name, g.link, g.shape) == (f["name"], f["link"], f["shape"])
        np.testing.assert_allclose(g.center, f["center"], atol=1e-6)
        np.testing.assert_allclose(g.quat_xyzw, f["quat_xyzw"], atol=1e-6)
        np.testing.assert_allclose(g.size, f["size"], atol=1e-6)
    assert geometry.render(fresh) == (ROOT / "reach_driver/arm_geometry.py").read_text()


def test_geoms_posed_by_the_driver_sit_where_mujoco_puts_them() -> None:
    """The driver's kinematics carry each link's geoms to the simulator's world poses."""
    arm = Alpha5Arm()
    m, d = arm.model, arm.data
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = rng.uniform([0.2, 0.2, 0.2, 0.0], [6.0, 3.3, 3.3, 6.2])
        d.qpos[:4] = q
        mujoco.mj_kinematics(m, d)
        poses = dict(zip(("m2_1_1", "m2", "m2_1_3", "m1"), link_poses(q), strict=True))
        poses["m3_inline"] = (np.zeros(3), np.eye(3))
        for g in GEOMS:
            if g.shape != "cylinder":  # the jaw's boxes follow the jaw, not tracked
                continue
            pos, rot = poses[g.link]
            world = pos + rot @ np.asarray(g.center)
            np.testing.assert_allclose(world, d.geom_xpos[m.geom(g.name).id], atol=2e-5)
            x, y, z, w = g.quat_xyzw
            local = np.zeros(9)
            mujoco.mju_quat2Mat(local, np.array([w, x, y, z]))
            axis = rot @ local.reshape(3, 3)[:, 2]  # the cylinder's axis
            expected = d.geom_xmat[m.geom(g.name).id].reshape(3, 3)[:, 2]
            assert abs(abs(float(axis @ expected)) - 1.0) < 1e-6


def test_the_bravo7_drawing_is_the_mjcfs_and_poses_where_mujoco_does() -> None:
    """reach_driver/bravo7_drawing.py is what tools/gen_arm_geometry.py makes of bravo7.xml;
    posed by the driver at any angles, each link's geoms and the tool centre point sit where
    MuJoCo puts them (to the 1e-6 the file is written to)."""
    from protocol.models import BRAVO7
    from reach_driver.drawing import drawing_for
    from reach_sim_bridge.model.bravo7 import Bravo7Arm

    chain, geoms, tcp = geometry.extract_bravo7()
    text = (ROOT / "reach_driver/bravo7_drawing.py").read_text()
    assert geometry.render_bravo7(chain, geoms, tcp) == text
    drawing = drawing_for(BRAVO7)
    assert drawing.links == ("link1", "link2", "link3", "link4", "link5", "link6")
    arm = Bravo7Arm()
    m, d = arm.model, arm.data
    rng = np.random.default_rng(7)
    for _ in range(5):
        q = rng.uniform(0.1, 3.1, 6)
        d.qpos[:] = 0.0
        d.qpos[:6], d.qpos[6] = q, 0.005  # the jaws at their default 5 mm
        mujoco.mj_kinematics(m, d)
        poses = dict(zip(drawing.links, drawing.link_poses(q), strict=True))
        poses[drawing.base_link] = (np.zeros(3), np.eye(3))
        drawn = 0
        for g in drawing.geoms:
            pos, rot = poses[g.link]
            world = pos + rot @ np.asarray(g.center)
            # the jaws' unnamed fingers are named by body and geom id (geometry.extract_bravo7)
            gid = int(g.name.rsplit("_", 1)[1]) if g.name.startswith("jaw_") else m.geom(g.name).id
            np.testing.assert_allclose(world, d.geom_xpos[gid], atol=1e-5)
            drawn += 1
        assert drawn == m.ngeom  # every geom of the arm is drawn
        pos, rot = poses["link6"]
        np.testing.assert_allclose(
            pos + rot @ drawing.tcp, d.site_xpos[m.site("tcp").id], atol=1e-5
        )


# -- the run recording ----------------------------------------------------------------------


def test_run_recording_entities_and_timelines(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    _write(path)
    chunks = _chunks(path)
    entities = {str(c.entity_path) for c in chunks}
    links = ["m2_1_1", "m2_1_1/m2", "m2_1_1/m2/m2_1_3", "m2_1_1/m2/m2_1_3/m1"]
    expected = {
        *(f"/joints/{j}/{kind}" for j in "EDCB" for kind in ("position", "current")),
        "/errors",
        "/velocities",
        "/link/frames",
        "/link/state_age",
        "/link/latency",
        "/arm",
        *(f"/arm/{p}" for p in links),
        *(f"/target/{p}" for p in links),
        "/events",
        "/run/metadata",
        "/run/summary",
        "/run/target",
    }
    assert expected <= entities, expected - entities
    assert "/link" not in entities  # counts and ages are no longer one plot

    # Timelines: arm time is a duration (seconds in the viewer), the step a sequence.
    temporal = [c for c in chunks if not c.is_static and str(c.entity_path) == "/link/frames"]
    schema = temporal[0].to_record_batch().schema
    assert schema.field(TIMELINE_TIME).type == pa.duration("ns")
    assert schema.field(TIMELINE_STEP).type == pa.int64()

    # The link's series: counts, then ms each on its own entity.
    def values(entity: str) -> np.ndarray:
        rows = [
            row
            for c in chunks
            if not c.is_static and str(c.entity_path) == entity
            for row in c.to_record_batch().column("Scalars:scalars").to_pylist()
        ]
        return np.array(rows, dtype=float)

    frames = values("/link/frames")
    assert frames.shape == (40, 2) and frames[-1].tolist() == [390.0, 3.0]
    np.testing.assert_allclose(values("/link/state_age"), 4.0)
    np.testing.assert_allclose(values("/link/latency"), 1.5)

    # The arm is the MJCF's cylinders; the ghost is translucent, the arm opaque.
    def static_colors(entity: str) -> list[int]:
        for c in chunks:
            batch = c.to_record_batch()
            if c.is_static and str(c.entity_path) == entity:
                if "Cylinders3D:colors" in batch.schema.names:
                    return [int(v) for v in batch.column("Cylinders3D:colors").to_pylist()[0]]
        raise AssertionError(f"no cylinders at {entity}")

    arm_alpha = static_colors("/arm/m2_1_1/m2")[0] & 0xFF
    ghost_alpha = static_colors("/target/m2_1_1/m2")[0] & 0xFF
    assert arm_alpha == 255 and 0 < ghost_alpha < 128
    assert len(static_colors("/arm")) == 1  # the base

    # The reader still reads it (the layout it depends on is unchanged).
    run = read_recording(path)
    assert len(run.step) == 40 and run.summary == {"reached": True}


def test_run_recording_blueprint(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    _write(path, 5)
    bp = read_blueprint(path)
    assert bp.timeline == TIMELINE_TIME  # opens on arm time, in seconds
    by_origin = {v.origin: v for v in bp.views}
    assert by_origin["/"].kind == "3D"
    for entity, title in (*LINK_VIEWS, *DIAGNOSTIC_VIEWS):  # one view, one scale, each
        assert (
            by_origin[f"/{entity}"].name == title and by_origin[f"/{entity}"].kind == "TimeSeries"
        )
    for j in "EDCB":
        assert "(rad)" in by_origin[f"/joints/{j}/position"].name
        assert "(mA)" in by_origin[f"/joints/{j}/current"].name
    assert "(N m)" in by_origin["/torques"].name
    assert "(rad/s)" in by_origin["/velocities"].name
    assert "(ms)" in by_origin["/link/state_age"].name
    series = [v for v in bp.views if v.kind == "TimeSeries"]
    # joints; errors, torques, velocities; the link; the Monitor readings and the flags
    assert len(series) == 4 * 2 + 3 + len(LINK_VIEWS) + 6
    for v in series:  # a unit in every plot's title
        assert re.search(r"\((rad|rad/s|mA|N m|ms|count|V|degC|%|bar|flags)\)", v.name), v.name
    assert by_origin["/events"].kind == "TextLog"
