"""Identify an Alpha 5 (virtual or real) through the driver and fit the twin to it.

    reach-sim --link /tmp/alpha5 --speed 4 &
    tools/identify.py --port /tmp/alpha5 --out arm.json            # excite, record, fit, report
    tools/identify.py --fit-only arm.log.npz --out arm.json        # refit a recorded log
    tools/identify.py --virtual hidden.json --out arm.json         # a virtual arm, in-process
    python -m policy.campaigns.identification --port ...           # the same, from the package
    reach-sim --params arm.json ...                                # serve the fitted twin

Each joint in turn is driven in current mode through `reach_driver` (`ArmClient` with its
limits, barrier and watchdog on; `ControlLoop`, stream pacing, so time is the arm's) while
the other joints are held by a PID (`policy.controllers.excitation`): adaptive relay swings
at three speeds and a current chirp (the fitting motions) and pseudo-random current steps and
a second chirp at another pose (the validation motions), each inside a window around its pose
(the excitation backs off near the window edges and above a speed limit), with a
position-mode move to the segment's pose before each (`driving`). Ctrl-C leaves the arm in
the driver's safe mode (zero velocity).

Two records of the excitation: PARAMS.log.npz (`reach_sim_bridge.fit.segments.save_segments`:
per segment the loop's q, qdot, commands and measured currents on its tick grid, and each
command's transport delay measured from the driver's timestamps) and PARAMS.rrd (`--record`,
a Rerun recording through `reach_driver.recording`, `recording`; `--fit-only` reads either).
The fit is by simulation (`reach_sim_bridge.fit`, docs/identification.md; `fitting`), with the
delay measured, not fitted (it trades off against the armature). Outputs: PARAMS.json, a
fitted twin (`reach_sim_bridge.model.twin.write_twin`: the `--params` format with the fit
under "_fit", which `load_arm_params` ignores): per parameter its value and 1-sigma
uncertainty, the delays, R^2 and residual RMS; and a report PARAMS.report/report.md with PNG
figures (measured vs nominal twin vs fitted twin; `report`), with `--truth HIDDEN.json
--check-controller pid,ddpg-distilled` the controller gap (`twin_gap`).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.markup import escape

from policy.campaigns.identification.driving import Session, excite
from policy.campaigns.identification.fitting import check_controllers, fit, fit_metadata
from policy.campaigns.identification.recording import ExcitationRecorder, load_recording
from policy.campaigns.identification.report import write_report
from policy.campaigns.identification.virtual import excite_virtual
from policy.controllers.excitation import plan
from protocol.alpha5 import JOINT_LETTERS, JOINTS
from protocol.models import ALPHA5
from reach_driver import ArmClient, DriverError, SafetyConfig, open_transport
from reach_driver.errors import ArmModelError
from reach_driver.identity import ModelCheck
from reach_driver.interfaces import DEFAULT_BAUD
from reach_sim_bridge.fit.replay import DEFAULT_WINDOW_S
from reach_sim_bridge.fit.segments import load_segments, save_segments
from reach_sim_bridge.model.params import load_arm_params
from reach_sim_bridge.model.sensors import SensorNoise
from reach_sim_bridge.model.twin import FittedTwin, write_twin

PAYLOAD_MAX_KG = 2.0
"""The most `--payload` takes (kg): the Alpha 5's lift at full reach (its datasheet)."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="identify.py",
        description=__doc__.split("\n\n")[0] if __doc__ else "",
        epilog="Method: docs/identification.md. Real arms: docs/hil.md (identification).",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--port", help="the arm, as reach-driver --port takes it")
    src.add_argument(
        "--fit-only",
        type=Path,
        nargs="+",
        metavar="LOG",
        help="refit a recorded excitation: its .npz log or its .rrd recording; several are "
        "fitted together (a run with --payload beside one without)",
    )
    src.add_argument(
        "--virtual",
        type=Path,
        metavar="HIDDEN.json",
        help="excite the virtual arm this parameter file describes in this process (no driver, "
        "no link: the same controller and plan, the arm stepped directly), then fit it: what "
        "the data can and cannot tell apart, in seconds instead of minutes",
    )
    p.add_argument(
        "--sensor-noise",
        default="0.002,0.02",
        metavar="Q,V",
        help="with --virtual: the readings' noise, rad and rad/s (default 0.002,0.02: "
        "reach-sim --sensor-noise's)",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="with --virtual: the sensor noise's seed (default 0)"
    )
    p.add_argument(
        "--payload",
        type=float,
        metavar="KG",
        help="a known load held in the jaws (a compact dense mass, e.g. 1 kg of dive lead; the "
        "Alpha 5 lifts 2 kg at full reach): its inertia weighs E's torque scale, which nothing "
        "else does. With --virtual, E's fitting motions run again holding it. With --port, the "
        "arm holds it throughout (--joints E only): fit that log together with one without "
        "(--fit-only bare.log.npz loaded.log.npz)",
    )
    p.add_argument(
        "--payload-volume",
        type=float,
        default=0.0,
        metavar="LITRES",
        help="the water the --payload displaces, litres (default 0; 1 kg of lead: 0.09); its "
        "buoyancy loads D and C, not E",
    )
    p.add_argument("--out", type=Path, required=True, metavar="PARAMS.json")
    p.add_argument("--log", type=Path, metavar="LOG.npz", help="default: PARAMS.log.npz")
    p.add_argument(
        "--record",
        type=Path,
        metavar="FILE.rrd",
        help="the excitation as a Rerun recording (default: PARAMS.rrd)",
    )
    p.add_argument("--no-record", action="store_true", help="write no .rrd")
    p.add_argument("--report", type=Path, metavar="DIR", help="default: PARAMS.report/")
    p.add_argument("--no-report", action="store_true")
    p.add_argument(
        "--joints", default="E,D,C,B", help="joints to identify, comma-separated (default all)"
    )
    p.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="scale every segment's length (default 1: 46 arm s per joint, ~4 min for "
        "four joints with the moves)",
    )
    p.add_argument("--rate", type=float, default=50.0, help="control rate, Hz (default 50)")
    p.add_argument("--baud", type=int, default=DEFAULT_BAUD, help="serial baud rate")
    p.add_argument(
        "--max-current",
        type=float,
        default=300.0,
        metavar="MA",
        help="cap on the excitation's current per joint in mA (default 300; B at most "
        "half of it), also given to the driver as its current limit",
    )
    p.add_argument("--watchdog", type=float, default=0.2, metavar="S")
    p.add_argument("--window", type=float, default=DEFAULT_WINDOW_S, metavar="S")
    p.add_argument("--iterations", type=int, default=12)
    p.add_argument(
        "--no-fit-starts",
        action="store_true",
        help="start each replay window from the readings as they are (default: the windows' "
        "starting angle and speed are fitted beside the arm; see docs/identification.md)",
    )
    p.add_argument(
        "--check-controller",
        metavar="NAMES",
        help="with --truth: run these controllers (comma-separated, e.g. pid,ddpg-distilled) "
        "on the hidden arm, the fitted twin and the nominal twin on the same episodes and report "
        "the energy and settling-time gaps (tools/twin_gap.py)",
    )
    p.add_argument("--check-episodes", type=int, default=6, metavar="N")
    p.add_argument(
        "--truth",
        type=Path,
        metavar="PARAMS.json",
        help="a virtual arm's true parameters: the report adds the error of each",
    )
    return p


def _pair(text: str) -> tuple[float, float]:
    """`Q,V` as two numbers (ValueError saying what was given)."""
    parts = text.split(",")
    try:
        q, v = (float(x) for x in parts)
    except ValueError:
        raise ValueError(f"--sensor-noise takes Q,V (rad, rad/s), got {text!r}") from None
    return q, v


def _payload_problem(args: argparse.Namespace, joints: list[int]) -> str | None:
    """Why `--payload` cannot be used as given (None: it can)."""
    kg, litres = args.payload, args.payload_volume
    if not (math.isfinite(kg) and 0.0 < kg <= PAYLOAD_MAX_KG):
        return f"--payload takes a mass in kg, over 0 and at most {PAYLOAD_MAX_KG:g}, got {kg:g}"
    if not (math.isfinite(litres) and litres >= 0.0):
        return f"--payload-volume takes litres >= 0, got {litres:g}"
    e = JOINT_LETTERS.index("E")
    if args.fit_only is not None:
        return "--payload is how an excitation was run; a log keeps it (--fit-only reads it)"
    if args.virtual is not None and e not in joints:
        return "--payload weighs E's torque scale: --joints must include E"
    if args.port is not None and joints != [e]:
        return (
            "--payload with --port: the arm holds the load throughout, and it weighs E only "
            "(C and D are weighed by the wrist; B turns about the load): give --joints E, and "
            "fit with the log of a run without it (--fit-only bare.log.npz loaded.log.npz)"
        )
    return None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = Console(stderr=True, soft_wrap=True)
    out: Path = args.out
    log_path: Path = args.log or out.with_suffix(".log.npz")
    report_dir: Path = args.report or out.with_suffix(".report")
    record_path: Path | None = None if args.no_record else (args.record or out.with_suffix(".rrd"))
    try:
        joints = [JOINT_LETTERS.index(x.strip().upper()) for x in args.joints.split(",")]
    except ValueError:
        console.print(f"[red]error:[/] --joints takes letters of E D C B, got {args.joints!r}")
        return 2
    payload = (0.0, 0.0)
    if args.payload is not None:
        problem = _payload_problem(args, joints)
        if problem:
            console.print(f"[red]error:[/] {problem}")
            return 2
        payload = (float(args.payload), float(args.payload_volume))
    truth = load_arm_params(args.truth) if args.truth else None
    session: Session | None = None
    if args.fit_only is not None:
        segments = []
        for path in args.fit_only:
            try:
                if path.suffix == ".rrd":
                    segments += load_recording(path)
                else:
                    segments += load_segments(path)
            except (OSError, ValueError, KeyError) as exc:
                console.print(f"[red]cannot read {path}:[/] {exc}")
                return 2
        log_path = args.fit_only[0]
    elif args.virtual is not None:
        try:
            hidden = load_arm_params(args.virtual)
            noise = SensorNoise(*_pair(args.sensor_noise))
        except ValueError as exc:
            console.print(f"[red]error:[/] {exc}")
            return 2
        segments = excite_virtual(
            hidden,
            joints,
            plan(args.scale),
            rate_hz=args.rate,
            noise=noise,
            seed=args.seed,
            max_current_mA=args.max_current,
        )
        if args.payload is not None:
            # E's fitting motions again, the virtual arm holding the load
            segments += excite_virtual(
                replace(hidden, payload_kg=payload[0], payload_volume_l=payload[1]),
                [JOINT_LETTERS.index("E")],
                [w for w in plan(args.scale) if w.role == "fit"],
                rate_hz=args.rate,
                noise=noise,
                seed=args.seed + 1,
                max_current_mA=args.max_current,
            )
        session = Session(segments=segments)
        session.arm_seconds = sum(x.ticks * x.period for x in segments)
        header = {"virtual": str(args.virtual), "rate_hz": args.rate, "scale": args.scale}
        save_segments(segments, log_path, header)
        console.print(f"log {log_path} ({len(segments)} segments, excited in-process)")
    else:
        max_current = np.array([1.0, 1.0, 1.0, 0.5]) * args.max_current
        safety = SafetyConfig(
            watchdog_s=args.watchdog,
            chatter=None,  # the relay swings are a deliberate bang-bang about a centre
            current_limits_mA={int(d): float(m) for d, m in zip(JOINTS, max_current, strict=True)},
        )
        session = Session()
        try:
            client = ArmClient(open_transport(args.port, baud=args.baud), safety=safety)
            # the excitation, the fit and the twin are the Alpha 5's: another arm is refused
            # before anything but a request is sent
            client.start(model_check=ModelCheck.CONFIRM)
        except ArmModelError as exc:
            client.close()
            console.print(
                f"[red]wrong arm:[/] identification fits a {ALPHA5.title} only: {escape(str(exc))}"
            )
            return 4
        except (DriverError, ValueError) as exc:
            console.print(f"[red]no arm:[/] {exc}")
            return 4
        recorder: ExcitationRecorder | None = None
        if record_path is not None:
            try:
                recorder = ExcitationRecorder(
                    record_path,
                    {"port": args.port, "rate_hz": args.rate, "scale": args.scale},
                    console,
                )
            except DriverError as exc:
                client.close()
                console.print(f"[red]error:[/] {exc}")
                return 2
        interrupted = False
        try:
            faults = client.blocking_faults()
            if faults:
                console.print(f"[red]arm reports faults, not moving:[/] {faults}")
                return 1
            excite(
                client,
                joints,
                plan(args.scale),
                args.rate,
                console,
                session,
                max_current,
                recorder,
                payload,
            )
        except KeyboardInterrupt:
            interrupted = True
        except DriverError as exc:
            console.print(f"[red]identification stopped:[/] {exc}")
            interrupted = True
        finally:
            try:
                client.safe_stop(JOINTS)
                left = "zero_velocity"
            except DriverError as exc:
                left = f"unknown ({exc})"
            client.close()
            console.print(f"arm left in {left}")
            header = {
                "port": args.port,
                "rate_hz": args.rate,
                "scale": args.scale,
                "arm_seconds": session.arm_seconds,
                "move_seconds": session.move_seconds,
                "complete": not interrupted,
                "retries": session.retries,
            }
            if session.segments:
                save_segments(session.segments, log_path, header)
                console.print(f"log {log_path} ({len(session.segments)} segments)")
            if recorder is not None:
                recorder.close(header)
                if recorder.failed is None:
                    console.print(f"recording {record_path} ({recorder.step} steps)")
        if interrupted:
            return 130
        segments = session.segments
        console.print(
            f"arm time {session.arm_seconds:.1f} s excitation + ~{session.move_seconds:.1f} s moves"
        )
    outcome, replay = fit(
        segments, console, args.window, args.iterations, fit_starts=not args.no_fit_starts
    )
    logs = " + ".join(str(x) for x in args.fit_only) if args.fit_only else log_path
    meta = fit_metadata(outcome, session, args.window, logs)
    write_twin(FittedTwin(outcome.params, meta), out)
    console.print(f"wrote {out}")
    for key, q in outcome.fitted_quality.items():
        nom = outcome.nominal_quality[key]["window"]
        console.print(
            f"{key}: R^2 {q['window']['r2']:.4f} RMS {q['window']['rms_mrad']:.2f} mrad "
            f"(nominal twin {nom['r2']:.4f}, {nom['rms_mrad']:.2f} mrad)"
        )
    gap_text = None
    if args.check_controller:
        if truth is None:
            console.print("[red]error:[/] --check-controller needs --truth (the hidden arm)")
            return 2
        gap_text, gap_summary = check_controllers(
            args.check_controller.split(","), truth, outcome.params, args.check_episodes, console
        )
        meta = replace(meta, controller_gap=gap_summary)
        write_twin(FittedTwin(outcome.params, meta), out)
    if not args.no_report:
        path = write_report(outcome, replay, segments, report_dir, args.window, session, truth)
        if gap_text is not None:
            with path.open("a", encoding="utf-8") as f:
                f.write("\n" + gap_text)
        console.print(f"report {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
