"""What `tools/evaluate.py` does with its options: a controller scored on step responses of
the simulated Alpha 5 (directly, on Ray or through the driver) or of another arm's twin
(`--arm`, directly), its JSON, its table and its Rerun recording. `Options` holds the
command line's values, one field per option."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from policy.campaigns.evaluation import (
    DEFAULT_RATE_HZ,
    DEFAULT_SECONDS,
    Episode,
    EpisodeResult,
    Evaluation,
    RunConfig,
    add_param_option,
    evaluate,
    load_controller,
    load_episodes,
    parse_controller_params,
    random_episodes,
)
from policy.campaigns.parallel import CampaignError, evaluate_parallel
from protocol.models import ALPHA5, ArmModelName, model_named
from reach_driver.cli.tables import show_table
from reach_driver.controllers import registered_list
from reach_driver.errors import DriverError
from reach_driver.metrics import ALL_METRIC_KEYS, metric_label
from reach_sim_bridge.model.sensors import SensorNoise


@dataclass(frozen=True)
class Options:
    """The command line of `tools/evaluate.py` (its help says what each one does); one of
    `targets` and `random` gives the episodes."""

    controller: str
    out: Path
    param: Sequence[str] = ()
    targets: Path | None = None
    random: int | None = None
    seed: int = 0
    noise: bool = False
    perturb: float = 0.0
    params: Path | None = None
    seconds: float = DEFAULT_SECONDS
    rate: float = DEFAULT_RATE_HZ
    via_driver: bool = False
    sim_speed: float = 4.0
    baud: int | None = None
    record: Path | None = None
    workers: int | None = None
    address: str | None = None
    quiet: bool = False
    arm: str = ALPHA5.name


def record_evaluation(evaluation: Evaluation, path: Path) -> None:
    """Episodes one after another on the recording's time line, each announced as an event."""
    from reach_driver.recording import RunRecorder, StepSample

    meta = {"controller": evaluation.controller, "config": evaluation.config.to_dict()}
    with RunRecorder(path, metadata=meta) as rec:
        t0, step0 = 0.0, 0
        for i, r in enumerate(evaluation.results):
            rec.log_event(f"episode {i}: {r.episode.to_dict()}", t=t0, step=step0)
            times = r.trace.times
            for k in range(len(times)):
                rec.log_step(
                    StepSample(
                        t=t0 + float(times[k]),
                        step=step0 + k,
                        q=r.trace.q[k],
                        qdot=r.trace.qdot[k],
                        target=r.trace.target,
                        current_cmd_mA=r.currents_mA[k],
                        torque_Nm=r.trace.tau[k],
                    )
                )
            rec.log_event(
                f"episode {i} metrics: {json.dumps(r.metrics.as_dict())}",
                t=t0 + float(times[-1]),
                step=step0 + len(times) - 1,
            )
            t0 += float(times[-1]) + evaluation.config.period
            step0 += len(times)
        rec.log_summary(evaluation.summary())


def summary_table(evaluation: Evaluation) -> Table:
    table = Table(title=f"{evaluation.controller}: {len(evaluation.results)} episodes")
    table.add_column("#", justify="right")
    for key in ALL_METRIC_KEYS:
        table.add_column(escape(metric_label(key).replace(" [", "\n[")), justify="right")
    table.add_column(escape("rmse_floor\n[rad]"), justify="right")
    for i, r in enumerate(evaluation.results):
        m = r.metrics.as_dict()
        cells = [_fmt(m[k]) for k in ALL_METRIC_KEYS] + [_fmt(r.rmse_floor)]
        table.add_row(str(i), *cells)
    s = evaluation.summary()
    table.add_section()
    table.add_row(
        "mean", *[_fmt(s[k]) for k in ALL_METRIC_KEYS], _fmt(s["rmse_floor"]), style="bold"
    )
    return table


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "NO"
    return f"{float(v):.4g}"


def run(args: Options, console: Console) -> Evaluation:
    """The controller over the episodes, on the backend the options ask for."""
    model = model_named(args.arm)
    parallel = args.workers is not None or args.address is not None
    if model.name != ALPHA5.name and (args.via_driver or parallel):
        raise ValueError(
            f"--via-driver, --workers and --address run the Alpha 5 only; the {model.title} "
            "runs on the direct backend"
        )
    if args.via_driver:
        from policy.campaigns.via_driver import DriverConfig, evaluate_via_driver
    from reach_sim_bridge.model.arms import load_params  # the twins: MuJoCo

    if args.targets is not None:
        episodes: list[Episode] = load_episodes(args.targets, model)
    elif args.random is not None:
        episodes = random_episodes(args.random, args.seed, model=model)
    else:
        raise ValueError("give --targets FILE or --random N")
    config = RunConfig(
        seconds=args.seconds,
        rate_hz=args.rate,
        noise=SensorNoise() if args.noise else None,
        seed=args.seed,
        param_spread=args.perturb,
        params=None if args.params is None else load_params(args.params, model),
    )
    params = parse_controller_params(args.param)
    if parallel and args.via_driver:
        raise ValueError("--workers/--address run the direct backend; drop --via-driver")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {args.workers}")
    # Built here even for Ray, whose workers build their own: a bad name or parameter fails
    # before a cluster is started.
    controller = load_controller(args.controller, arm=model, **params)
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("{task.fields[last]}"),
        console=console,
        disable=args.quiet,
    ) as progress:
        task = progress.add_task(args.controller, total=len(episodes), last="")

        def done(i: int, r: EpisodeResult) -> None:
            mark = "reached" if r.metrics.reached else "NOT reached"
            if not r.metrics.at_rest:
                mark += " (not at rest)"
            progress.update(task, advance=1, last=f"#{i} rmse {r.metrics.rmse:.3f} {mark}")

        if parallel:
            evaluation = evaluate_parallel(
                args.controller,
                params,
                episodes,
                config,
                workers=args.workers,
                address=args.address,
                on_episode=done,
            )
        elif args.via_driver:
            evaluation = evaluate_via_driver(
                controller,
                episodes,
                config,
                name=args.controller,
                driver=DriverConfig(speed=args.sim_speed, baud=args.baud),
                on_episode=done,
            )
        else:
            evaluation = evaluate(
                controller, episodes, config, name=args.controller, on_episode=done
            )
    return evaluation


def execute(args: Options) -> int:
    """Run, write the JSON (and the recording); the exit code (2 with the reason on stderr
    for a clear error)."""
    console = Console(stderr=True, soft_wrap=True)
    try:
        evaluation = run(args, console)
    except (ValueError, DriverError, CampaignError) as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(evaluation.to_dict(), indent=1), encoding="utf-8")
    if args.record is not None:
        record_evaluation(evaluation, args.record)
    if not args.quiet:
        show_table(Console(), summary_table(evaluation))
        console.print(f"wrote {args.out}" + (f" and {args.record}" if args.record else ""))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="evaluate.py",
        description=(
            "Run a controller closed-loop on the MuJoCo Alpha 5 (another arm's twin with --arm) "
            "for a set of step episodes (start -> target, arm angles in rad, joint order E D C "
            "B on the Alpha 5) and write per-episode "
            "metrics and their means to JSON. The controller sees q and qdot (noisy with "
            "--noise) once per control period; its currents (mA) are held for the period."
        ),
        epilog="Metrics are defined in docs/metrics.md; results in docs/results.md.",
    )
    p.add_argument(
        "--controller",
        required=True,
        help=f"a registered controller: {registered_list()} (`reach-driver controllers` says "
        "what each is)",
    )
    add_param_option(p, "--param horizon=15")
    p.add_argument(
        "--arm",
        choices=[m.value for m in ArmModelName],
        default=ALPHA5.name,
        help="the arm whose twin runs the episodes (default alpha5); bravo7: episodes of six "
        "angles G F E D C B, --random draws in its workspace (docs/training.md), direct "
        "backend only",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--targets",
        type=Path,
        metavar="FILE",
        help='JSON list of {"start": [E,D,C,B], "target": [E,D,C,B], '
        '"torque_scale": [4 numbers, optional]} (six, G F E D C B, with --arm bravo7)',
    )
    src.add_argument(
        "--random",
        type=int,
        metavar="N",
        help="draw N starts and targets uniformly in the evaluation workspace "
        "E [0.4, 5.8], D [0.5, 2.9], C [0.5, 2.9], B [0.5, 2.8]",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed for --random episodes and for the sensor noise (default 0)",
    )
    p.add_argument(
        "--noise",
        action="store_true",
        help="add sensor noise to what the controller sees "
        "(sigma 0.002 rad on q, 0.02 rad/s on qdot)",
    )
    p.add_argument(
        "--perturb",
        type=float,
        default=0.0,
        metavar="SPREAD",
        help="randomly degrade each episode's arm: friction, armature, link masses "
        "and buoyancy each scaled by U(1-SPREAD, 1+SPREAD), e.g. 0.2 "
        "(default 0: the nominal arm)",
    )
    p.add_argument(
        "--params",
        type=Path,
        metavar="FILE.json",
        help="run every episode on the arm this parameter file describes (ArmParams "
        "field names, any subset, E D C B; as tools/identify.py writes); --perturb then "
        "spreads around it (default: the nominal arm)",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=DEFAULT_SECONDS,
        help=f"episode length in seconds (default {DEFAULT_SECONDS:g})",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=DEFAULT_RATE_HZ,
        metavar="HZ",
        help=f"control rate (default {DEFAULT_RATE_HZ:g} Hz, the env's default)",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="OUT.json",
        help="where to write the per-episode results and the summary",
    )
    p.add_argument(
        "--via-driver",
        action="store_true",
        help="run through the serial protocol (reach_driver -> virtual arm on a pty) "
        "instead of stepping the simulator directly; metrics still use the "
        "simulator's true angles (policy/campaigns/via_driver.py)",
    )
    p.add_argument(
        "--sim-speed",
        type=float,
        default=4.0,
        metavar="X",
        help="with --via-driver: simulator speed-up (default 4)",
    )
    p.add_argument(
        "--baud",
        type=int,
        metavar="BAUD",
        help="with --via-driver: throttle the pty like a serial line, e.g. 115200",
    )
    p.add_argument(
        "--record",
        type=Path,
        metavar="FILE.rrd",
        help="also write a Rerun recording of every episode",
    )
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run episodes in parallel on Ray with N CPUs on this machine (results are the "
        "serial run's: each episode's randomness depends on its seed only); needs the "
        "optional extra: pip install -e '.[scale]'",
    )
    p.add_argument(
        "--address",
        metavar="ADDR",
        help="run episodes on the Ray cluster at ADDR (e.g. ray://head:10001 or auto); "
        "its nodes need reach-stack installed",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar or table")
    return p


def main(argv: list[str] | None = None) -> int:
    """`tools/evaluate.py`'s command line: parse `argv` and run it."""
    return execute(Options(**vars(build_parser().parse_args(argv))))
