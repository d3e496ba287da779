"""Read a run back from its .rrd recording (`reach-driver inspect`).

Uses rerun's chunk reader (`rerun.chunk.RrdReader`), which also reads a file whose writer was
killed before it could write its footer: a crashed run's recording still summarises. A file
cut inside a message (a full disk, a kill mid-write) is refused by that reader as a whole, so
it is read up to its last complete message instead (`RecordedRun.truncated`); a run killed
before its first step is still recognised by the metadata written when it opened. The arm
recorded, and so its joints, is the one the metadata names (`arm`; a recording without it is
an Alpha 5's, as every recording was before the driver drove another arm).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import struct
import tempfile
import warnings
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
from rerun.chunk import RrdReader

from protocol import HardwareStatus
from protocol.files import UserFileError, parse_json
from protocol.models import ALPHA5, MODELS, ArmModel, model_named
from reach_driver.metrics import Trace, compute_metrics, overshoot_anatomy
from reach_driver.recording import (
    STATUS_ENTITY,
    TIMELINE_STEP,
    TIMELINE_TIME,
    diagnostic_letters,
)
from reach_driver.state import MONITOR_READINGS

#: rerun's PlayState component values (rerun.blueprint.components.PlayState).
_PLAY_STATES = {1: "Paused", 2: "Playing", 3: "Following"}

#: `run/metadata`'s "source" in a simulator recording (reach_sim_bridge.emulator.recording).
SIM_SOURCE = "reach-sim"


class RecordingReadError(ValueError):
    """The file is missing, not a recording, or holds no run written by reach-stack."""


@dataclass(frozen=True)
class DiagnosticSeries:
    """One diagnostics entity read back: a row per time it was logged."""

    t: np.ndarray  # arm time of each row (s)
    values: np.ndarray  # (rows, devices): joints then jaw (E D C B A), NaN: not reported


#: `RecordedRun.diagnostics`' keys: each Monitor reading's, and this one for the status flags.
STATUS_KEY = "status"
_DIAGNOSTIC_ENTITIES = {
    **{f"/diagnostics/{m.key}": m.key for m in MONITOR_READINGS},
    f"/{STATUS_ENTITY}": STATUS_KEY,
}


@dataclass
class RecordedRun:
    """Per-step series of one recorded run, sorted by step (arrays in the joint order of the
    arm recorded, `model`: E D C B on the Alpha 5)."""

    t: np.ndarray
    step: np.ndarray
    q: np.ndarray
    target: np.ndarray
    qdot: np.ndarray | None
    torque: np.ndarray | None
    current_cmd: np.ndarray
    current_meas: np.ndarray
    events: list[tuple[float, str, str]] = field(default_factory=list)
    metadata: dict[str, object] = field(default_factory=dict)
    summary: dict[str, object] = field(default_factory=dict)
    closed_cleanly: bool = True
    truncated: bool = False  # cut inside a message: read up to the last complete one
    truncated_bytes: int = 0  # the bytes of the incomplete message that were skipped
    #: ms since the previous command, per step (NaN where not logged; None: not recorded)
    loop_period_ms: np.ndarray | None = None
    #: The devices' Monitor readings and status flags, by MONITOR_READINGS key and STATUS_KEY
    #: (only those the recording holds: none in a recording made before they were logged).
    diagnostics: dict[str, DiagnosticSeries] = field(default_factory=dict)
    model: ArmModel = ALPHA5  # the arm recorded

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0


def _seconds(column: pa.Array) -> np.ndarray:
    """A duration timeline column (ns) as float seconds."""
    values = column.cast(pa.int64()).to_numpy(zero_copy_only=False)
    return values.astype(float) * 1e-9


def _temporal_series(chunks: list, entity: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time, step, values) of a Scalars entity, concatenated over its chunks (a
    RecordingReadError if its rows differ in length: no writer of ours makes such a file)."""
    times, steps, values = [], [], []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if "Scalars:scalars" not in names or TIMELINE_STEP not in names:
            continue
        times.append(_seconds(batch.column(TIMELINE_TIME)))
        steps.append(batch.column(TIMELINE_STEP).cast(pa.int64()).to_numpy(zero_copy_only=False))
        values.extend(batch.column("Scalars:scalars").to_pylist())
    if not steps:
        return np.zeros(0), np.zeros(0, dtype=int), np.zeros((0, 0))
    t, s = np.concatenate(times), np.concatenate(steps)
    rows = [row if row is not None else [] for row in values]
    widths = sorted({len(row) for row in rows})
    if len(widths) > 1:
        raise RecordingReadError(
            f"{entity}: rows of {' and '.join(map(str, widths))} values mixed: not a series "
            "reach-stack writes"
        )
    v = np.array(rows, dtype=float)
    order = np.argsort(s, kind="stable")
    return t[order], s[order], v[order]


def _flat(values: list) -> list:
    """Rerun stores each row's component as a list (a batch); rows here hold one value."""
    return [v[0] if isinstance(v, list) and v else v for v in values]


def _static_text(chunks: list) -> str | None:
    for chunk in chunks:
        batch = chunk.to_record_batch()
        if "TextDocument:text" in batch.schema.names:
            texts = _flat(batch.column("TextDocument:text").to_pylist())
            if texts:
                return str(texts[-1])
    return None


# The .rrd framing (rerun 0.2x..0.4x): a 12-byte file header ("RRF2", version, options), then
# messages, each a u64 kind and a u64 payload length (little-endian) and the payload; kind 0
# ends the stream (the footer follows it).
_RRD_MAGIC = b"RRF2"
_RRD_HEADER = 12
_MSG_HEADER = struct.Struct("<QQ")


def complete_prefix(path: str | Path) -> tuple[int, int] | None:
    """(bytes of whole messages from the start, file size) of an .rrd file; None if the file
    does not start with the framing this module knows."""
    with open(path, "rb") as f:
        if f.read(4) != _RRD_MAGIC:
            return None
        size = f.seek(0, 2)
        good = offset = _RRD_HEADER
        while offset + _MSG_HEADER.size <= size:
            f.seek(offset)
            kind, length = _MSG_HEADER.unpack(f.read(_MSG_HEADER.size))
            end = offset + _MSG_HEADER.size + length
            if kind == 0 or end > size:  # the end of the stream, or a message cut short
                break
            good = offset = end
        return good, size


def _read_chunks(path: Path) -> tuple[list, bool]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        chunks = RrdReader(path).stream().to_chunks()
    # A writer that died before closing leaves no footer; the data before it is still good.
    return chunks, not any("no footer" in str(w.message) for w in caught)


def _read_truncated(path: Path, exc: Exception) -> tuple[list, int]:
    """The chunks of the whole messages before a cut (and how many bytes were skipped)."""
    try:
        found = complete_prefix(path)
    except OSError:
        found = None
    if found is None or found[0] <= _RRD_HEADER or found[0] >= found[1]:
        raise RecordingReadError(f"{path} is not a readable .rrd recording: {exc}") from exc
    good, size = found
    with tempfile.TemporaryDirectory(prefix="reach-inspect-") as tmp:
        copy = Path(tmp) / path.name
        with open(path, "rb") as src, open(copy, "wb") as dst:
            shutil.copyfileobj(_Limited(src, good), dst)
        try:
            chunks, _ = _read_chunks(copy)
        except Exception as again:
            raise RecordingReadError(
                f"{path} is not a readable .rrd recording: {exc} (and its first {good} bytes, "
                f"the whole messages before the cut, do not read either: {again})"
            ) from exc
    return chunks, size - good


class _Limited:
    """The first `n` bytes of a binary file, for copyfileobj."""

    def __init__(self, f: object, n: int) -> None:
        self.f, self.left = f, n

    def read(self, size: int = -1) -> bytes:
        if self.left <= 0:
            return b""
        want = self.left if size < 0 else min(size, self.left)
        data: bytes = self.f.read(want)  # type: ignore[attr-defined]
        self.left -= len(data)
        return data


def _events(by_entity: dict[str, list]) -> list[tuple[float, str, str]]:
    events: list[tuple[float, str, str]] = []
    for chunk in by_entity.get("/events", []):
        batch = chunk.to_record_batch()
        if "TextLog:text" not in batch.schema.names:
            continue
        ts = _seconds(batch.column(TIMELINE_TIME))
        texts = _flat(batch.column("TextLog:text").to_pylist())
        levels = (
            _flat(batch.column("TextLog:level").to_pylist())
            if "TextLog:level" in batch.schema.names
            else ["INFO"] * len(texts)
        )
        events.extend(
            (float(tt), str(lv), str(tx)) for tt, lv, tx in zip(ts, levels, texts, strict=True)
        )
    events.sort(key=lambda e: e[0])
    return events


def _metadata(text: str | None) -> dict[str, object]:
    if not text:
        return {}
    try:
        value = parse_json(text, "run/metadata")
    except UserFileError:
        return {}
    return value if isinstance(value, dict) else {}


def recorded_model(metadata: dict[str, object]) -> ArmModel:
    """The arm a recording's metadata names (`arm`); without it, the model whose joints it
    names (`joint_names`), else the Alpha 5. RecordingReadError for a model not known."""
    name = metadata.get("arm")
    if name is not None:
        try:
            return model_named(str(name))
        except ValueError as exc:
            raise RecordingReadError(
                f"recorded on an arm this stack does not know: {exc}"
            ) from None
    names = metadata.get("joint_names")
    for model in MODELS.values():
        if isinstance(names, list) and tuple(names) == model.joint_letters:
            return model
    return ALPHA5


def _summary(text: str | None) -> dict[str, object]:
    """The summary a run wrote at its end ({} if it did not get there)."""
    if not text:
        return {}
    try:
        value = parse_json(text, "its run/summary")
    except UserFileError as exc:
        raise RecordingReadError(str(exc)) from None
    if not isinstance(value, dict):
        raise RecordingReadError("its run/summary is not a JSON object")
    return value


Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class BlueprintEye:
    """A 3D view's pinned eye (EyeControls3D), world coordinates."""

    position: Vec3
    look_target: Vec3
    eye_up: Vec3


@dataclass(frozen=True)
class BlueprintView:
    kind: str  # rerun's view class: "TimeSeries", "3D", "TextLog", ...
    name: str
    origin: str
    legend_visible: bool | None = None  # a plot's PlotLegend: None when left to the viewer
    #: a plot's time axis range, the kind of each end ("Infinite", "Absolute",
    #: "CursorRelative"); None when left to the viewer (the span of the plot's own data)
    time_range: tuple[str, str] | None = None
    eye: BlueprintEye | None = None  # a 3D view's eye; None when left to the viewer


@dataclass(frozen=True)
class RecordingBlueprint:
    """What the viewer opens on: the default blueprint stored in the file."""

    timeline: str | None  # the time panel's timeline
    views: list[BlueprintView]
    play_state: str | None = None  # the time panel's: "Following", ...; None: the viewer's


def _boundary_kinds(column: pa.Array) -> tuple[str, str]:
    """The kinds of a TimeAxis:view_range's ends (a struct of two dense unions)."""
    ranges = column.flatten()
    kinds = []
    for end in ("start", "end"):
        union = ranges.field(end)
        names = {code: union.type.field(i).name for i, code in enumerate(union.type.type_codes)}
        kinds.append(names[union.type_codes.to_pylist()[-1]])
    return kinds[0], kinds[1]


def _vec3(column: pa.Array) -> Vec3:
    x, y, z = _flat(column.to_pylist())[-1]
    return (float(x), float(y), float(z))


def read_blueprint(path: str | Path) -> RecordingBlueprint:
    """The default blueprint a recording carries: its views (with the properties reach-stack
    sets: legends, time axes, the 3D eye), the timeline it opens on and its play state."""
    reader = RrdReader(Path(path))
    stores = reader.blueprints()
    timeline: str | None = None
    play_state: str | None = None
    views: list[BlueprintView] = []
    if not stores:
        return RecordingBlueprint(None, [])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chunks = reader.stream(store=stores[0]).to_chunks()
    props: dict[str, dict[str, object]] = defaultdict(dict)  # view entity -> property
    view_paths: list[str] = []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        names = batch.schema.names
        entity = str(chunk.entity_path)
        owner = entity.rsplit("/", 1)[0]
        if "TimePanelBlueprint:timeline" in names:
            values = _flat(batch.column("TimePanelBlueprint:timeline").to_pylist())
            timeline = str(values[-1]) if values and values[-1] is not None else timeline
        if "TimePanelBlueprint:play_state" in names:
            states = _flat(batch.column("TimePanelBlueprint:play_state").to_pylist())
            if states and states[-1] is not None:
                play_state = _PLAY_STATES.get(int(states[-1]), str(states[-1]))
        if "PlotLegend:visible" in names:
            props[owner]["legend"] = bool(_flat(batch.column("PlotLegend:visible").to_pylist())[-1])
        if "TimeAxis:view_range" in names:
            props[owner]["range"] = _boundary_kinds(batch.column("TimeAxis:view_range"))
        if "EyeControls3D:position" in names:
            props[owner]["eye"] = BlueprintEye(
                _vec3(batch.column("EyeControls3D:position")),
                _vec3(batch.column("EyeControls3D:look_target")),
                _vec3(batch.column("EyeControls3D:eye_up")),
            )
        if "ViewBlueprint:class_identifier" in names:
            kinds = _flat(batch.column("ViewBlueprint:class_identifier").to_pylist())
            view_paths.extend([entity] * len(kinds))
            titles = (
                _flat(batch.column("ViewBlueprint:display_name").to_pylist())
                if "ViewBlueprint:display_name" in names
                else [""] * len(kinds)
            )
            origins = (
                _flat(batch.column("ViewBlueprint:space_origin").to_pylist())
                if "ViewBlueprint:space_origin" in names
                else [""] * len(kinds)
            )
            views.extend(
                BlueprintView(str(k), str(n or ""), str(o or ""))
                for k, n, o in zip(kinds, titles, origins, strict=True)
            )
    views = [
        dataclasses.replace(
            view,
            legend_visible=props[where].get("legend"),  # type: ignore[arg-type]
            time_range=props[where].get("range"),  # type: ignore[arg-type]
            eye=props[where].get("eye"),  # type: ignore[arg-type]
        )
        for view, where in zip(views, view_paths, strict=True)
    ]
    views.sort(key=lambda v: (v.origin, v.name))
    return RecordingBlueprint(timeline, views, play_state)


def read_recording(path: str | Path) -> RecordedRun:
    path = Path(path)
    if not path.is_file():
        raise RecordingReadError(f"no such recording: {path}")
    truncated_bytes = 0
    try:
        chunks, closed_cleanly = _read_chunks(path)
    except Exception as exc:  # rerun raises its own types for unreadable files
        chunks, truncated_bytes = _read_truncated(path, exc)
        closed_cleanly = False
    by_entity: dict[str, list] = defaultdict(list)
    for chunk in chunks:
        by_entity[str(chunk.entity_path)].append(chunk)

    series = {name: _temporal_series(c, name) for name, c in by_entity.items()}
    diagnostics = {
        key: DiagnosticSeries(series[entity][0], series[entity][2])
        for entity, key in _DIAGNOSTIC_ENTITIES.items()
        if entity in series and len(series[entity][1])
    }
    meta_text = _static_text(by_entity.get("/run/metadata", []))
    metadata = _metadata(meta_text)
    model = recorded_model(metadata)
    letters = model.joint_letters
    n = len(letters)
    positions = [series.get(f"/joints/{j}/position") for j in letters]
    if any(p is None or len(p[1]) == 0 for p in positions) and "joint_names" in metadata:
        # Written when the recorder opened: a run that ended (was killed) before its first step.
        empty = np.zeros((0, n))
        return RecordedRun(
            t=np.zeros(0),
            step=np.zeros(0, dtype=int),
            q=empty,
            target=empty,
            qdot=None,
            torque=None,
            current_cmd=empty,
            current_meas=empty,
            events=_events(by_entity),
            metadata=metadata,
            closed_cleanly=closed_cleanly,
            truncated=truncated_bytes > 0,
            truncated_bytes=truncated_bytes,
            diagnostics=diagnostics,
            model=model,
        )
    if any(p is None or len(p[1]) == 0 for p in positions):
        raise RecordingReadError(
            f"{path} holds no joint positions: not a run recorded by reach-stack "
            f"(entities: {sorted(by_entity)[:8]})"
        )
    # Align every series on the steps all joints have (a crash may cut the last step).
    common = set(positions[0][1].tolist())  # type: ignore[index]
    for p in positions[1:]:
        common &= set(p[1].tolist())  # type: ignore[index]
    steps = np.array(sorted(common), dtype=int)

    def aligned(name: str, width: int) -> np.ndarray | None:
        entry = series.get(name)
        if entry is None or len(entry[1]) == 0:
            return None
        _, s, v = entry
        index = {int(k): i for i, k in enumerate(s)}
        out = np.full((len(steps), width), np.nan)
        for row, k in enumerate(steps):
            i = index.get(int(k))
            if i is not None and v.shape[1] == width:
                out[row] = v[i]
        return out

    pos = [aligned(f"/joints/{j}/position", 2) for j in letters]
    cur = [aligned(f"/joints/{j}/current", 2) for j in letters]
    t_all, s_all, _ = positions[0]  # type: ignore[misc]
    t_index = {int(k): float(tt) for tt, k in zip(t_all, s_all, strict=True)}

    events = _events(by_entity)
    summary_text = _static_text(by_entity.get("/run/summary", []))
    period = aligned("/link/loop_period", 1)
    return RecordedRun(
        t=np.array([t_index[int(k)] for k in steps]),
        step=steps,
        q=np.stack([p[:, 0] for p in pos if p is not None], axis=1),
        target=np.stack([p[:, 1] for p in pos if p is not None], axis=1),
        qdot=aligned("/velocities", n),
        torque=aligned("/torques", n),
        current_cmd=np.stack([c[:, 0] for c in cur if c is not None], axis=1)
        if all(c is not None for c in cur)
        else np.full((len(steps), n), np.nan),
        current_meas=np.stack([c[:, 1] for c in cur if c is not None], axis=1)
        if all(c is not None for c in cur)
        else np.full((len(steps), n), np.nan),
        events=events,
        metadata=metadata,
        summary=_summary(summary_text),
        closed_cleanly=closed_cleanly,
        truncated=truncated_bytes > 0,
        truncated_bytes=truncated_bytes,
        diagnostics=diagnostics,
        loop_period_ms=None if period is None else period[:, 0],
        model=model,
    )


def _column_stats(values: np.ndarray) -> dict[str, list[float | None]]:
    """Per device (column): the last reported value and the range over the recording."""
    final, low, high = [], [], []
    for column in values.T:
        seen = column[np.isfinite(column)]
        final.append(float(seen[-1]) if len(seen) else None)
        low.append(float(seen.min()) if len(seen) else None)
        high.append(float(seen.max()) if len(seen) else None)
    return {"final": final, "min": low, "max": high}


def diagnostics_summary(run: RecordedRun) -> dict[str, object] | None:
    """What `inspect` says of the diagnostics: per Monitor reading its rows and, per device
    (the joints, then the jaw: E D C B A on the Alpha 5), the last value and the range; each
    device's last status flags by name ("ok" when none, None if it never reported). None when
    the recording has none."""
    if not run.diagnostics:
        return None
    letters = diagnostic_letters(run.model)
    out: dict[str, object] = {"devices": list(letters)}
    for m in MONITOR_READINGS:
        series = run.diagnostics.get(m.key)
        if series is not None:
            out[m.key] = {"rows": len(series.t), **_column_stats(series.values)}
    status = run.diagnostics.get(STATUS_KEY)
    if status is not None:
        last = _column_stats(status.values)["final"]
        out["final_status"] = {
            letter: None if v is None else HardwareStatus(int(v)).flag_names() or ["ok"]
            for letter, v in zip(letters, last, strict=True)
        }
    return out


def _finite_or_none(values: np.ndarray) -> list[float | None]:
    return [float(v) if np.isfinite(v) else None for v in values]


def _last_event(events: list[tuple[float, str, str]], prefix: str) -> str | None:
    texts = [text[len(prefix) :].strip() for _, _, text in events if text.startswith(prefix)]
    return texts[-1] if texts else None


def _summarize_sim(path: str | Path, run: RecordedRun) -> dict[str, object]:
    """A simulator recording (`reach-sim --record`): the arm's true state, no targets. The
    position "setpoint" is the firmware's (None for a joint not in position mode)."""
    modes_text = _last_event(run.events, "modes:")
    modes: dict[str, str] = {}
    for item in (modes_text or "").split(","):
        joint, _, mode = item.strip().partition("=")
        if joint and mode:
            modes[joint] = mode
    faults = [f"{t:8.3f}s {lv}: {tx}" for t, lv, tx in run.events if tx.startswith("faults:")]
    final_faults = _last_event(run.events, "faults:")
    letters = run.model.joint_letters
    empty = [None] * len(letters)
    part = run.metadata.get("part")
    out: dict[str, object] = {
        "file": str(path),
        "kind": "simulator",
        "arm": run.model.name,
        "steps": int(len(run.step)),  # samples logged (fewer per second while the arm idles)
        "duration_s": run.duration_s,
        "start_s": float(run.t[0]) if len(run.t) else None,  # sim time of the first sample
        "end_s": float(run.t[-1]) if len(run.t) else None,
        "joints": list(letters),
        "final_position": _finite_or_none(run.q[-1]) if len(run.step) else empty,
        "final_setpoint": _finite_or_none(run.target[-1]) if len(run.step) else empty,
        "final_modes": [modes.get(j) for j in letters],
        "final_faults": final_faults or "none",
        "faults": faults,
        "part": part,  # 0 for the first file written; a later part starts mid-run
        "closed_cleanly": run.closed_cleanly,
        "truncated": run.truncated,
        "truncated_bytes": run.truncated_bytes,
        "events": [f"{t:8.3f}s {lv}: {tx}" for t, lv, tx in run.events],
        "metadata": run.metadata,
    }
    return out


def summarize_recording(path: str | Path) -> dict[str, object]:
    """Duration, joints, final errors and the evaluation metrics, computed from the recording.

    `kind` says what wrote it: "run" (`reach-driver run --record`: targets, errors, metrics)
    or "simulator" (`reach-sim --record`: the true state, no targets; see `_summarize_sim`).

    Metrics need a uniform period: they use the median step period, and the last target of the
    run (a run with several targets is scored against its final one).
    """
    with malformed_is_read_error():
        return _summarize(path)


@contextmanager
def malformed_is_read_error() -> Iterator[None]:
    """Reading or using a file no writer of ours makes: a RecordingReadError saying what is
    wrong, not a traceback."""
    try:
        yield
    except RecordingReadError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, ArithmeticError) as exc:
        raise RecordingReadError(
            f"not a recording reach-stack can read: {type(exc).__name__}: {exc}"
        ) from None


def _summarize(path: str | Path) -> dict[str, object]:
    run = read_recording(path)
    if run.metadata.get("source") == SIM_SOURCE:
        return _summarize_sim(path, run)
    if len(run.step):
        final_target: list[float | None] = run.target[-1].tolist()
        final_position: list[float | None] = run.q[-1].tolist()
        final_error: list[float | None] = (run.target[-1] - run.q[-1]).tolist()
    else:  # ended before its first step: nothing to show but how it started
        final_target = final_position = final_error = [None] * run.model.n_joints
    out: dict[str, object] = {
        "file": str(path),
        "kind": "run",
        "arm": run.model.name,
        "steps": int(len(run.step)),
        "duration_s": run.duration_s,
        "joints": list(run.model.joint_letters),
        "final_target": final_target,
        "final_position": final_position,
        "final_error": final_error,
        "closed_cleanly": run.closed_cleanly,
        "truncated": run.truncated,
        "truncated_bytes": run.truncated_bytes,
        "events": [f"{t:8.3f}s {lv}: {tx}" for t, lv, tx in run.events],
        "metadata": run.metadata,
    }
    dt = float(np.median(np.diff(run.t))) if len(run.step) >= 2 else math.nan
    if len(run.step) >= 2 and not (math.isfinite(dt) and dt > 0):
        out["notes"] = [
            f"no metrics: the steps are not spaced in time (median period {dt:g} s, "
            f"{len(run.step)} steps from {run.t[0]:g} to {run.t[-1]:g} s)"
        ]
    elif len(run.step) >= 2:
        qdot = run.qdot if run.qdot is not None else np.gradient(run.q, run.t, axis=0)
        tau = run.torque if run.torque is not None else np.zeros_like(run.q)
        trace = Trace(
            dt=dt,
            q=run.q,
            qdot=np.nan_to_num(qdot),
            tau=np.nan_to_num(tau),
            target=run.target[-1],
            model=run.model,
        )
        out["control_period_s"] = dt
        out["metrics"] = compute_metrics(trace).as_dict()
        letters = run.model.joint_letters
        anatomy = overshoot_anatomy(trace.q, trace.qdot, trace.target, dt, letters)
        out["overshoot"] = None if anatomy is None else anatomy.as_dict()
    diagnostics = diagnostics_summary(run)
    if diagnostics is not None:
        out["diagnostics"] = diagnostics
    if run.summary:
        out["recorded_summary"] = run.summary
    return out
