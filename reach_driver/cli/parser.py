"""The `reach-driver` command line: options, subcommands and their help."""

from __future__ import annotations

import argparse
import math
import os
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from protocol.alpha5 import TORQUE_PER_AMP_NM
from protocol.models import ArmModelName
from protocol.viewer import add_viewer_option
from reach_driver.cli.exits import exit_table_text
from reach_driver.control import Pacing
from reach_driver.controllers import registered_list
from reach_driver.realtime import RealtimePolicy
from reach_driver.transport import DEFAULT_BAUD

DESCRIPTION = """\
Talk to a Reach Alpha 5 or Bravo 7 arm, or a virtual one (reach-sim), over the Reach/BPL
serial protocol. The arm's model is found from the devices that answer (--arm names it).

--port takes a serial device (/dev/ttyUSB0), any pyserial URL (loop://, rfc2217://...),
udp://HOST[:PORT] for Ethernet arms (port 6789 by default) or can://INTERFACE/CHANNEL for
an arm behind a CAN gateway (see docs/can-tunnel.md). It defaults to $REACH_PORT.

Joint angles are the arm's own, in radians, base to tip: E D C B on an Alpha 5 (base,
shoulder, elbow, wrist), G F E D C B on a Bravo 7; the jaw is in mm. Safety is always on:
commands outside the limits the arm reports are refused before anything is sent, and Ctrl-C
leaves the arm in a safe mode.
"""

EPILOG = """\
examples:
  reach-driver --port /dev/ttyUSB0 info
  reach-driver --port udp://192.168.2.3 monitor
  reach-driver --port /dev/ttyUSB0 move 3.1 1.5 1.5 3.0 --jaw 8
  reach-driver --port /dev/ttyUSB0 run --controller pid --target 3.1 1.5 1.5 3.0 --seconds 10
  reach-driver --port /dev/ttyUSB0 run --controller ddpg-distilled \\
      --target 5.78 1.97 1.67 3.96 --seconds 20 --record run.rrd
  reach-driver controllers          # what each controller is; a learned one's training
  reach-driver workspace --xyz 200 0 150   # where the tool reaches; angles for a point
  reach-driver inspect run.rrd
  reach-driver export run.rrd --to run.mcap   # ROS 2 messages: ros2 bag, Foxglove
  reach-driver export run.rrd --to run.csv    # one row per control step (.parquet too)
  reach-driver --port /tmp/alpha5 run --controller pid --target 3.1 1.5 1.5 3.0 \\
      --seconds 10 --viewer serve     # watch it live from a browser (or an SSH tunnel)

exit status (every command):
{exits}
docs/hil.md: using a real arm.
"""


def package_version() -> str:
    try:
        return version("reach-stack")
    except PackageNotFoundError:  # a source tree that was never installed
        return "unknown (not installed)"


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


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


VIEWER_HELP = (
    "watch live in Rerun, beside --record (the file is still written): spawn [PORT] starts "
    "the native viewer (needs a display); connect [URL|PORT] streams to a running one "
    "(default rerun+http://127.0.0.1:9876/proxy, what plain `rerun` listens on); serve "
    "[GRPC_PORT [WEB_PORT]] hosts a gRPC server (default 9876) and the web viewer (default "
    "9090) here, both on loopback unless --viewer-bind, and prints the address to open: "
    "the way to watch on a machine without a display (ssh -L both ports). "
    "A viewer that cannot start or goes away is "
    "named once and dropped; control never stops for it. Put it after positional arguments"
)


def _add_connection_options(
    parser: argparse.ArgumentParser, default: Any, request_timeout: bool
) -> None:
    g = parser.add_argument_group("connection and safety (before or after the command)")
    g.add_argument(
        "--port",
        default=default(os.environ.get("REACH_PORT")),
        help="device path, pyserial URL, udp://HOST[:PORT] or can://IF/CHANNEL "
        "(default: $REACH_PORT)",
    )
    g.add_argument(
        "--arm",
        choices=[m.value for m in ArmModelName],
        default=default(None),
        help="the arm's model; by default it is found from the devices that answer (0x06 "
        "and 0x07 answering: a Bravo 7). Given, an arm whose devices say otherwise is "
        "refused before anything but a request is sent (exit 4)",
    )
    g.add_argument(
        "--baud",
        type=int,
        default=default(DEFAULT_BAUD),
        help="serial baud rate (default 115200, 8N1)",
    )
    g.add_argument(
        "--rs485",
        action="store_true",
        default=default(False),
        help="half-duplex RS-485: space writes, never broadcast requests",
    )
    names = ["--timeout", "--reply-timeout"] if request_timeout else ["--reply-timeout"]
    g.add_argument(
        *names,
        dest="timeout",
        type=_positive,
        default=default(0.1),
        metavar="S",
        help="seconds to wait for each reply before retrying (default 0.1)",
    )
    g.add_argument(
        "--retries",
        type=_non_negative_int,
        default=default(2),
        help="retries per request before giving up (default 2)",
    )
    g.add_argument(
        "--watchdog",
        type=_positive,
        default=default(0.2),
        metavar="S",
        help="seconds without a command or fresh feedback before the arm is put in a safe "
        "mode during velocity/current control (default 0.2); at least two control periods "
        "(`run` refuses a --period it cannot span)",
    )
    g.add_argument(
        "--safe-wait",
        type=_non_negative,
        default=default(5.0),
        metavar="S",
        help="at the end of a move or run (Ctrl-C, a signal and failures included): seconds "
        "to keep sending the safe mode until the arm confirms it, waiting for a lost link "
        "meanwhile (default 5)",
    )
    g.add_argument(
        "--max-current",
        metavar="MA[,MA,MA,MA]",
        default=default(None),
        help="tighten the current limits the arm reports: one value for every joint or one "
        "per joint comma-separated (E,D,C,B on an Alpha 5; G,F,E,D,C,B on a Bravo 7), in mA; a "
        "controller's output is clipped to them (for first runs on a real arm)",
    )
    g.add_argument(
        "--position-margin",
        type=float,
        default=default(0.0),
        metavar="RAD",
        help="keep this far inside the arm's position limits (default 0)",
    )
    g.add_argument(
        "--no-chatter-guard",
        dest="chatter_guard",
        action="store_false",
        default=default(True),
        help="do not stop a run whose controller bang-bangs a joint around its goal "
        "(docs/chatter.md; on by default)",
    )
    g.add_argument(
        "--chatter-hold",
        choices=["position", "zero_velocity"],
        default=default("position"),
        help="how the chatter guard holds the arm when it fires (default: position, at the "
        "present angles)",
    )


def _add_global_options(
    parser: argparse.ArgumentParser,
    *,
    suppress: bool,
    request_timeout: bool = True,
    connection: bool = True,
) -> None:
    """The options every subcommand shares. On the top parser they carry the defaults; on
    the parent every subparser gets, they default to SUPPRESS, so a value given after the
    subcommand overrides one given before it and an absent one leaves it alone."""

    def default(value: object) -> object:
        return argparse.SUPPRESS if suppress else value

    if connection:
        _add_connection_options(parser, default, request_timeout)
    out = parser.add_argument_group("output (before or after the command)")
    out.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=default(0),
        help="log link events (-vv: and debug detail) to stderr",
    )
    out.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default(False),
        help="no live view or progress lines: results, warnings and errors only",
    )
    out.add_argument(
        "--log-file",
        metavar="FILE",
        default=default(None),
        help="append the driver's log (link events, retries, debug with -vv) to FILE",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="reach-driver",
        description=DESCRIPTION,
        epilog=EPILOG.format(exits=exit_table_text()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    _add_global_options(parser, suppress=False)
    common = argparse.ArgumentParser(add_help=False)
    _add_global_options(common, suppress=True)
    # `move --timeout` is the move's own timeout; the reply timeout is --reply-timeout there.
    common_move = argparse.ArgumentParser(add_help=False)
    _add_global_options(common_move, suppress=True, request_timeout=False)
    offline = argparse.ArgumentParser(add_help=False)  # commands that need no arm
    _add_global_options(offline, suppress=True, connection=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name: str, parents: list[argparse.ArgumentParser] | None = None, **kw: Any) -> Any:
        return sub.add_parser(name, parents=parents or [common], **kw)

    add(
        "info",
        help="devices found, versions, serials, limits, modes, status flags",
        description="List the devices that answer with their software versions, serial and "
        "model numbers, modes, limits and hardware status flags by name.",
    ).add_argument("--json", action="store_true", help="print JSON instead of a table")

    mon = add(
        "monitor",
        help="live table of joint states, update rates and link error counters",
        description="Stream positions, velocities, currents and modes and show them live "
        "with per-joint update rates and the link's error counters. Ctrl-C to stop.",
    )
    mon.add_argument(
        "--rate", type=_rate, default=10, help="heartbeat rate, 1..255 Hz (default 10)"
    )
    mon.add_argument(
        "--seconds",
        type=_positive,
        help="stop after watching this many seconds (counted once --record and --viewer are open)",
    )
    mon.add_argument(
        "--json",
        action="store_true",
        help="a JSON object per refresh, one a line (JSON Lines), instead of the table",
    )
    mon.add_argument(
        "--record",
        metavar="FILE.rrd",
        help="record what the arm reports for Rerun: states at 20 Hz, each device's Monitor "
        "readings and status flags as they are read (read back with `reach-driver inspect`)",
    )
    add_viewer_option(
        mon,
        VIEWER_HELP + ". With a viewer, states go to it at 20 Hz; the table still refreshes "
        "twice a second",
        keep=True,
    )

    move = add(
        "move",
        parents=[common_move],
        help="position-mode move of the joints (rad) and optionally the jaw (mm)",
        description="Move the joints (E D C B on an Alpha 5, G F E D C B on a Bravo 7) to "
        "absolute angles (rad, as the arm reports them) "
        "in position mode and wait until every joint is within --tolerance. Targets outside "
        "the limits are refused before anything moves (exit 3). If the link goes down during the "
        "move it stops waiting at once and exits 5, saying since when and the last positions "
        "the arm reported.",
    )
    move.add_argument(
        "angles",
        nargs="*",
        metavar="ANGLE",
        help="the four angles E D C B in rad: base angle, shoulder, elbow, wrist (or --xyz); "
        "on a Bravo 7 the six G F E D C B. The jaw's opening (mm) may follow them (as "
        "--jaw), or name the joints to move, the others staying where they are: G=1.2 A=5 "
        "(A: the jaw, mm)",
    )
    move.add_argument(
        "--xyz",
        nargs=3,
        type=_finite,
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
        "--tolerance",
        type=_positive,
        default=0.02,
        metavar="RAD",
        help="done when every joint is this close to its target (default 0.02 rad)",
    )
    move.add_argument(
        "--jaw-tolerance",
        type=_positive,
        default=0.5,
        metavar="MM",
        help="done when the jaw is this close (default 0.5 mm)",
    )
    move.add_argument(
        "--timeout",
        dest="move_timeout",
        type=_positive,
        default=60.0,
        metavar="S",
        help="give up (exit 1, joints stopped) after this many seconds (default 60); the "
        "reply timeout is --reply-timeout here",
    )
    add_viewer_option(move, VIEWER_HELP, keep=True)

    run = add(
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
        epilog="watching a run from a second terminal: the arm's port is exclusive, so "
        "`monitor` cannot share it; start the run with --viewer serve (then open the printed "
        "address, or `rerun --connect rerun+http://127.0.0.1:9876/proxy` in the other "
        "terminal) or start `rerun` there first and give the run --viewer connect. "
        "Exit status: the table in `reach-driver --help`. Recording never stops "
        "control: a write error to the --record file is named once, recording stops, the run "
        "goes on, its summary is printed and it exits 6. A viewer failing changes nothing "
        "but a warning.",
    )
    run.add_argument(
        "--controller",
        required=True,
        help=f"a registered name: {registered_list()} (`reach-driver controllers` says what "
        "each is)",
    )
    run.add_argument(
        "--target",
        nargs="+",
        type=float,
        required=True,
        metavar="ANGLE",
        help="the joint angles to reach, rad: E D C B on an Alpha 5, G F E D C B on a Bravo 7",
    )
    run.add_argument("--seconds", type=_positive, required=True, help="loop (arm) seconds")
    run.add_argument(
        "--period",
        type=_period,
        help="control period in arm seconds (default: the controller's own, e.g. the rate a "
        "policy was trained at, else 0.05); at least 0.001 s, and 1/255 .. 1 s with --pacing "
        "stream (the arm's heartbeat is 1..255 Hz); at most half of --watchdog",
    )
    run.add_argument(
        "--pacing",
        choices=[p.value for p in Pacing],
        default=Pacing.STREAM.value,
        help="stream: the arm's heartbeat paces the loop (arm time); poll: host clock",
    )
    run.add_argument(
        "--realtime",
        choices=[p.value for p in RealtimePolicy],
        default=RealtimePolicy.TRY.value,
        help="real-time priority (SCHED_FIFO 10) for the control loop's thread and the link's "
        "reader, so that a busy machine cannot hold them off past --watchdog. try (default): "
        "ask, and run without it if refused (the summary says why); require: refuse the run "
        "before anything is commanded (exit 7); off: do not ask. Linux grants it to root, to "
        "a python given CAP_SYS_NICE (setcap cap_sys_nice+ep) or to a user whose rtprio "
        "limit is at least 10 (`ulimit -r`, /etc/security/limits.d): docs/hil.md section 2a",
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
        "--json",
        action="store_true",
        help="print the summary and metrics as one JSON object on stdout (the live view "
        "stays on stderr; -q silences it)",
    )
    run.add_argument(
        "--record",
        metavar="FILE.rrd",
        help="record the run for Rerun (a write error stops the recording, not the run: exit 6)",
    )
    add_viewer_option(run, VIEWER_HELP, keep=True)

    ctl = add(
        "controllers",
        parents=[offline],
        help="the registered controllers: what each is, how a learned one was trained",
        description="List every controller registered in the reach_stack.controllers entry "
        "points (the names `run --controller` takes): its name, whether it is learned or "
        "engineered, the first line of its docstring and, for a learned one, its provenance "
        "(algorithm, demonstrations, teacher, env steps, wall time, seed, the training "
        "command). Each entry point is imported to describe it; one that fails to import is "
        "listed with its error (one whose library is not installed, with the extra that "
        "brings it), and the exit status is still 0.",
    )
    ctl.add_argument(
        "--json",
        action="store_true",
        help="a JSON list, one object per controller (name, target, kind, summary, "
        "provenance, error, extra: the extra to install when it is not installed)",
    )
    ws = add(
        "workspace",
        parents=[offline],
        help="where the tool can reach: the envelope, and the angles for a point (no arm needed)",
        description="Print where the tool centre point of the arm --arm names (the Alpha 5 "
        "by default; --arm bravo7) can reach inside the position limits (the factory ones, "
        "tightened by --position-margin): its distance from the axis the base yaw turns "
        "about (the base's z axis on the Alpha, 67.5 mm off it on the Bravo), its height and "
        "its farthest reach (mm, base frame, as `move --xyz` takes them), and the limits used. "
        "With --xyz: the joint angles that put it there (E D C; G F E D C on the Bravo), or, "
        "out of reach, the nearest reachable point and its angles (exit 3, as `move --xyz` "
        "refuses it). B turns the tool about its own axis and never moves the point. Needs "
        "no arm: the driver's own kinematics, the same `move --xyz` uses.",
    )
    ws.add_argument(
        "--xyz",
        nargs=3,
        type=_finite,
        metavar=("X", "Y", "Z"),
        help="a tool centre point target in mm, base frame",
    )
    ws.add_argument(
        "--position-margin",
        type=float,
        default=argparse.SUPPRESS,
        metavar="RAD",
        help="keep this far inside the factory position limits, as `move --position-margin` "
        "(default 0)",
    )
    ws.add_argument("--json", action="store_true", help="print JSON instead of text")
    ins = add(
        "inspect",
        parents=[offline],
        help="summarise a recorded run (.rrd): duration, final errors, events, metrics",
    )
    ins.add_argument("file", help="a recording written by `run --record`, or `reach-sim --record`")
    ins.add_argument("--json", action="store_true", help="print the summary as JSON")
    exp = add(
        "export",
        parents=[offline],
        help="write a recorded run (.rrd) as ROS 2 messages (.mcap) or a table (.csv, .parquet)",
        description="Write the run in a recording for other tools, in the format --to's suffix "
        "names. .mcap: ROS 2 messages (CDR, ros2msg schemas) for `ros2 bag` and Foxglove: "
        "sensor_msgs/msg/JointState on /joint_states (measured position, velocity, current as "
        "effort, mA), /joint_commands (commanded current as effort) and /joint_targets "
        "(target as position), rcl_interfaces/msg/Log on /events; needs the export extra. "
        ".csv or .parquet: one row per control step (step, t_s, then q, target, qdot, "
        "current_cmd, current_meas and torque per joint E D C B, the unit in each column's "
        "name; empty or NaN where the recording has no value). Stamps are the recording's arm "
        "time. The file appears only when complete; one already there is replaced then.",
    )
    exp.add_argument("file", help="a recording written by `run --record`, or `reach-sim --record`")
    exp.add_argument(
        "--to",
        required=True,
        metavar="OUT.mcap|OUT.csv|OUT.parquet",
        help="the file to write; its suffix says the format",
    )
    return parser
