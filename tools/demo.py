#!/usr/bin/env python3
"""`make demo`: the shipped learned controller drives the virtual Alpha 5 through `reach-driver`,
the same command a real arm gets: `ddpg`, the torque policy learned by reinforcement learning
from scratch, with nothing around the network (`reach-driver controllers` says what each
controller is and how it was trained).

The virtual arm (SimServer) is served on a pseudo-terminal in this process, starting at the
paper's zero pose; `reach-driver info` and `reach-driver run` then talk to it from a separate
process, exactly as they would to /dev/ttyUSB0. The target is the paper's scenario 1 mapped
to the arm's own angles by policy/tasks/scenarios.py (the one place that mapping lives).
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from protocol.extras import script_needs_extra

with script_needs_extra("tools/demo.py", "sim"):
    from policy.tasks.scenarios import SCENARIOS
    from reach_sim_bridge.emulator.faults import FaultConfig
    from reach_sim_bridge.emulator.server import SimConfig, SimServer


def driver_command() -> list[str]:
    """The installed `reach-driver` beside this interpreter, else the module."""
    script = Path(sys.executable).with_name("reach-driver")
    if script.is_file():
        return [str(script)]
    found = shutil.which("reach-driver")
    return [found] if found else [sys.executable, "-m", "reach_driver.cli"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="demo.py",
        description=(
            "Serve the virtual Alpha 5 on a pty, then run a controller (by default "
            "ddpg, the policy learned from scratch) through "
            "`reach-driver run` (the real CLI path, in its own process) to the paper's "
            "scenario 1 target, print the run's metrics and write a Rerun recording."
        ),
        epilog=(
            "The run ends by naming the recording's viewer and `reach-driver inspect` as you "
            "type them here. The same run against a real arm: docs/hil.md."
        ),
    )
    p.add_argument(
        "--controller",
        default="ddpg",
        help="registered controller (default ddpg; `reach-driver controllers` lists them)",
    )
    p.add_argument(
        "--scenario",
        type=int,
        default=1,
        choices=(1, 2, 3, 4),
        help="the paper's scenario (default 1; 3 runs E at 25%% torque)",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=20.0,
        help="arm seconds to run (default 20, the paper's episode)",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="simulator speed-up (default 1: real time; the run's metrics do not "
        "depend on it, its wall time is seconds/speed)",
    )
    p.add_argument(
        "--record",
        type=Path,
        default=Path("demo.rrd"),
        help="where to write the recording (default demo.rrd)",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not (math.isfinite(args.speed) and args.speed > 0):
        print(f"demo: --speed must be a positive number, got {args.speed}", file=sys.stderr)
        return 2
    if not (math.isfinite(args.seconds) and args.seconds > 0):
        print(f"demo: --seconds must be a positive number, got {args.seconds}", file=sys.stderr)
        return 2
    scenario = SCENARIOS[args.scenario - 1]
    episode = scenario.episode()
    e, d, c, b = (float(v) for v in episode.start)
    start = (e, d, c, b)
    target = [f"{v:.6f}" for v in episode.target]
    se, sd, sc, sb = (float(v) for v in episode.torque_scale)
    faults = FaultConfig(torque_scale=(se, sd, sc, sb))
    config = SimConfig(speed=args.speed, start=start, faults=faults)
    print(
        f"scenario {scenario.number} ({scenario.title}): paper angles "
        f"{list(scenario.paper_target)} -> arm angles E D C B {' '.join(target)} rad, "
        f"from {' '.join(f'{v:.4f}' for v in start)}"
    )
    driver = driver_command()
    with SimServer(config) as sim:
        port = sim.pty_path
        assert port is not None
        print(f"virtual Alpha 5 on {port} at {args.speed:g}x real time\n")
        base = [*driver, "--port", port]
        info = subprocess.run([*base, "info"], check=False)
        if info.returncode != 0:
            print(f"demo: `reach-driver info` failed (exit {info.returncode})", file=sys.stderr)
            return info.returncode
        run = [
            *base,
            "run",
            "--controller",
            args.controller,
            "--target",
            *target,
            "--seconds",
            f"{args.seconds:g}",
            "--record",
            str(args.record),
        ]
        print("$ reach-driver " + " ".join(run[len(driver) :]) + "\n", flush=True)
        try:
            code = subprocess.run(run, check=False).returncode
        except KeyboardInterrupt:
            print("\ndemo interrupted", file=sys.stderr)
            return 130
        true_error = episode.target - sim.snapshot().q
        if sim.error is not None:
            print(f"demo: the simulator failed: {sim.error!r}", file=sys.stderr)
            return 1
    print(
        "\nsimulator's true final error (rad, E D C B): "
        + " ".join(f"{e:+.4f}" for e in true_error)
        + f"  (max {np.max(np.abs(true_error)):.4f})"
    )
    return code  # the run named the recording and its viewer, as the user types them


if __name__ == "__main__":
    sys.exit(main())
