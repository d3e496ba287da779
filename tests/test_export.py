"""`reach-driver export`: a recorded run as ROS 2 messages in MCAP, read back by an independent
ROS 2 decoder (mcap-ros2-support, with the vendored rosidl parser for the schemas), and as CSV
and Parquet read back by pandas, each value equal to the recording's; bad input is one line,
exit 1 (an unreadable recording, as inspect) or 2 (a bad --to) and no file."""

from __future__ import annotations

import json
import math
import os
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import WATCHDOG_S

from reach_driver.cli import Exit, main
from reach_driver.export import (
    JOINT_STATE,
    LOG,
    SCHEMAS,
    Format,
    Topic,
    joint_state,
    log_message,
    table_columns,
)
from reach_driver.recording import RunRecorder, StepSample
from reach_driver.rrd_summary import RecordedRun, read_recording

mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")
mcap_ros2_dynamic = pytest.importorskip("mcap_ros2._dynamic")
pd = pytest.importorskip("pandas")

DT = 0.05
STEPS = 40
JOINTS = ["E", "D", "C", "B"]


def _record(path: Path, *, monitor_from: int = STEPS) -> None:
    """A run written by the project's recorder: `run`'s steps up to `monitor_from`, then
    `monitor`'s (measured only: no command, no torque), with events between."""
    with RunRecorder(path, metadata={"controller": "synthetic"}) as rec:
        rec.log_event("start")
        for k in range(STEPS):
            t = 0.5 + k * DT  # the arm's clock does not start at 0
            q = np.array([1.0, 1.2, 1.4, 1.6]) + 0.01 * k * np.array([1, -1, 2, -2])
            target = np.array([2.0, 1.0, 1.8, 1.2]) if k < STEPS // 2 else np.full(4, 1.5)
            if k < monitor_from:
                rec.log_step(
                    StepSample(
                        t=t,
                        step=k,
                        q=q,
                        qdot=np.array([0.1, -0.1, 0.2, -0.2]) * (k + 1),
                        target=target,
                        current_cmd_mA=np.array([100.0, -50.0, 25.5, 7.25]) + k,
                        current_meas_mA=np.array([90.0, -45.0, 20.0, 5.0]) + k / 3,
                        torque_Nm=np.full(4, 0.5),
                    )
                )
            else:
                rec.log_state(t, k, q, np.zeros(4), np.full(4, 12.0 + k), target)
            if k == STEPS // 2:
                rec.log_event("target changed: ünïcode ok", level="WARNING", t=t, step=k)
        rec.log_event("run ended", level="ERROR")
        rec.log_summary({"reached": False})


def _decoded(path: Path) -> tuple[Any, dict[str, list[tuple[int, Any]]], list[int]]:
    """(summary, topic -> [(log time, decoded message)], log times in file order), through
    mcap's reader (CRCs checked) and mcap-ros2-support's decoder."""
    with open(path, "rb") as f:
        reader = mcap_reader.make_reader(
            f, validate_crcs=True, decoder_factories=[mcap_ros2_decoder.DecoderFactory()]
        )
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        by_topic: dict[str, list[tuple[int, Any]]] = defaultdict(list)
        file_order: list[int] = []
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            assert message.publish_time == message.log_time
            by_topic[channel.topic].append((message.log_time, decoded))
            file_order.append(message.log_time)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    summary.reach_stack = metadata["reach-stack"]
    return summary, by_topic, file_order


def _ns(t: float) -> int:
    return round(t * 1e9)


def _same(a: list[float], b: np.ndarray) -> None:
    """Equal to the bit, NaN where the recording has NaN."""
    assert len(a) == len(b)
    for x, y in zip(a, b.tolist(), strict=True):
        assert (math.isnan(x) and math.isnan(y)) or x == y, (a, b)


def _assert_mcap_matches(path: Path, run: RecordedRun) -> None:
    summary, by_topic, file_order = _decoded(path)
    n = len(run.step)
    assert n > 0
    topics = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    assert {t: (s.name, s.encoding) for t, s in topics.items()} == {
        "/joint_states": ("sensor_msgs/msg/JointState", "ros2msg"),
        "/joint_commands": ("sensor_msgs/msg/JointState", "ros2msg"),
        "/joint_targets": ("sensor_msgs/msg/JointState", "ros2msg"),
        "/events": ("rcl_interfaces/msg/Log", "ros2msg"),
    }
    for channel in summary.channels.values():
        assert channel.message_encoding == "cdr"
        assert "offered_qos_profiles" in channel.metadata  # the ros2 profile requires it
    joint_state_text = topics["/joint_states"].data.decode()
    assert "\nMSG: std_msgs/Header\n" in joint_state_text
    assert "\nMSG: builtin_interfaces/Time\n" in joint_state_text
    counts = {
        summary.channels[c].topic: k for c, k in summary.statistics.channel_message_counts.items()
    }
    assert counts == {
        "/joint_states": n,
        "/joint_commands": n,
        "/joint_targets": n,
        "/events": len(run.events),
    }
    assert file_order == sorted(file_order)  # ros2 bag plays in file order
    for topic in ("/joint_states", "/joint_commands", "/joint_targets"):
        stamps = [ns for ns, _ in by_topic[topic]]
        assert stamps == [_ns(t) for t in run.t]
        assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
        for ns, msg in by_topic[topic]:
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == ns
            assert msg.header.frame_id == "" and list(msg.name) == JOINTS
    for k in range(n):
        _, state = by_topic["/joint_states"][k]
        _same(state.position, run.q[k])
        assert run.qdot is not None
        _same(state.velocity, run.qdot[k])
        _same(state.effort, run.current_meas[k])
        _, command = by_topic["/joint_commands"][k]
        assert list(command.position) == [] and list(command.velocity) == []
        _same(command.effort, run.current_cmd[k])
        _, target = by_topic["/joint_targets"][k]
        _same(target.position, run.target[k])
        assert list(target.velocity) == [] and list(target.effort) == []
    levels = {"INFO": 20, "WARNING": 30, "ERROR": 40}
    assert [(ns, m.level, m.name, m.msg) for ns, m in by_topic["/events"]] == [
        (_ns(t), levels[lv], "reach-driver", text) for t, lv, text in run.events
    ]
    assert json.loads(summary.reach_stack["metadata"]) == run.metadata
    assert json.loads(summary.reach_stack["summary"]) == run.summary


def test_mcap_export_reads_back_with_an_independent_ros2_decoder(tmp_path, capsys) -> None:
    rrd, out = tmp_path / "run.rrd", tmp_path / "run.mcap"
    _record(rrd, monitor_from=30)
    assert main(["export", str(rrd), "--to", str(out)]) == Exit.OK
    assert capsys.readouterr().out.strip() == f"wrote {out}: {STEPS} steps, 3 events"
    run = read_recording(rrd)
    assert len(run.step) == STEPS and len(run.events) == 3
    assert np.isnan(run.current_cmd[30:]).all()  # monitor's steps: no command, kept as NaN
    _assert_mcap_matches(out, run)
    # step k's positions, as the test wrote them
    _, by_topic, _ = _decoded(out)
    _, state = by_topic["/joint_states"][7]
    assert state.position == pytest.approx([1.07, 1.13, 1.54, 1.46], abs=1e-12)
    assert by_topic["/joint_states"][7][0] == 850_000_000


@pytest.mark.parametrize("names", [["E", "D", "C", "B"], ["joint_a", "b", "ccc", "dddd"]])
@pytest.mark.parametrize(
    ("position", "velocity", "effort"),
    [
        ([1.0, 2.0, 3.0, 4.0], [0.5, -0.5, 1e-300, -0.0], [float("nan"), 1.0, 2.0, 3.0]),
        ([1.0, 2.0, 3.0, 4.0], [], [5.0, 6.0, 7.0, 8.0]),  # velocity not recorded
        ([], [], [100.0, -50.0, 25.5, 7.25]),  # a command
        ([2.0, 1.0, 1.8, 1.2], [], []),  # a target
    ],
)
def test_joint_state_bytes_are_the_reference_encoders(names, position, velocity, effort) -> None:
    """Alignment and padding as mcap-ros2-support's CDR writer puts them, empty sequences and
    string lengths that leave the float64s unaligned included."""
    encode = mcap_ros2_dynamic.serialize_dynamic(JOINT_STATE, SCHEMAS[JOINT_STATE])[JOINT_STATE]
    ns = 12_345_678_901
    ours = joint_state(ns, names, position, velocity, effort)
    reference = encode(
        {
            "header": {"stamp": {"sec": 12, "nanosec": 345_678_901}, "frame_id": ""},
            "name": names,
            "position": position,
            "velocity": velocity,
            "effort": effort,
        }
    )
    assert ours == reference


@pytest.mark.parametrize("text", ["start", "ab", "ünïcode: ✓", ""])
def test_log_bytes_are_the_reference_encoders(text) -> None:
    encode = mcap_ros2_dynamic.serialize_dynamic(LOG, SCHEMAS[LOG])[LOG]
    reference = encode(
        {
            "stamp": {"sec": 3, "nanosec": 5},
            "level": 40,
            "name": "reach-driver",
            "msg": text,
            "file": "",
            "function": "",
            "line": 0,
        }
    )
    assert log_message(3_000_000_005, 40, "reach-driver", text) == reference


def test_topics_are_the_documented_ones() -> None:
    assert [(t.topic, t.type) for t in Topic] == [
        ("/joint_states", JOINT_STATE),
        ("/joint_commands", JOINT_STATE),
        ("/joint_targets", JOINT_STATE),
        ("/events", LOG),
    ]
    docs = (Path(__file__).resolve().parents[1] / "docs" / "hil.md").read_text()
    for topic in Topic:
        assert f"`{topic.topic}`" in docs and f"`{topic.type}`" in docs, topic
    assert "`step`, `t_s`" in docs


def _assert_table_matches(frame: Any, run: RecordedRun) -> None:
    assert list(frame.columns) == table_columns()
    assert frame["step"].tolist() == run.step.tolist()
    assert frame["t_s"].tolist() == run.t.tolist()
    attrs = {"q": run.q, "target": run.target, "qdot": run.qdot}
    attrs |= {"current_cmd": run.current_cmd, "current_meas": run.current_meas}
    attrs["torque"] = run.torque
    for name, values in attrs.items():
        assert values is not None
        for i, j in enumerate(JOINTS):
            (column,) = [c for c in frame.columns if c.startswith(f"{name}_{j}_")]
            _same(frame[column].tolist(), values[:, i])


def test_csv_and_parquet_hold_one_row_per_step_equal_to_the_recording(tmp_path) -> None:
    rrd = tmp_path / "run.rrd"
    _record(rrd, monitor_from=30)
    run = read_recording(rrd)
    assert main(["export", str(rrd), "--to", str(tmp_path / "run.csv")]) == Exit.OK
    frame = pd.read_csv(tmp_path / "run.csv")
    assert len(frame) == STEPS
    _assert_table_matches(frame, run)
    assert frame.loc[7, "q_C_rad"] == 1.4 + 0.01 * 7 * 2
    assert frame["current_cmd_E_mA"][30:].isna().all()  # monitor's steps: no command
    assert frame["torque_B_Nm"][30:].isna().all()
    # NaN is an empty field, as spreadsheets and pandas take a missing value
    last = (tmp_path / "run.csv").read_text().splitlines()[-1].split(",")
    assert last[table_columns().index("current_cmd_E_mA")] == ""
    assert main(["export", str(rrd), "--to", str(tmp_path / "run.parquet")]) == Exit.OK
    frame = pd.read_parquet(tmp_path / "run.parquet")
    assert len(frame) == STEPS and str(frame["step"].dtype) == "int64"
    _assert_table_matches(frame, run)


@pytest.mark.slow
def test_a_real_run_against_the_virtual_arm_exports(sim, tmp_path, capsys) -> None:
    """`run --record` on the virtual arm, then both exports: every step and event as the
    recording holds them."""
    rrd = tmp_path / "run.rrd"
    target = sim.snapshot().q + np.array([0.2, -0.1, 0.1, 0.2])
    argv = ["--port", str(sim.link), "--watchdog", str(WATCHDOG_S), "run", "--controller", "pid"]
    argv += ["--target", *map(str, target), "--seconds", "1", "--record", str(rrd), "-q"]
    assert main(argv) == Exit.OK, capsys.readouterr()
    run = read_recording(rrd)
    assert len(run.step) >= 5 and run.events
    assert main(["export", str(rrd), "--to", str(tmp_path / "run.mcap")]) == Exit.OK
    _assert_mcap_matches(tmp_path / "run.mcap", run)
    assert main(["export", str(rrd), "--to", str(tmp_path / "run.csv")]) == Exit.OK
    _assert_table_matches(pd.read_csv(tmp_path / "run.csv"), run)


def test_a_recording_cut_short_exports_what_it_holds_and_says_so(tmp_path, capsys) -> None:
    rrd = tmp_path / "run.rrd"
    _record(rrd)
    data = rrd.read_bytes()
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(data[: len(data) * 2 // 3])
    run = read_recording(cut)
    assert len(run.step) > 0 and run.truncated
    assert main(["export", str(cut), "--to", str(tmp_path / "cut.mcap")]) == Exit.OK
    captured = capsys.readouterr()
    assert captured.out.startswith(f"wrote {tmp_path / 'cut.mcap'}: {len(run.step)} steps")
    assert "was not closed by its writer" in captured.err and "bytes" in captured.err
    _assert_mcap_matches(tmp_path / "cut.mcap", run)


# -- bad input: one line, exit 1 or 2, no file -----------------------------------------------------


def _left(directory: Path) -> set[str]:
    return {p.name for p in directory.iterdir()}


@pytest.mark.parametrize(
    ("case", "said"),
    [
        ("missing", "no such recording"),
        ("junk", "not a readable .rrd recording"),
        ("not-ours", "holds no joint positions"),
        ("ragged", "rows of"),
        ("suffix", "unknown suffix '.txt'; give one of .mcap, .csv, .parquet"),
        ("no-suffix", "unknown suffix '(none)'"),
        ("itself", "is the recording itself"),
        ("a-directory", "is not a regular file"),
        ("a-device", "is a device"),
    ],
)
@pytest.mark.parametrize("suffix", [".mcap", ".csv", ".parquet"])
def test_bad_input_is_one_line_and_no_file(tmp_path, capsys, case, said, suffix) -> None:
    work = tmp_path / "work"
    work.mkdir()
    rrd, out = work / "run.rrd", work / f"out{suffix}"
    if case == "missing":
        pass
    elif case == "junk":
        rrd.write_bytes(b"not a recording at all")
    elif case == "not-ours":
        import rerun as rr

        rec = rr.RecordingStream("someone-else", recording_id="other")
        rec.save(str(rrd))
        rec.log("points", rr.Points3D([[0.0, 0.0, 0.0]]))
        rec.flush()
        rec.disconnect()
    elif case == "ragged":
        import rerun as rr

        rec = rr.RecordingStream("reach-driver", recording_id="ragged")
        rec.save(str(rrd))
        for k in range(10):
            rec.set_time("arm_time", duration=0.05 * k)
            rec.set_time("step", sequence=k)
            for j in JOINTS:
                rec.log(f"joints/{j}/position", rr.Scalars([1.0, 1.5] if k < 5 else [1.0]))
        rec.flush()
        rec.disconnect()
    else:
        _record(rrd)
        if case == "suffix":
            out = work / "out.txt"
        elif case == "no-suffix":
            out = work / "out"
        elif case == "itself":
            rrd = rrd.rename(work / f"run{suffix}")
            out = rrd
        elif case == "a-directory":
            out.mkdir()
        elif case == "a-device":
            out = Path("/dev/null")
    before = _left(work)
    device = os.stat("/dev/null")
    code = main(["export", str(rrd), "--to", str(out)])
    captured = capsys.readouterr()
    # a recording that cannot be read fails as inspect's does (1); a bad --to is usage (2)
    unreadable = case in ("missing", "junk", "not-ours", "ragged")
    assert code == (Exit.FAILED if unreadable else Exit.USAGE), captured
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    assert lines[0].startswith("error: ") and said in lines[0], lines[0]
    assert captured.out == ""
    assert _left(work) == before  # no output, no leftover part file
    assert os.stat("/dev/null").st_rdev == device.st_rdev  # still the device


def test_a_failed_export_leaves_an_existing_file_as_it_was(tmp_path, capsys) -> None:
    (tmp_path / "junk.rrd").write_bytes(b"junk")
    out = tmp_path / "run.csv"
    out.write_text("what was there\n")
    assert main(["export", str(tmp_path / "junk.rrd"), "--to", str(out)]) == Exit.FAILED
    assert out.read_text() == "what was there\n"
    assert _left(tmp_path) == {"junk.rrd", "run.csv"}
    capsys.readouterr()


def test_a_write_that_fails_midway_leaves_no_file(tmp_path, capsys, monkeypatch) -> None:
    """A full disk in the middle of the file: exit 1, one line, nothing left behind; a
    directory that does not exist is the same kind of failure."""
    from reach_driver import export

    rrd = tmp_path / "run.rrd"
    _record(rrd)

    def half_then_full(run: RecordedRun, f: Any) -> None:
        f.write(b"step,t_s\n0,0.5\n")
        raise OSError(28, "No space left on device")

    monkeypatch.setitem(export._WRITERS, Format.CSV, half_then_full)
    out = tmp_path / "run.csv"
    assert main(["export", str(rrd), "--to", str(out)]) == Exit.FAILED
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1 and "No space left on device" in err and "nothing was written" in err
    )
    assert _left(tmp_path) == {"run.rrd"}
    missing = tmp_path / "no-such-dir" / "run.parquet"
    assert main(["export", str(rrd), "--to", str(missing)]) == Exit.FAILED
    assert "cannot write" in capsys.readouterr().err
    assert _left(tmp_path) == {"run.rrd"}


def test_suffixes_are_case_blind() -> None:
    assert Format.of("RUN.MCAP") is Format.MCAP and Format.of("x.Parquet") is Format.PARQUET
