#!/usr/bin/env python3
"""Cost of recording a control step to .rrd, as a share of the control period.

Logs the same per-step content a closed-loop run does (positions vs targets, currents, errors,
velocities, torques, link statistics, the 3D arm) for N steps, and compares the time per step
with the period's budget at the given control rate (aim: under 5%).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from reach_driver.recording import RunRecorder, StepSample


def bench(steps: int, rate_hz: float) -> dict[str, float]:
    rng = np.random.default_rng(0)
    q = rng.uniform(0.5, 2.5, size=(steps, 4))
    target = np.array([2.0, 1.5, 1.0, 0.5])
    samples = [
        StepSample(
            k / rate_hz,
            k,
            q[k],
            np.zeros(4),
            target,
            np.full(4, 100.0),
            np.full(4, 90.0),
            np.full(4, 0.5),
        )
        for k in range(steps)
    ]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.rrd"
        per_step = []
        with RunRecorder(path) as rec:
            t_start = time.perf_counter()
            for k, s in enumerate(samples):
                t0 = time.perf_counter()
                rec.log_step(s)
                rec.log_link(s.t, k, good=k * 8, bad=0, state_age_s=0.003)
                per_step.append(time.perf_counter() - t0)
            total = time.perf_counter() - t_start
        size = path.stat().st_size
    per = np.array(per_step)
    budget = 1.0 / rate_hz
    return {
        "mean_ms": per.mean() * 1e3,
        "p50_ms": float(np.percentile(per, 50) * 1e3),
        "p99_ms": float(np.percentile(per, 99) * 1e3),
        "share_of_budget_pct": per.mean() / budget * 100,
        "p99_share_pct": float(np.percentile(per, 99)) / budget * 100,
        "total_s": total,
        "bytes_per_step": size / steps,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="control steps to log")
    parser.add_argument("--rate", type=float, default=20.0, help="control rate (Hz)")
    args = parser.parse_args()
    for rate in sorted({args.rate, 100.0}):
        r = bench(args.steps, rate)
        print(
            f"recording at {rate:5.0f} Hz: {r['mean_ms']:.3f} ms/step mean, p50 {r['p50_ms']:.3f}, "
            f"p99 {r['p99_ms']:.3f} ms -> {r['share_of_budget_pct']:.2f}% of the "
            f"{1e3 / rate:.0f} ms period (p99 {r['p99_share_pct']:.2f}%), "
            f"{r['bytes_per_step']:.0f} B/step"
        )


if __name__ == "__main__":
    main()
