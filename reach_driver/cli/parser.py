"""The `reach-driver` command line: options, subcommands and their help."""

from __future__ import annotations

import argparse
import math
import os
from typing import Any

from protocol.alpha5 import TORQUE_PER_AMP_NM
from reach_driver.control import Pacing
from reach_driver.transport import DEFAULT_BAUD

DESCRIPTION = """\
Talk to a Reach Alpha 5 arm, or the virtual arm (reach-sim), over the Reach/BPL serial
protocol.

--port takes a serial device (/dev/ttyUSB0), any pyserial URL (loop://, rfc2217://...),
udp://HOST[:PORT] for Ethernet arms (port 6789 by default) or can://INTERFACE/CHANNEL for
an arm behind a CAN gateway (see docs/can-tunnel.md). It defaults to $REACH_PORT.

Joint angles are the arm's own, in radians, in the order E D C B (base, shoulder, elbow,
wrist); the jaw is in mm. Safety is always on: commands outside the limits the arm reports
are refused before anything is sent, and Ctrl-C leaves the arm in a safe mode.
"""

EPILOG = """\
examples:
  reach-driver --port /dev/ttyUSB0 info
  reach-driver --port udp://192.168.2.3 monitor
  reach-driver --port /dev/ttyUSB0 move 3.1 1.5 1.5 3.0 --jaw 8
  reach-driver --port /dev/ttyUSB0 run --controller pid --target 3.1 1.5 1.5 3.0 --seconds 10
  reach-driver --port /dev/ttyUSB0 run --controller ddpg --target 5.78 1.97 1.67 3.96 \
      --seconds 20 --record run.rrd
  reach-driver inspect run.rrd

exit status: 0 done; 1 failed (timeout, fault, lost link during run); 2 bad usage; 3 refused
by a limit (nothing moved); 4 no arm (wrong port, no permission, nothing answering, wrong
baud); 5 the link was lost during a move (the message says since when and the last known
positions); 6 a run completed but its --record file is incomplete (a write error, e.g. a
full disk: recording stopped, control went on); 130 interrupted (arm left in a safe mode).
docs/hil.md: using a real arm.
"""


def _floats(text: str) -> float | list[float]:
    parts = [p for p in text.split(",") if p.strip()]
    values = [float(p) for p in parts]
    return values[0] if len(values) == 1 else values


def _param(text: str) -> tuple[str, Any]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        number = _floats(value)
    except ValueError:
        return key, value
    if not all(math.isfinite(v) for v in (number if isinstance(number, list) else [number])):
        raise argparse.ArgumentTypeError(f"{key}: values must be finite numbers, got {value!r}")
    return key, number


MIN_PERIOD_S = 0.001


def _period(text: str) -> float:
    value = _positive(text)
    if value < MIN_PERIOD_S:
        raise argparse.ArgumentTypeError(
            f"must be at least {MIN_PERIOD_S} s (1 ms), got {text}; with --pacing stream the "
            "arm's heartbeat allows 1/255 s (3.9 ms) .. 1 s"
        )
    return value


def _rate(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number of Hz, got {text!r}") from None
    if not 1 <= value <= 255:
        raise argparse.ArgumentTypeError(
            f"must be 1..255 Hz (the arm's HEARTBEAT_FREQUENCY, one byte; 0 turns streaming "
            f"off), got {text}"
        )
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="reach-driver",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--port",
        default=os.environ.get("REACH_PORT"),
        help="device path, pyserial URL, udp://HOST[:PORT] or can://IF/CHANNEL "
        "(default: $REACH_PORT)",
    )
    parser.add_argument(
        "--baud", type=int, default=DEFAULT_BAUD, help="serial baud rate (default 115200, 8N1)"
    )
    parser.add_argument(
        "--rs485",
        action="store_true",
        help="half-duplex RS-485: space writes, never broadcast requests",
    )
    parser.add_argument(
        "--timeout",
        type=_positive,
        default=0.1,
        help="seconds to wait for each reply before retrying (default 0.1)",
    )
    parser.add_argument(
        "--retries",
        type=_non_negative_int,
        default=2,
        help="retries per request before giving up (default 2)",
    )
    parser.add_argument(
        "--watchdog",
        type=_positive,
        default=0.2,
        help="seconds without a command or fresh feedback before the arm is put in a safe "
        "mode during velocity/current control (default 0.2)",
    )
    parser.add_argument(
        "--max-current",
        metavar="MA[,MA,MA,MA]",
        help="tighten the current limits the arm reports: one value for every joint or four "
        "comma-separated (E,D,C,B), in mA; a controller's output is clipped to them (for "
        "first runs on a real arm)",
    )
    parser.add_argument(
        "--position-margin",
        type=float,
        default=0.0,
        metavar="RAD",
        help="keep this far inside the arm's position limits (default 0)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log link events in detail")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sub.add_parser(
        "info",
        help="devices found, versions, serials, limits, modes, status flags",
        description="List the devices that answer with their software versions, serial and "
        "model numbers, modes, limits and hardware status flags by name.",
    ).add_argument("--json", action="store_true", help="print JSON instead of a table")

    mon = sub.add_parser(
        "monitor",
        help="live table of joint states, update rates and link error counters",
        description="Stream positions, velocities, currents and modes and show them live "
        "with per-joint update rates and the link's error counters. Ctrl-C to stop.",
    )
    mon.add_argument(
        "--rate", type=_rate, default=10, help="heartbeat rate, 1..255 Hz (default 10)"
    )
    mon.add_argument("--seconds", type=_positive, help="stop after this many seconds")

    move = sub.add_parser(
        "move",
        help="position-mode move of E D C B (rad) and optionally the jaw (mm)",
        description="Move the four joints to absolute angles (rad, as the arm reports them) "
        "in position mode and wait until every joint is within --tolerance. Targets outside "
        "the limits are refused before anything moves (exit 3). If the link goes down during the "
        "move it stops waiting at once and exits 5, saying since when and the last positions "
        "the arm reported.",
    )
    move.add_argument(
        "angles", nargs="*", type=float, metavar="ANGLE", help="E D C B in rad (or --xyz)"
    )
    move.add_argument(
        "--xyz",
        nargs=3,
        type=float,
        metavar=("X", "Y", "Z"),
        help="instead of the angles: the tool centre point's target in mm, base frame; the "
        "driver's inverse kinematics turns it into joint positions inside the limits (B keeps "
        "its angle); an unreachable target is refused before anything moves (exit 3)",
    )
    move.add_argument(
        "--xyz-tolerance", type=_positive, default=2.0, help="mm, with --xyz (default 2)"
    )
    move.add_argument("--jaw", type=float, metavar="MM", help="jaw opening in mm")
    move.add_argument(
        "--tolerance", type=_positive, default=0.02, help="rad per joint (default 0.02)"
    )
    move.add_argument("--jaw-tolerance", type=_positive, default=0.5, help="mm (default 0.5)")
    move.add_argument(
        "--timeout", dest="move_timeout", type=_positive, default=60.0, help="s (default 60)"
    )

    run = sub.add_parser(
        "run",
        help="closed-loop control with a registered controller",
        description="Run a controller (found by name in the reach_stack.controllers entry "
        "points) in current mode towards a target, then leave the arm in a safe mode and "
        "print the final errors, timing statistics and the run's metrics (energy, RMSE, MIE, "
        "MSSE, overshoot, settling time, reached; docs/metrics.md) computed from the angles "
        "the arm reported, with torque = measured current x the joint's torque constant "
        f"(E/D/C {TORQUE_PER_AMP_NM[0]:.3g}, B {TORQUE_PER_AMP_NM[3]:.3g} N m/A). "
        "With --pacing stream (default) the arm's heartbeat paces "
        "the loop and time is arm time: against reach-sim --speed X a run takes 1/X of the "
        "wall time and gives the same metrics.",
        epilog="exit status: 0 the run completed (whether or not it reached the target: see "
        "'reached'); 1 it was cut short (lost link, watchdog, fault, controller error); 3 the "
        "target is outside a limit (nothing moved); 4 no arm; 6 the run completed but writing "
        "its --record file failed (a full disk...): recording never stops control, so the "
        "warning names the file and the error, recording stops, the run goes on and its "
        "summary is printed; 130 interrupted.",
    )
    run.add_argument("--controller", required=True, help="e.g. pid, mpc, ddpg")
    run.add_argument("--target", nargs=4, type=float, required=True, metavar=("E", "D", "C", "B"))
    run.add_argument("--seconds", type=_positive, required=True, help="loop (arm) seconds")
    run.add_argument(
        "--period",
        type=_period,
        help="control period in arm seconds (default: the controller's own, e.g. the rate a "
        "policy was trained at, else 0.05); at least 0.001 s, and 1/255 .. 1 s with --pacing "
        "stream (the arm's heartbeat is 1..255 Hz)",
    )
    run.add_argument(
        "--pacing",
        choices=[p.value for p in Pacing],
        default=Pacing.STREAM.value,
        help="stream: the arm's heartbeat paces the loop (arm time); poll: host clock",
    )
    run.add_argument(
        "--param",
        action="append",
        type=_param,
        default=[],
        metavar="KEY=VALUE",
        help="controller parameter (repeatable; comma-separated values give a list)",
    )
    run.add_argument(
        "--record",
        metavar="FILE.rrd",
        help="record the run for Rerun (a write error stops the recording, not the run: exit 6)",
    )

    sub.add_parser("controllers", help="list the registered controllers")
    ins = sub.add_parser(
        "inspect",
        help="summarise a recorded run (.rrd): duration, final errors, events, metrics",
    )
    ins.add_argument("file", help="a recording written by `run --record`, or `reach-sim --record`")
    ins.add_argument("--json", action="store_true", help="print the summary as JSON")
    return parser
