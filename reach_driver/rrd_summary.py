"""Read a run back from its .rrd recording (`reach-driver inspect`).

Uses rerun's chunk reader (`rerun.chunk.RrdReader`), which also reads a file whose writer was
killed before it could write its footer: a crashed run's recording still summarises.
"""

from __future__ import annotations

import json
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
from rerun.chunk import RrdReader

from protocol.alpha5 import JOINT_LETTERS
from reach_driver.metrics import Trace, compute_metrics
from reach_driver.recording import TIMELINE_STEP, TIMELINE_TIME


class RecordingReadError(ValueError):
    """The file is missing, not a recording, or holds no run written by reach-stack."""


@dataclass
class RecordedRun:
    """Per-step series of one recorded run, sorted by step (arrays in E D C B order)."""

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

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0


def _seconds(column: pa.Array) -> np.ndarray:
    """A duration timeline column (ns) as float seconds."""
    values = column.cast(pa.int64()).to_numpy(zero_copy_only=False)
    return values.astype(float) * 1e-9


def _temporal_series(chunks: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time, step, values) of a Scalars entity, concatenated over its chunks."""
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
    v = np.array([row if row is not None else [] for row in values], dtype=float)
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


def read_recording(path: str | Path) -> RecordedRun:
    path = Path(path)
    if not path.is_file():
        raise RecordingReadError(f"no such recording: {path}")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            chunks = RrdReader(path).stream().to_chunks()
    except Exception as exc:  # rerun raises its own types for unreadable files
        raise RecordingReadError(f"{path} is not a readable .rrd recording: {exc}") from exc
    # A writer that died before closing leaves no footer; the data before it is still good.
    closed_cleanly = not any("no footer" in str(w.message) for w in caught)
    by_entity: dict[str, list] = defaultdict(list)
    for chunk in chunks:
        by_entity[str(chunk.entity_path)].append(chunk)

    series = {name: _temporal_series(c) for name, c in by_entity.items()}
    positions = [series.get(f"/joints/{j}/position") for j in JOINT_LETTERS]
    if any(p is None or len(p[1]) == 0 for p in positions):
        raise RecordingReadError(
            f"{path} holds no joint positions: not a run recorded by reach-stack "
            f"(entities: {sorted(by_entity)[:8]})"
        )
    # Align every series on the steps all four joints have (a crash may cut the last step).
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

    pos = [aligned(f"/joints/{j}/position", 2) for j in JOINT_LETTERS]
    cur = [aligned(f"/joints/{j}/current", 2) for j in JOINT_LETTERS]
    t_all, s_all, _ = positions[0]  # type: ignore[misc]
    t_index = {int(k): float(tt) for tt, k in zip(t_all, s_all, strict=True)}

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

    meta_text = _static_text(by_entity.get("/run/metadata", []))
    summary_text = _static_text(by_entity.get("/run/summary", []))
    return RecordedRun(
        t=np.array([t_index[int(k)] for k in steps]),
        step=steps,
        q=np.stack([p[:, 0] for p in pos if p is not None], axis=1),
        target=np.stack([p[:, 1] for p in pos if p is not None], axis=1),
        qdot=aligned("/velocities", 4),
        torque=aligned("/torques", 4),
        current_cmd=np.stack([c[:, 0] for c in cur if c is not None], axis=1)
        if all(c is not None for c in cur)
        else np.full((len(steps), 4), np.nan),
        current_meas=np.stack([c[:, 1] for c in cur if c is not None], axis=1)
        if all(c is not None for c in cur)
        else np.full((len(steps), 4), np.nan),
        events=events,
        metadata=json.loads(meta_text) if meta_text else {},
        summary=json.loads(summary_text) if summary_text else {},
        closed_cleanly=closed_cleanly,
    )


def summarize_recording(path: str | Path) -> dict[str, object]:
    """Duration, joints, final errors and the evaluation metrics, computed from the recording.

    Metrics need a uniform period: they use the median step period, and the last target of the
    run (a run with several targets is scored against its final one).
    """
    run = read_recording(path)
    final_error = run.target[-1] - run.q[-1]
    out: dict[str, object] = {
        "file": str(path),
        "steps": int(len(run.step)),
        "duration_s": run.duration_s,
        "joints": list(JOINT_LETTERS),
        "final_target": run.target[-1].tolist(),
        "final_position": run.q[-1].tolist(),
        "final_error": final_error.tolist(),
        "closed_cleanly": run.closed_cleanly,
        "events": [f"{t:8.3f}s {lv}: {tx}" for t, lv, tx in run.events],
        "metadata": run.metadata,
    }
    if len(run.step) >= 2:
        dt = float(np.median(np.diff(run.t)))
        qdot = run.qdot if run.qdot is not None else np.gradient(run.q, run.t, axis=0)
        tau = run.torque if run.torque is not None else np.zeros_like(run.q)
        trace = Trace(
            dt=dt,
            q=run.q,
            qdot=np.nan_to_num(qdot),
            tau=np.nan_to_num(tau),
            target=run.target[-1],
        )
        out["control_period_s"] = dt
        out["metrics"] = compute_metrics(trace).as_dict()
    if run.summary:
        out["recorded_summary"] = run.summary
    return out
