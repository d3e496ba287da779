"""`reach-sim`: serve a virtual Reach Alpha 5 (or, with `--arm bravo7`, a Reach Bravo 7) on a
pty (and/or UDP) until interrupted."""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import FrameType

from protocol.models import ALPHA5, ArmModelName, model_named
from protocol.viewer import add_viewer_option, viewer_options_problem
from reach_sim_bridge.emulator.faults import FaultConfig, torque_scales
from reach_sim_bridge.emulator.server import TURNAROUND_BYTES, SimConfig, SimServer, serve_forever
from reach_sim_bridge.emulator.udp import DEFAULT_UDP_HOST, DEFAULT_UDP_PORT, parse_udp_address
from reach_sim_bridge.model.arms import load_params
from reach_sim_bridge.model.params import ArmParams
from reach_sim_bridge.model.sensors import (
    DEFAULT_POSITION_NOISE,
    DEFAULT_VELOCITY_NOISE,
    SensorNoise,
)

DESCRIPTION = """\
Serve a simulated Reach Alpha 5 (MuJoCo physics + emulated joint firmware) speaking the
Reach/BPL serial protocol. A pseudo-terminal is created and its path printed: open it like
the arm's serial port (any baud rate; 8N1; raw). With --udp the arm also answers on UDP, as
the Ethernet variants do. Devices 0x01 (jaws, mm) to 0x05 (base) and broadcast 0xFF.
With --arm bravo7, a Reach Bravo 7: devices 0x01 (jaws) to 0x07 (base) and the router 0x0D,
which answers the wrist's force-torque reading (0xD8; six zeros written to it tare it).
Stop with Ctrl-C or SIGTERM (the --link symlink is removed)."""

EPILOG = """\
output (stdout, one per line, then the server runs):
  pty /dev/pts/N       the serial device to open
  link PATH            the stable symlink to it (with --link)
  udp HOST:PORT        the UDP address (with --udp)

examples:
  reach-sim --link /tmp/alpha5
  reach-sim --udp --no-pty                      # UDP only, 127.0.0.1:6789
  reach-sim --speed 5 --torque-scale E=0.25      # paper scenario 3, five times real time
  reach-sim --baud 115200 --latency-ms 5 --drop-rate 0.01 --sensor-noise
  reach-sim --link /tmp/alpha5 --half-duplex     # RS-485: one talker at a time, 115200 baud
  reach-sim --params arm.json --randomize-params 3  # an identified arm, perturbed
  reach-sim --link /tmp/alpha5 --record sim.rrd --viewer serve 9877 9091  # watch it live
  reach-sim --arm bravo7 --udp --link /tmp/bravo7  # a Bravo 7 on UDP 6789 and a pty
"""


def _positive_float(text: str) -> float:
    value = _float(text)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return value


def _probability(text: str) -> float:
    value = _float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"a probability is in [0, 1], got {text}")
    return value


def _non_negative(text: str) -> float:
    value = _float(text)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _baud(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"baud is a whole number of bits/s: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"baud must be > 0, got {text}")
    return value


def _udp(text: str) -> tuple[str, int]:
    try:
        return parse_udp_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _noise(text: str) -> SensorNoise:
    parts = text.split(",")
    if len(parts) > 2:
        raise argparse.ArgumentTypeError(f"expected POS_STD[,VEL_STD], got {text!r}")
    try:
        pos = float(parts[0])
        vel = float(parts[1]) if len(parts) == 2 else DEFAULT_VELOCITY_NOISE
        return SensorNoise(pos, vel)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"bad --sensor-noise {text!r}: {exc}") from None


def _version() -> str:
    try:
        return version("reach-stack")
    except PackageNotFoundError:  # running from a source tree that was never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="reach-sim",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    link = p.add_argument_group("serving")
    link.add_argument(
        "--link",
        metavar="PATH",
        help="also make a stable symlink PATH to the pty (replaces an old "
        "symlink, never a real file; removed on exit)",
    )
    link.add_argument("--no-pty", action="store_true", help="do not create a pty (serve UDP only)")
    link.add_argument(
        "--udp",
        nargs="?",
        type=_udp,
        metavar="HOST:PORT",
        const=(DEFAULT_UDP_HOST, DEFAULT_UDP_PORT),
        help="also serve UDP: answer each datagram's sender, one frame per "
        "reply datagram; several frames per incoming datagram are fine. Heartbeats and "
        "status go to the last sender of a valid frame; datagrams without one are "
        "counted, dropped and not answered. "
        f"Without a value {DEFAULT_UDP_HOST}:{DEFAULT_UDP_PORT}; a bare "
        "PORT or :PORT stays on loopback. Port 0 picks a free port",
    )
    link.add_argument(
        "--speed",
        type=_positive_float,
        default=1.0,
        metavar="X",
        help="run X times faster than the wall clock (default 1: real time). "
        "Sim-time rates (heartbeats, 1 Hz status) speed up too",
    )
    link.add_argument(
        "--baud",
        type=_baud,
        metavar="BAUD",
        help="throttle the pty both ways to a serial line's byte rate, "
        "BAUD/10 bytes/s (8N1), e.g. 115200. At most 0.2 s of output waits for the line; "
        "replies go ahead of heartbeats, and the oldest heartbeats are dropped (counted) "
        "when it is full. Default: unthrottled",
    )
    link.add_argument(
        "--half-duplex",
        action="store_true",
        help="the pty as one RS-485 wire (at --baud, default "
        f"{ALPHA5.serial_baud}): the arm answers only once the host's bytes have landed and "
        "the line "
        f"has been quiet {TURNAROUND_BYTES} byte times; host bytes sent while the arm is "
        "sending collide, and both frames are lost (counted as collisions); a broadcast "
        "REQUEST that several devices answer gets no answer. UDP is unaffected",
    )
    arm = p.add_argument_group("arm")
    arm.add_argument(
        "--arm",
        choices=[m.value for m in ArmModelName],
        default=ALPHA5.name,
        help="the arm served (default alpha5). bravo7: devices 0x01-0x07 (G base .. B wrist "
        "roll, A jaws) and the router 0x0D with the wrist's force-torque reading",
    )
    arm.add_argument(
        "--start",
        nargs="+",
        type=_float,
        metavar="RAD",
        help="initial joint angles in rad, the arm's own angles, one per joint base to tip "
        "(E D C B on the Alpha 5, G F E D C B on the Bravo 7; default: the middle of each "
        "joint's range)",
    )
    arm.add_argument(
        "--jaw",
        type=_non_negative,
        default=5.0,
        metavar="MM",
        help="initial jaw opening in mm (default 5)",
    )
    arm.add_argument(
        "--params",
        type=Path,
        metavar="FILE.json",
        help="serve the arm this parameter file describes: a JSON object of ArmParams "
        "field names (any subset; per-joint arrays of four in E D C B order, of six in G F E D "
        "C B with --arm bravo7; the rest the arm's nominal; keys starting with _ ignored), as "
        "tools/identify.py writes; a file of another arm's joints is refused in one line. "
        "--randomize-params then "
        "perturbs around it and --torque-scale multiplies its torque_scale. A file that cannot "
        "be used (not a regular file, over 16 MB, not JSON, an unknown key) is one line and "
        "exit 2",
    )
    arm.add_argument(
        "--dt",
        type=_positive_float,
        default=0.002,
        metavar="S",
        help="physics and firmware loop step in sim seconds (default 0.002)",
    )
    faults = p.add_argument_group("faults")
    faults.add_argument(
        "--torque-scale",
        action="append",
        default=[],
        metavar="JOINT=S",
        help="scale the torque joint JOINT (E D C B; G F E D C B on the Bravo 7) delivers by "
        "S in [0, 1]; "
        "repeatable. E=0.25 is the paper's 75%% torque loss",
    )
    faults.add_argument(
        "--sensor-noise",
        nargs="?",
        type=_noise,
        metavar="POS[,VEL]",
        const=SensorNoise(),
        help="add Gaussian noise to reported positions and velocities: "
        "standard deviations in rad and rad/s (mm, mm/s for the jaws); "
        f"default {DEFAULT_POSITION_NOISE},{DEFAULT_VELOCITY_NOISE}. "
        "The firmware's own loops see the true values",
    )
    faults.add_argument(
        "--randomize-params",
        type=int,
        metavar="SEED",
        help="perturb friction, armature, masses and buoyancy by up to "
        "+-20%% per joint, drawn from SEED",
    )
    faults.add_argument(
        "--corrupt-rate",
        type=_probability,
        default=0.0,
        metavar="P",
        help="flip each outgoing byte with probability P",
    )
    faults.add_argument(
        "--drop-rate",
        type=_probability,
        default=0.0,
        metavar="P",
        help="drop each outgoing frame with probability P",
    )
    faults.add_argument(
        "--latency-ms",
        type=_non_negative,
        default=0.0,
        metavar="N",
        help="delay every outgoing frame by N wall-clock milliseconds",
    )
    faults.add_argument(
        "--seed",
        type=int,
        metavar="N",
        help="seed for the link faults and sensor noise (reproducible runs)",
    )
    out = p.add_argument_group("output")
    out.add_argument(
        "--stats-interval",
        type=_non_negative,
        default=None,
        metavar="S",
        help="log frame/error counters every S wall seconds (0: never; default: never, "
        "every 10 s with -v)",
    )
    out.add_argument(
        "--record",
        metavar="FILE.rrd",
        type=Path,
        help="write the arm's true state (angles, setpoints, currents, torques, "
        "modes, link counters, 3D skeleton) to a Rerun recording",
    )
    add_viewer_option(
        out,
        "watch the arm's true state live in Rerun, beside --record (the file is still "
        "written) or alone: spawn [PORT] starts the native viewer (needs a display); connect "
        "[URL|PORT] streams to a running one (default rerun+http://127.0.0.1:9876/proxy); "
        "serve [GRPC_PORT [WEB_PORT]] hosts a gRPC server (default 9876) and the web viewer "
        "(default 9090), both on loopback unless --viewer-bind, and prints the address to "
        "open (no display needed; ssh -L both ports). "
        "A viewer that cannot start or goes away is named once and dropped; the "
        "simulator runs on. A driver run served on 9876 at the same time needs other ports",
    )
    out.add_argument(
        "--record-rate",
        type=_positive_float,
        default=50.0,
        metavar="HZ",
        help="samples per second of sim time in the recording (default 50)",
    )
    out.add_argument(
        "--record-max-mb",
        type=_positive_float,
        default=200.0,
        metavar="MB",
        help="cap on the recording's size on disk: it is split into parts FILE.rrd (newest), "
        "FILE.1.rrd, ... FILE.3.rrd, the oldest deleted (default 200)",
    )
    out.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="more log output (-v: info, -vv: debug); errors are always logged",
    )
    return p


def config_from_args(args: argparse.Namespace) -> SimConfig:
    """The SimConfig the parsed options ask for (ValueError on inconsistent options)."""
    model = model_named(getattr(args, "arm", ALPHA5.name))
    faults = FaultConfig(
        torque_scale=torque_scales(args.torque_scale, model),
        sensor_noise=args.sensor_noise,
        randomize_seed=args.randomize_params,
        corrupt_rate=args.corrupt_rate,
        drop_rate=args.drop_rate,
        latency_ms=args.latency_ms,
    )
    start = None if args.start is None else tuple(args.start)
    if start is not None and len(start) != model.n_joints:
        raise ValueError(
            f"--start takes {model.n_joints} angles ({' '.join(model.joint_letters)}) for the "
            f"{model.title}, got {len(start)}"
        )
    params: ArmParams | None = None
    if getattr(args, "params", None) is not None:
        params = load_params(args.params, model)
    return SimConfig(
        model=model,
        speed=args.speed,
        pty=not args.no_pty,
        link=args.link,
        udp=args.udp,
        baud=model.serial_baud if args.half_duplex and args.baud is None else args.baud,
        half_duplex=args.half_duplex,
        start=start,
        jaw_mm=args.jaw,
        dt=args.dt,
        faults=faults,
        seed=args.seed,
        params=params,
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    viewer_problem = viewer_options_problem(args)
    if viewer_problem:
        parser.error(viewer_problem)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )
    if args.stats_interval is None:  # quiet unless asked: a server runs for hours
        args.stats_interval = 10.0 if args.verbose else 0.0
    if args.stats_interval > 0.0:
        logging.getLogger("reach_sim_bridge.emulator.server").setLevel(min(level, logging.INFO))
    viewer = getattr(args, "viewer", None)
    try:
        config = config_from_args(args)
        server = SimServer(config)
    except ValueError as exc:
        parser.error(str(exc))

    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)
    try:
        path = server.start()
    except OSError as exc:
        print(f"reach-sim: error: {exc}", file=sys.stderr)
        return 1
    recorder = None
    if args.record is not None or viewer is not None:
        from reach_sim_bridge.emulator.recording import SimRecorder

        recorder = SimRecorder(
            server,
            args.record,
            rate_hz=args.record_rate,
            max_bytes=int(args.record_max_mb * 1e6),
            viewer=viewer,
            announce=lambda msg: print(msg, file=sys.stderr, flush=True),
        )
        recorder.start()
    try:
        if path is not None:
            print(f"pty {path}")
        if config.link is not None:
            print(f"link {config.link}")
        if server.udp_address is not None:
            host, port = server.udp_address
            print(f"udp {host}:{port}")
        sys.stdout.flush()
        serve_forever(server, stop, args.stats_interval)
    except RuntimeError as exc:
        print(f"reach-sim: error: {exc}: {server.error!r}", file=sys.stderr)
        return 1
    finally:
        server.stop()
        if recorder is not None:
            recorder.stop()
            if args.record is not None:
                print(f"recording {args.record} ({recorder.samples} samples)")
        s = server.stats()
        logging.getLogger("reach_sim_bridge.emulator.server").info(
            "stopped at t=%.1f s: frames in %d out %d, bad %s, errors %s",
            s.sim_time,
            s.frames_in,
            s.frames_out,
            s.bad_frames,
            s.firmware_errors,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
