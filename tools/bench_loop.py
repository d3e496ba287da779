#!/usr/bin/env python3
"""Does the control loop keep time when the machine is busy? The README's `run` command on a
pseudo-terminal (its live table drawn) with `--record`, first as the machine is, then beside
a second reach-sim and a process of two threads multiplying matrices, with `--viewer serve`;
the loop period (wall time between two commands, what the watchdog judges) of each set,
pooled over its runs, and the loaded set's p99.9 as a ratio of the first's.

    .venv/bin/python tools/bench_loop.py [--runs 4] [--seconds 6]

The aim is no watchdog trip at the default 0.2 s in the loaded runs; the script exits 1 when
one trips or a run fails. A longer campaign, other loads and the gaps taken apart:
tools/loop_timing.py.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from loop_timing import Load, RunResult, Sim, fmt, percentiles, run_once

LOADED = [("sim", 1), ("threads", 2)]


def runs(
    where: Path, n: int, seconds: float, load: list[tuple[str, int]], viewer: list[str]
) -> list[RunResult]:
    sim = Sim(where, "alpha5", "127.0.0.1:0", 0)
    extra = Load(load, where, 0)
    try:
        time.sleep(1.0)
        return [run_once(k, sim.link, where, seconds, viewer, tty=True) for k in range(1, n + 1)]
    finally:
        extra.stop()
        sim.stop()


def pooled(results: list[RunResult]) -> np.ndarray:
    return np.concatenate([r.periods_ms for r in results]) if results else np.zeros(0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=4, help="runs in each set (default 4)")
    parser.add_argument("--seconds", type=float, default=6.0, help="each run's --seconds (6)")
    args = parser.parse_args(argv)
    print(
        f"README run (ddpg, --record, on a pty), {args.runs} x {args.seconds:g} s per set; "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the start"
    )
    with tempfile.TemporaryDirectory(prefix="bench-loop-") as tmp:
        base_dir, load_dir = Path(tmp, "base"), Path(tmp, "loaded")
        base_dir.mkdir()
        load_dir.mkdir()
        base = runs(base_dir, args.runs, args.seconds, [], [])
        loaded = runs(load_dir, args.runs, args.seconds, LOADED, ["--viewer", "serve"])
    b, lo = percentiles(pooled(base)), percentiles(pooled(loaded))
    print(f"  as the machine is: loop period {fmt(b)} ({pooled(base).size} periods)")
    print(
        f"  + a reach-sim, 2 busy threads, --viewer serve: loop period {fmt(lo)} "
        f"({pooled(loaded).size} periods; load average {os.getloadavg()[0]:.1f})"
    )
    ratio = lo["p99.9"] / b["p99.9"] if b["p99.9"] > 0 else float("nan")
    print(f"loop period p99.9 loaded / as is: {ratio:.2f}; p99 {lo['p99'] / b['p99']:.2f}")
    bad = [r for r in base + loaded if r.watchdog or r.exit_code != 0]
    for r in bad:
        print(f"  run {r.index}: exit {r.exit_code}: {r.watchdog or r.failure}")
    trips = sum(1 for r in loaded if r.watchdog)
    verdict = "met" if not bad else "MISSED"
    print(
        f"watchdog trips under load: {trips} of {len(loaded)}; aim none, no failed run: {verdict}"
    )
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
