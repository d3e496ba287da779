"""A recorded run (.rrd) for other tools (`reach-driver export`): ROS 2 messages in MCAP for
`ros2 bag` and Foxglove, or one row per control step in CSV or Parquet for pandas.

The run is read by `rrd_summary.read_recording`, the reader `inspect` uses, so an export holds
what `inspect` sees: a crashed run's recording up to its last complete message included.
Stamps are the recording's `arm_time` (seconds on the arm's clock), not wall time: a
recording holds no wall time.

MCAP (the `ros2` profile): each message CDR-encoded (little-endian, XCDR1, as rmw writes them)
under its `ros2msg` schema with the definitions it depends on, as rosbag2 stores them:

    /joint_states    sensor_msgs/msg/JointState   measured: position (rad), velocity (rad/s,
                                                  empty if not recorded), effort = the
                                                  measured current (mA, the arm's unit)
    /joint_commands  sensor_msgs/msg/JointState   effort = the commanded current (mA)
    /joint_targets   sensor_msgs/msg/JointState   position = the target (rad)
    /events          rcl_interfaces/msg/Log       the recording's events (mode changes, faults,
                                                  start and stop) with their levels

One message per control step on each JointState topic, named E D C B; NaN where the recording
has no value (a `monitor` recording has no commands).

The output is written to a temporary file beside it and renamed into place when complete: an
export that fails leaves no partial file and an existing file as it was.
"""

from __future__ import annotations

import csv
import json
import math
import os
import secrets
import struct
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import IO

import numpy as np

from protocol.alpha5 import JOINT_LETTERS
from protocol.extras import MissingExtra, needs_extra
from reach_driver.errors import ExtraNotInstalledError
from reach_driver.rrd_summary import (
    SIM_SOURCE,
    RecordedRun,
    malformed_is_read_error,
    read_recording,
)


class ExportError(ValueError):
    """The export cannot be made as asked (a --to suffix not known, the recording itself as
    the output, an output that is not a file); nothing was written."""


class Format(Enum):
    """What `--to` writes, by its suffix."""

    MCAP = ".mcap"
    CSV = ".csv"
    PARQUET = ".parquet"

    @classmethod
    def of(cls, path: str | Path) -> Format:
        suffix = Path(path).suffix.lower()
        for fmt in cls:
            if fmt.value == suffix:
                return fmt
        known = ", ".join(f.value for f in cls)
        raise ExportError(f"{path}: unknown suffix {suffix or '(none)'!r}; give one of {known}")


# -- the table (CSV, Parquet) ----------------------------------------------------------------

#: The per-joint quantities of a row, in column order: (name, unit, RecordedRun attribute).
QUANTITIES: tuple[tuple[str, str, str], ...] = (
    ("q", "rad", "q"),
    ("target", "rad", "target"),
    ("qdot", "rad_s", "qdot"),
    ("current_cmd", "mA", "current_cmd"),
    ("current_meas", "mA", "current_meas"),
    ("torque", "Nm", "torque"),
)


def table_columns() -> list[str]:
    """The columns of the CSV and Parquet exports: `step`, `t_s`, then each quantity per joint
    (`q_E_rad`, `q_D_rad`, ..., `torque_B_Nm`)."""
    return ["step", "t_s"] + [f"{n}_{j}_{u}" for n, u, _ in QUANTITIES for j in JOINT_LETTERS]


def step_table(run: RecordedRun) -> dict[str, np.ndarray]:
    """One row per control step, by `table_columns()`; NaN where the recording has no value."""
    steps = len(run.step)
    out: dict[str, np.ndarray] = {
        "step": np.asarray(run.step, dtype=np.int64),
        "t_s": np.asarray(run.t, dtype=float),
    }
    for name, unit, attr in QUANTITIES:
        values = getattr(run, attr)
        block = (
            np.full((steps, len(JOINT_LETTERS)), np.nan)
            if values is None
            else np.asarray(values, dtype=float)
        )
        for i, j in enumerate(JOINT_LETTERS):
            out[f"{name}_{j}_{unit}"] = block[:, i]
    return out


def _write_csv(run: RecordedRun, f: IO[bytes]) -> None:
    """Floats as Python writes them (they read back exactly), an empty field for NaN."""
    table = step_table(run)
    text = _TextOut(f)
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(table.keys())
    columns = list(table.values())
    for row in range(len(run.step)):
        writer.writerow(
            [int(columns[0][row])]
            + ["" if math.isnan(v := float(c[row])) else repr(v) for c in columns[1:]]
        )


class _TextOut:
    """The text side of a binary file for `csv.writer` (UTF-8)."""

    def __init__(self, f: IO[bytes]) -> None:
        self.f = f

    def write(self, text: str) -> int:
        return self.f.write(text.encode("utf-8"))


def _write_parquet(run: RecordedRun, f: IO[bytes]) -> None:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as exc:  # pyarrow comes with rerun-sdk; a build without Parquet
        raise ExportError(
            f"writing .parquet needs pyarrow with Parquet support ({exc}): pip install pyarrow"
        ) from None
    table = pa.table(step_table(run))
    meta = {
        b"reach_stack.metadata": json.dumps(run.metadata, default=str).encode(),
        b"reach_stack.summary": json.dumps(run.summary, default=str).encode(),
    }
    pq.write_table(table.replace_schema_metadata(meta), f)


# -- ROS 2 messages ----------------------------------------------------------------------------

#: Dependent definitions follow the top one, each after a line of 80 '=' and `MSG: <type>`,
#: the field type as the .msg names it (rosbag2's message definition cache writes the same).
_DELIMITER = "=" * 80 + "\nMSG: "
_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"

JOINT_STATE = "sensor_msgs/msg/JointState"
LOG = "rcl_interfaces/msg/Log"

#: The `ros2msg` schema of each message type the export writes.
SCHEMAS: dict[str, str] = {
    JOINT_STATE: (
        "std_msgs/Header header\n"
        "string[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n"
        f"{_DELIMITER}std_msgs/Header\n{_HEADER}"
        f"{_DELIMITER}builtin_interfaces/Time\n{_TIME}"
    ),
    LOG: (
        "byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\nbyte FATAL=50\n"
        "builtin_interfaces/Time stamp\nuint8 level\nstring name\nstring msg\n"
        "string file\nstring function\nuint32 line\n"
        f"{_DELIMITER}builtin_interfaces/Time\n{_TIME}"
    ),
}


class Topic(Enum):
    """The MCAP export's topics: (name, message type)."""

    STATES = ("/joint_states", JOINT_STATE)
    COMMANDS = ("/joint_commands", JOINT_STATE)
    TARGETS = ("/joint_targets", JOINT_STATE)
    EVENTS = ("/events", LOG)

    @property
    def topic(self) -> str:
        return self.value[0]

    @property
    def type(self) -> str:
        return self.value[1]


#: rcl_interfaces/msg/Log's levels by the recording's (rerun TextLog) level names.
LOG_LEVELS: dict[str, int] = {
    "TRACE": 10,
    "DEBUG": 10,
    "INFO": 20,
    "WARN": 30,
    "WARNING": 30,
    "ERROR": 40,
    "CRITICAL": 50,
    "FATAL": 50,
}


class Cdr:
    """Plain little-endian CDR as rmw serialises a ROS 2 message: the encapsulation header
    (CDR_LE: 00 01 00 00), then each primitive aligned to its own size counted from the end of
    that header; a string is a u32 length (with its NUL) and the bytes and NUL, a sequence a
    u32 count and its elements (aligned only when there is one)."""

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")

    def _align(self, size: int) -> None:
        self.buf += b"\x00" * (-(len(self.buf) - 4) % size)

    def u8(self, value: int) -> None:
        self.buf += struct.pack("<B", value)

    def i32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", value)

    def u32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", value)

    def string(self, value: str) -> None:
        data = value.encode("utf-8") + b"\x00"
        self.u32(len(data))
        self.buf += data

    def strings(self, values: Sequence[str]) -> None:
        self.u32(len(values))
        for value in values:
            self.string(value)

    def float64s(self, values: Sequence[float]) -> None:
        self.u32(len(values))
        if len(values):
            self._align(8)
            self.buf += struct.pack(f"<{len(values)}d", *values)

    def time(self, ns: int) -> None:
        """builtin_interfaces/Time."""
        self.i32(ns // 1_000_000_000)
        self.u32(ns % 1_000_000_000)


def joint_state(
    ns: int,
    names: Sequence[str],
    position: Sequence[float] = (),
    velocity: Sequence[float] = (),
    effort: Sequence[float] = (),
) -> bytes:
    """A sensor_msgs/msg/JointState, CDR-encoded (frame_id empty)."""
    cdr = Cdr()
    cdr.time(ns)
    cdr.string("")
    cdr.strings(names)
    cdr.float64s(position)
    cdr.float64s(velocity)
    cdr.float64s(effort)
    return bytes(cdr.buf)


def log_message(ns: int, level: int, name: str, msg: str) -> bytes:
    """An rcl_interfaces/msg/Log, CDR-encoded (no file, function or line)."""
    cdr = Cdr()
    cdr.time(ns)
    cdr.u8(level)
    cdr.string(name)
    cdr.string(msg)
    cdr.string("")
    cdr.string("")
    cdr.u32(0)
    return bytes(cdr.buf)


def stamp_ns(t: float, what: str) -> int:
    """Arm time (s) as the non-negative nanoseconds MCAP and builtin_interfaces/Time take."""
    if not math.isfinite(t) or t < 0 or t >= 2**31:
        raise ExportError(f"{what} is at arm time {t!r} s, which no ROS 2 stamp can hold")
    return round(t * 1e9)


def ros_messages(run: RecordedRun) -> list[tuple[int, Topic, bytes]]:
    """(log time ns, topic, CDR message) of the run, in time order (at one time: the step's
    state, command and target, then events)."""
    names = list(JOINT_LETTERS)
    out: list[tuple[int, Topic, bytes]] = []
    for row in range(len(run.step)):
        ns = stamp_ns(float(run.t[row]), f"step {int(run.step[row])}")
        velocity = [] if run.qdot is None else run.qdot[row].tolist()
        out.append(
            (
                ns,
                Topic.STATES,
                joint_state(
                    ns, names, run.q[row].tolist(), velocity, run.current_meas[row].tolist()
                ),
            )
        )
        out.append(
            (ns, Topic.COMMANDS, joint_state(ns, names, effort=run.current_cmd[row].tolist()))
        )
        out.append((ns, Topic.TARGETS, joint_state(ns, names, position=run.target[row].tolist())))
    source = "reach-sim" if run.metadata.get("source") == SIM_SOURCE else "reach-driver"
    for t, level, text in run.events:
        ns = stamp_ns(t, f"event {text!r}")
        level_id = LOG_LEVELS.get(level.upper(), LOG_LEVELS["INFO"])
        out.append((ns, Topic.EVENTS, log_message(ns, level_id, source, text)))
    out.sort(key=lambda m: m[0])  # stable: a time's messages keep the order above
    return out


def _need_mcap() -> None:
    """The `mcap` library, or an ExtraNotInstalledError naming the extra that brings it."""
    try:
        with needs_extra("reach-driver export to .mcap", "export"):
            import mcap.writer  # noqa: F401
    except MissingExtra as exc:
        raise ExtraNotInstalledError(str(exc), exc.extra) from None


def _write_mcap(run: RecordedRun, f: IO[bytes], recording_name: str) -> None:
    from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
    from mcap.writer import CompressionType, Writer

    messages = ros_messages(run)
    writer = Writer(f, compression=CompressionType.ZSTD)
    writer.start(profile=Profile.ROS2, library="reach-stack")
    schema_ids = {
        name: writer.register_schema(name, SchemaEncoding.ROS2, text.encode("utf-8"))
        for name, text in SCHEMAS.items()
    }
    # rosbag2 reads the QoS it replays with from here; empty: the default (reliable, volatile).
    channels = {
        topic: writer.register_channel(
            topic.topic, MessageEncoding.CDR, schema_ids[topic.type], {"offered_qos_profiles": ""}
        )
        for topic in Topic
    }
    sequence = dict.fromkeys(Topic, 0)
    for ns, topic, data in messages:
        writer.add_message(channels[topic], ns, data, ns, sequence[topic])
        sequence[topic] += 1
    writer.add_metadata("reach-stack", _mcap_metadata(run, recording_name))
    writer.finish()


def _mcap_metadata(run: RecordedRun, recording_name: str) -> dict[str, str]:
    """The `reach-stack` metadata record: what the run's recording says of it, as text."""
    return {
        "recording": recording_name,
        "time": "arm_time: seconds on the arm's clock, not wall time",
        "metadata": json.dumps(run.metadata, default=str),
        "summary": json.dumps(run.summary, default=str),
        "closed_cleanly": str(run.closed_cleanly).lower(),
        "truncated_bytes": str(run.truncated_bytes),
    }


# -- the export ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExportReport:
    """What an export wrote."""

    out: Path
    format: Format
    steps: int
    events: int  # on /events (MCAP only; the tables have none)
    closed_cleanly: bool  # the recording's writer closed it
    truncated_bytes: int  # bytes of an incomplete last message the reader skipped


def _output(path: Path, recording: Path) -> Path:
    """Where the export goes: through a symbolic link to its file; refused if that is the
    recording itself or anything but a regular file (a rename would replace a device)."""
    final = Path(os.path.realpath(path))
    if final.exists():
        if not final.is_file():
            raise ExportError(f"--to {path} is not a regular file")
        if recording.exists() and os.path.samefile(final, recording):
            raise ExportError(f"--to {path} is the recording itself")
    return final


@contextmanager
def _atomic(final: Path) -> Iterator[IO[bytes]]:
    """A new file beside `final`, renamed onto it when the block ends normally and removed
    when it does not: no partial output, and a file already at `final` stays until then."""
    part = final.with_name(f".{final.name}.{secrets.token_hex(4)}.part")
    f = open(part, "xb")  # noqa: SIM115 - closed below, before the rename
    try:
        with f:
            yield f
        os.replace(part, final)
    except BaseException:
        part.unlink(missing_ok=True)
        raise


_WRITERS = {Format.CSV: _write_csv, Format.PARQUET: _write_parquet}


def export_recording(recording: str | Path, out: str | Path) -> ExportReport:
    """Write the run in `recording` to `out`, in the format its suffix names. Raises
    ExportError or RecordingReadError (bad input: nothing written), ExtraNotInstalledError
    (MCAP without the `export` extra) or OSError (writing failed: nothing left behind)."""
    recording, out = Path(recording), Path(out)
    fmt = Format.of(out)
    final = _output(out, recording)
    if fmt is Format.MCAP:
        _need_mcap()  # before the recording is read: say it at once
    with malformed_is_read_error():
        run = read_recording(recording)
    with _atomic(final) as f:
        if fmt is Format.MCAP:
            _write_mcap(run, f, recording.name)
        else:
            _WRITERS[fmt](run, f)
    return ExportReport(
        out=out,
        format=fmt,
        steps=len(run.step),
        events=len(run.events) if fmt is Format.MCAP else 0,
        closed_cleanly=run.closed_cleanly,
        truncated_bytes=run.truncated_bytes,
    )
