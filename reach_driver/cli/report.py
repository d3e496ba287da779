"""A run's summary as the metrics see it and as it is serialised (recordings, JSON)."""

from __future__ import annotations

import dataclasses

import numpy as np

from protocol.models import ALPHA5, ArmModel
from reach_driver.metrics import (
    Metrics,
    OvershootAnatomy,
    Trace,
    compute_metrics,
    overshoot_anatomy,
)
from reach_driver.records import ControlSummary, LoopTrace


def run_metrics(summary: ControlSummary) -> Metrics | None:
    """The run scored like an evaluation episode (on the angles the arm reported)."""
    tr = summary.trace
    if tr is None or tr.samples < 2:
        return None
    return compute_metrics(trace_for_metrics(tr, summary.target, summary.model))


def run_overshoot(summary: ControlSummary) -> OvershootAnatomy | None:
    """How the run's overshoot came about (docs/metrics.md, "Overshoot"); None without one."""
    tr = summary.trace
    if tr is None or tr.samples < 2:
        return None
    letters = summary.model.joint_letters
    return overshoot_anatomy(tr.q, tr.qdot, summary.target, tr.dt, letters)


def trace_for_metrics(tr: LoopTrace, target: np.ndarray, model: ArmModel = ALPHA5) -> Trace:
    return Trace(dt=tr.dt, q=tr.q, qdot=tr.qdot, tau=tr.torque_Nm, target=target, model=model)


def summary_dict(s: ControlSummary) -> dict[str, object]:
    t = s.timing
    metrics = run_metrics(s)
    overshoot = run_overshoot(s)
    return {
        "ok": s.ok,
        "stopped_by": s.stopped_by,
        "chatter": None if s.chatter is None else dataclasses.asdict(s.chatter),
        "steps": s.steps,
        "loop_seconds": s.loop_seconds,
        "wall_seconds": s.wall_seconds,
        "final_q": s.final_q.tolist(),
        "final_error": s.final_error.tolist(),
        "saturated_steps": s.saturated_steps,
        "barrier_steps": s.barrier_steps,
        "implausible_samples": s.implausible_samples,
        "measured_hz": s.measured_hz,
        "duplicate_packets": s.duplicate_packets,
        "rate_hz": t.rate_hz,
        "arm_speed": t.arm_speed,
        "period_jitter_s": t.period_jitter_s,
        "state_age_p99_s": t.state_age_p99_s,
        "latency_p50_s": t.latency_p50_s,
        "latency_p99_s": t.latency_p99_s,
        "missed_deadlines": t.missed_deadlines,
        "skipped_states": t.skipped_states,
        "partial_states": t.partial_states,
        "incomplete_ticks": t.incomplete_ticks,
        "stream_gaps": t.stream_gaps,
        "lost_ticks": t.lost_ticks,
        "loop_period_p50_s": t.gaps.p50_s,
        "loop_period_p99_s": t.gaps.p99_s,
        "loop_period_p999_s": t.gaps.p999_s,
        "loop_period_max_s": t.gaps.max_s,
        "gc_pauses": t.gaps.gc_pauses,
        "gc_longest_s": t.gaps.gc_longest_s,
        "longest_gaps": [g.as_dict() for g in t.gaps.longest],
        "realtime": t.realtime.as_dict(),
        "left_in": s.left_in,
        "events": list(s.events),
        "metrics": None if metrics is None else metrics.as_dict(),
        "overshoot": None if overshoot is None else overshoot.as_dict(),
    }
