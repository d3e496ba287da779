"""Benchmark the driver's closed loop against the virtual arm on a throttled serial line.

    .venv/bin/python tools/bench_driver.py [--seconds 10] [--baud 115200] [--hz 140]

The virtual arm runs in its own process (`reach-sim --baud B`), so the CPU figures are the
driver's alone. The loop streams POSITION and VELOCITY of the four joints (the telemetry a
state needs) and answers each complete state with four CURRENT commands from the PID. The
figures:

- closed-loop rate reached, against the wire-budget maximum for that telemetry at the baud
  rate (each reply is a 10-byte frame: 8 per state);
- latency from the arrival of the byte completing a state to the command being written
  (p50/p99), and the age of the state's oldest reading when the controller ran;
- CPU per cycle: the loop thread, and the whole driver process (reader thread included);
- the same loop on an unthrottled pty in the same process: the baseline the throttled run
  is compared with, and the host-paced (poll) loop on the throttled line.

The figure judged is the rate of *complete* states (a state with a lost reading filled in
does not count) as a share of the wire budget; the aim is AIM (95%), and the script exits 1
when it is missed, or when a run fails.

The loop streams without CURRENT (`measure_current=False`): with it a state is 12 frames,
120 B, and 115200 baud carries at most 96 states/s (the loop itself drops CURRENT when the
line cannot carry it at the rate asked, see `reach_driver.control.telemetry_fits`).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from protocol import PacketID, commands
from reach_driver import (
    ArmClient,
    ControlLoop,
    ControlSummary,
    Pacing,
    load_controller,
    open_transport,
)
from reach_driver.transport_serial import BITS_PER_BYTE

ROOT = Path(__file__).resolve().parents[1]
AIM = 0.95  # complete states per second, as a share of the wire budget
HEARTBEAT_SHARE = 0.97  # default heartbeat: this share of the budget, rounded down


def wire_budget_hz(baud: int) -> tuple[float, int, int]:
    """Max states/s the line carries for POSITION+VELOCITY of 4 joints, and the bytes per
    state each way."""
    telemetry = sum(
        len(commands.position(d, 0.0).encode()) + len(commands.velocity(d, 0.0).encode())
        for d in (5, 4, 3, 2)
    )
    command = sum(len(commands.current(d, 0.0).encode()) for d in (5, 4, 3, 2))
    return baud / BITS_PER_BYTE / telemetry, telemetry, command


class Sim:
    """`reach-sim` in a subprocess, reachable through a symlink to its pty."""

    def __init__(self, baud: int | None) -> None:
        self.dir = tempfile.TemporaryDirectory(prefix="bench-driver-")
        self.link = os.path.join(self.dir.name, "arm")
        cmd = [sys.executable, "-m", "reach_sim_bridge.cli", "--link", self.link]
        if baud:
            cmd += ["--baud", str(baud)]
        self.proc = subprocess.Popen(
            cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        deadline = time.monotonic() + 30
        while not os.path.exists(self.link):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                err = self.proc.stderr.read().decode() if self.proc.stderr else ""
                raise RuntimeError(f"reach-sim did not start: {err}")
            time.sleep(0.05)

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.dir.cleanup()


def run_loop(baud: int | None, hz: float, seconds: float, pacing: Pacing) -> ControlSummary:
    """One run against a fresh virtual arm (no backlog from an earlier run on its line)."""
    sim = Sim(baud)
    try:
        with ArmClient(open_transport(sim.link)) as client:
            q = client.read_joints((PacketID.POSITION, PacketID.VELOCITY)).q
            loop = ControlLoop(
                client, load_controller("pid"), 1.0 / hz, pacing=pacing, measure_current=False
            )
            return loop.run(q, seconds)
    finally:
        sim.close()


def complete_rate(s: ControlSummary) -> float:
    """States per second the loop acted on that had every reading fresh."""
    t = s.timing
    return max(t.steps - t.partial_states, 0) / s.wall_seconds if s.wall_seconds > 0 else 0.0


def report(name: str, s: ControlSummary, budget: float | None) -> None:
    t = s.timing
    share = f" = {100 * complete_rate(s) / budget:.1f}% of the wire budget" if budget else ""
    print(f"{name}")
    print(
        f"  rate        {t.rate_hz:8.1f} Hz over {s.wall_seconds:.1f} s; complete states"
        f" {complete_rate(s):.1f}/s{share}"
    )
    print(
        f"  period      mean {t.period_mean_s * 1e3:.2f} ms, jitter sd"
        f" {t.period_jitter_s * 1e3:.2f} ms, max {t.period_jitter_max_s * 1e3:.2f} ms;"
        f" missed deadlines {t.missed_deadlines},"
        f" skipped states {t.skipped_states}, partial states {t.partial_states},"
        f" incomplete ticks {t.incomplete_ticks}"
    )
    print(
        f"  latency     state complete -> command written p50 {t.latency_p50_s * 1e3:.3f} ms,"
        f" p99 {t.latency_p99_s * 1e3:.3f} ms, max {t.latency_max_s * 1e3:.3f} ms"
    )
    print(
        f"  state age   p50 {t.state_age_p50_s * 1e3:.2f} ms, p99 {t.state_age_p99_s * 1e3:.2f} ms"
    )
    print(
        f"  CPU/cycle   loop thread {t.cpu_per_step_s * 1e6:.0f} us, driver process"
        f" {t.process_cpu_per_step_s * 1e6:.0f} us"
    )
    if s.error:
        print(f"  ERROR       {s.error}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="per run (default 10)")
    parser.add_argument("--baud", type=int, default=115200, help="throttled line (default 115200)")
    parser.add_argument(
        "--hz",
        type=int,
        help=f"heartbeat rate (default: {100 * HEARTBEAT_SHARE:.0f}%% of the budget, rounded down)",
    )
    parser.add_argument("--poll-hz", type=float, default=50.0, help="polled loop rate (default 50)")
    args = parser.parse_args(argv)

    budget, telemetry, command = wire_budget_hz(args.baud)
    # A heartbeat at the full budget leaves no slack for the emulator's timing: the queue on
    # the line then grows and every state arrives late. 97% keeps it empty and clears the aim.
    hz = args.hz or int(np.floor(budget * HEARTBEAT_SHARE))
    print(
        f"wire budget at {args.baud} baud 8N1: {telemetry} B of telemetry per state -> "
        f"{budget:.1f} states/s max; commands {command} B/cycle on the other wire "
        f"({args.baud / BITS_PER_BYTE / command:.0f}/s)"
    )
    print(
        f"heartbeat {hz} Hz ({100 * hz / budget:.1f}% of the budget), {args.seconds:g} s per run\n"
    )

    stream = run_loop(args.baud, hz, args.seconds, Pacing.STREAM)
    report(f"stream pacing, {args.baud} baud", stream, budget)
    poll = run_loop(args.baud, args.poll_hz, min(args.seconds, 5.0), Pacing.POLL)
    report(f"poll pacing at {args.poll_hz:g} Hz, {args.baud} baud", poll, budget)
    base = run_loop(None, hz, args.seconds, Pacing.STREAM)
    report("baseline: stream pacing, unthrottled pty", base, None)
    ratio = complete_rate(stream) / complete_rate(base) if complete_rate(base) else 0.0
    reached = complete_rate(stream) / budget
    print(
        f"\nthrottled / unthrottled complete-state rate: {ratio:.3f}; latency p99 ratio "
        f"{stream.timing.latency_p99_s / base.timing.latency_p99_s:.2f}"
    )
    ok = stream.ok and base.ok and reached >= AIM
    verdict = "met" if ok else "MISSED"
    print(
        f"wire budget ratio {reached:.3f} (complete states {complete_rate(stream):.1f}/s of "
        f"{budget:.1f}/s); aim >= {AIM:.2f}: {verdict}"
    )
    if not (stream.ok and base.ok):
        print(f"a run failed: {stream.error or base.error}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
