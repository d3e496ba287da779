"""What `tools/robustness.py` does with its options: run controllers over the planned arms
(or export or identify the arms, or reload saved results), print their summaries and write
their docs blocks. `Options` holds the command line's values, one field per option."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from policy.campaigns.evaluation import add_param_option, parse_controller_params
from policy.campaigns.parallel import CampaignError
from policy.campaigns.robustness.arms import Plan, export_arms, plan, read_fitted
from policy.campaigns.robustness.campaign import campaign
from policy.campaigns.robustness.identification import (
    identify_arms,
    identify_table,
    verdict_table,
)
from policy.campaigns.robustness.progress import ProgressLog
from policy.campaigns.robustness.report import (
    COMPARISON,
    DOC,
    NEW_BLOCKS,
    TABLES_DOC,
    begin_marker,
    comparison_block,
    end_marker,
    markdown_block,
    overshoot_by_table,
    print_summary,
    update_doc,
)
from policy.campaigns.robustness.summary import check_factors, overshoot_by, summaries
from reach_driver.controllers import registered_list
from reach_driver.errors import DriverError
from reach_sim_bridge.model.params import ArmParams, load_arm_params


@dataclass(frozen=True)
class Options:
    """The command line of `tools/robustness.py` (its help says what each one does)."""

    controller: Sequence[str] | None = None
    label: str | None = None
    param: Sequence[str] = ()
    corners: bool = False
    max_corners: int | None = None
    draws: int | None = None
    params: Path | str | None = None
    twin: bool = False
    twin_error: float = 0.0
    twin_from: Path | None = None
    export_arms: Path | None = None
    identify: Path | None = None
    identify_args: str = "--max-current 600 --watchdog 1.0"
    sim_speed: float = 1.0
    identify_virtual: bool = False
    seed: int = 1
    seconds: float = 20.0
    rate: float = 20.0
    out: Path = field(default_factory=lambda: Path("runs/robustness"))
    workers: int | None = None
    address: str | None = None
    from_files: Sequence[Path] | None = None
    write_docs: bool = False
    force: bool = False
    overshoot_by: Sequence[str] | None = None
    doc: Path | None = None  # None: docs/robustness.md and its tables page
    quiet: bool = False


def read_reports(paths: Sequence[Path]) -> list[dict[str, Any]]:
    """Saved results, each summarised afresh (this version's summary)."""
    reports = []
    for path in paths:
        try:
            report = json.loads(path.read_text(encoding="utf-8"))
            report["summary"] = summaries(report["episodes"])
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise ValueError(f"cannot read {path} as a robustness.py result: {exc}") from exc
        reports.append(report)
    return reports


def _plan_of(opts: Options) -> Plan:
    base = None if opts.params is None else load_arm_params(opts.params)
    return plan(opts.seed, opts.corners, opts.draws, opts.max_corners, base=base)


def identify(opts: Options, console: Console) -> None:
    """`--identify DIR`: the planned arms identified into DIR, their table printed."""
    assert opts.identify is not None
    if opts.controller:
        raise ValueError(
            "--identify runs no controller: identify first, then run --controller "
            "lambda --twin --twin-from DIR on the same arms"
        )
    if opts.sim_speed <= 0:
        raise ValueError(f"--sim-speed must be positive, got {opts.sim_speed}")
    rows = identify_arms(
        _plan_of(opts).arms,
        opts.identify,
        opts.seed,
        console,
        speed=opts.sim_speed,
        identify_args=shlex.split(opts.identify_args),
        virtual=opts.identify_virtual,
        workers=opts.workers,
        address=opts.address,
    )
    Console().print(escape(identify_table(rows)), soft_wrap=True)
    Console().print(escape("\n" + verdict_table(rows)), soft_wrap=True)
    failed = [r["arm"] for r in rows if "joints" not in r]
    if failed:
        raise ValueError(f"{len(failed)} arms not identified: {', '.join(failed)}")


def check(opts: Options) -> None:
    """A clear error for options that do not make a campaign."""
    if not opts.controller:
        raise ValueError("give --controller NAME ... (or --from FILE.json to report saved runs)")
    if opts.label and len(opts.controller) > 1:
        raise ValueError("--label names one controller's results; give one --controller")
    if opts.draws is not None and opts.draws < 1:
        raise ValueError(f"--draws must be at least 1, got {opts.draws}")
    if opts.max_corners is not None and not opts.corners:
        raise ValueError("--max-corners needs --corners")
    if opts.twin_error and not opts.twin:
        raise ValueError("--twin-error needs --twin")
    if not 0 <= opts.twin_error < 1:
        raise ValueError(f"--twin-error must be in [0, 1), got {opts.twin_error}")
    if opts.twin_from is not None and not opts.twin:
        raise ValueError("--twin-from needs --twin")


def settings_of(opts: Options, base: ArmParams | None, fitted: bool) -> dict[str, Any]:
    """What decides a campaign's numbers, recorded in its docs block."""
    settings: dict[str, Any] = {
        "seed": opts.seed,
        "corners": opts.corners,
        "max_corners": opts.max_corners,
        "draws": opts.draws,
        "seconds": opts.seconds,
        "rate_hz": opts.rate,
    }
    if opts.twin:  # only when given, so old blocks still match
        settings["twin_error"] = opts.twin_error
    if fitted:
        assert opts.twin_from is not None
        settings["twin_from"] = opts.twin_from.name
    if base is not None:  # only what differs from the nominal arm, so old blocks still match
        nominal = ArmParams().to_json_dict()
        settings["params"] = {k: v for k, v in base.to_json_dict().items() if v != nominal[k]}
    return settings


def run(opts: Options, command: str, console: Console) -> list[dict]:
    """The reports of this command: saved ones (`--from`), none (`--export-arms`,
    `--identify`) or one per controller run, each also written to OUT/LABEL.json."""
    if opts.workers is not None and opts.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {opts.workers}")
    if opts.overshoot_by:
        check_factors(opts.overshoot_by)  # a misspelt factor fails before a campaign runs
    if opts.from_files:
        return read_reports(opts.from_files)
    if opts.export_arms is not None:
        paths = export_arms(_plan_of(opts).arms, opts.export_arms, opts.seed)
        console.print(f"wrote {len(paths)} arm files to {opts.export_arms}")
        return []
    if opts.identify is not None:
        identify(opts, console)
        return []
    check(opts)
    assert opts.controller
    params = parse_controller_params(opts.param)
    base = None if opts.params is None else load_arm_params(opts.params)
    the_plan = plan(opts.seed, opts.corners, opts.draws, opts.max_corners, base=base)
    fitted = None
    if opts.twin_from is not None:
        fitted = read_fitted(opts.twin_from, the_plan.arms)
        the_plan = replace(the_plan, arms=[a for a in the_plan.arms if (a.set, a.index) in fitted])
        console.print(f"{len(fitted)} fitted twins in {opts.twin_from}")
    settings = settings_of(opts, base, fitted is not None)
    reports = []
    for name in opts.controller:
        label = opts.label or name
        with ProgressLog(label, len(the_plan.arms), console, opts.quiet) as progress:
            report = campaign(
                name,
                label,
                params,
                the_plan,
                opts.seed,
                settings=settings,
                command=command,
                workers=opts.workers,
                address=opts.address,
                seconds=opts.seconds,
                rate_hz=opts.rate,
                progress=progress.done,
                twin_error=opts.twin_error if opts.twin else None,
                fitted=fitted,
            )
        opts.out.mkdir(parents=True, exist_ok=True)
        path = opts.out / f"{label}.json"
        path.write_text(json.dumps(report, indent=1), encoding="utf-8")
        console.print(f"wrote {path}")
        reports.append(report)
    return reports


def write_docs(docs: Sequence[Path], reports: Sequence[dict[str, Any]], force: bool) -> list[Path]:
    """Each report's block, in whichever of ``docs`` holds it (a new one where the new-blocks
    marker is), and the comparison, when a doc has one and there are several reports. Returns
    the files written."""
    texts = {doc: doc.read_text(encoding="utf-8") for doc in docs}

    def holder(label: str) -> Path:
        for doc, text in texts.items():
            if begin_marker(label) in text and end_marker(label) in text:
                return doc
        return next((doc for doc, text in texts.items() if NEW_BLOCKS in text), docs[0])

    changed: set[Path] = set()
    for report in reports:
        doc = holder(report["label"])
        block = markdown_block(report)
        texts[doc] = update_doc(texts[doc], block, report["label"], report["settings"], force)
        changed.add(doc)
    for doc, text in texts.items():
        if len(reports) > 1 and begin_marker(COMPARISON) in text:
            texts[doc] = update_doc(text, comparison_block(reports), COMPARISON)
            changed.add(doc)
    written = [doc for doc in docs if doc in changed]
    for doc in written:
        doc.write_text(texts[doc], encoding="utf-8")
    return written


def execute(opts: Options, command: str) -> int:
    """Run the command; its exit code (2 with the reason on stderr for a clear error)."""
    console = Console(stderr=True, soft_wrap=True)
    try:
        reports = run(opts, command, console)
        out = Console()
        for report in reports:
            print_summary(report, out)
            if opts.overshoot_by:
                for set_name in report["summary"]:
                    rows = [r for r in report["episodes"] if r["set"] == set_name]
                    out.print(f"\n{escape(report['label'])} {set_name}, overshoot by level:")
                    table = overshoot_by_table(overshoot_by(rows, opts.overshoot_by))
                    out.print(escape(table), soft_wrap=True)
        if opts.write_docs:
            docs = (opts.doc,) if opts.doc is not None else (DOC, TABLES_DOC)
            for path in write_docs(docs, reports, opts.force):
                console.print(f"wrote {path}")
    except (ValueError, DriverError, CampaignError, OSError) as exc:
        console.print(f"[red]error:[/red] {escape(str(exc))}")
        return 2
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="robustness.py",
        description="Run controllers over the uncertainty envelope (policy/tasks/envelope.py): one "
        "episode (sensor noise on, scaled per arm) on each feasible corner and/or N random "
        "arms; write per-episode results and print reached, at rest, overshoot, settling "
        "and energy with 95 % bootstrap intervals, the worst arms and failures by factor.",
        epilog="The envelope and the results: docs/robustness.md.",
    )
    p.add_argument(
        "--controller",
        nargs="+",
        metavar="NAME",
        help=f"one or more registered controllers: {registered_list()}",
    )
    p.add_argument(
        "--label",
        help="name for the results and the docs block (default: the controller's name; "
        "one controller only), e.g. robust for --param weights=FILE",
    )
    add_param_option(p, "--param weights=runs/robust/actor.npz (every controller's)")
    p.add_argument("--corners", action="store_true", help="run the envelope's feasible corners")
    p.add_argument(
        "--max-corners",
        type=int,
        metavar="K",
        help="only K corners, chosen by a permutation seeded by --seed (for slow controllers)",
    )
    p.add_argument("--draws", type=int, metavar="N", help="run N feasible random arms")
    p.add_argument(
        "--params",
        metavar="FILE.json",
        help="the arm the envelope spreads around: ArmParams fields, the rest nominal (as in "
        'tools/evaluate.py), e.g. {"friction_holds": true} for friction that holds',
    )
    p.add_argument(
        "--twin",
        action="store_true",
        help="give the controller each arm's twin, its parameters and loop latency, as an "
        "identification (tools/identify.py) would: for controllers that take params= and "
        "latency_periods= (lambda)",
    )
    p.add_argument(
        "--twin-error",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="with --twin: scale each twin's friction, damping, armature, masses and volumes "
        "by independent factors in 1 +- FRACTION, seeded per arm (default 0: exact)",
    )
    p.add_argument(
        "--twin-from",
        type=Path,
        metavar="DIR",
        help="with --twin: each arm's twin from DIR/SET-INDEX.json (an identification's fit, "
        "tools/identify.py), only the arms that have one; --twin-error is then only how far "
        "the controller is told to trust it",
    )
    p.add_argument(
        "--export-arms",
        type=Path,
        metavar="DIR",
        help="do not run: write each planned arm as DIR/SET-INDEX.json, a reach-sim --params "
        "file (its sensor noise and latency under _envelope), to identify it",
    )
    p.add_argument(
        "--identify",
        type=Path,
        metavar="DIR",
        help="do not run controllers: identify each planned arm through the driver (reach-sim "
        "serving it on a pty, tools/identify.py exciting and fitting it; about 12 min of one "
        "CPU each) into DIR/SET-INDEX.json, the fits --twin-from DIR reads; --workers and "
        "--address run arms in parallel; arms already in DIR are skipped",
    )
    p.add_argument(
        "--identify-args",
        default="--max-current 600 --watchdog 1.0",
        metavar="ARGS",
        help="with --identify: options for tools/identify.py (default: '--max-current 600 "
        "--watchdog 1.0', the envelope's weak drives need the current, a loaded host the "
        "watchdog's slack)",
    )
    p.add_argument(
        "--sim-speed",
        type=float,
        default=1.0,
        metavar="X",
        help="with --identify: reach-sim --speed (default 1: host stalls stay out of the data)",
    )
    p.add_argument(
        "--identify-virtual",
        action="store_true",
        help="with --identify: excite each arm in the identification's own process "
        "(tools/identify.py --virtual: no reach-sim, no driver, no link), a few minutes of one "
        "CPU per arm: what the data can tell apart (docs/identification.md)",
    )
    p.add_argument("--seed", type=int, default=1, help="seed of the draws and episodes (1)")
    p.add_argument("--seconds", type=float, default=20.0, help="episode length (20 s)")
    p.add_argument("--rate", type=float, default=20.0, metavar="HZ", help="control rate (20)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("runs/robustness"),
        metavar="DIR",
        help="where LABEL.json goes (default runs/robustness)",
    )
    p.add_argument(
        "--workers", type=int, metavar="N", help="run on Ray with N CPUs on this machine"
    )
    p.add_argument("--address", metavar="ADDR", help="run on the Ray cluster at ADDR")
    p.add_argument(
        "--from",
        dest="from_files",
        nargs="+",
        type=Path,
        metavar="FILE.json",
        help="do not run: report (and with --write-docs, write) saved results",
    )
    p.add_argument(
        "--write-docs",
        action="store_true",
        help="regenerate each label's block in docs/robustness.md or docs/robustness-tables.md",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="with --write-docs: replace a block made with other settings",
    )
    p.add_argument(
        "--overshoot-by",
        nargs="+",
        metavar="FACTOR",
        help="also print the overshoot grouped by these factors' levels (low / high half of "
        "each range; the weak joint by letter), e.g. latency_periods coulomb_edc",
    )
    p.add_argument("--doc", type=Path, default=None, help=argparse.SUPPRESS)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    """`tools/robustness.py`'s command line: parse `argv` and run it (the command is recorded)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return execute(Options(**vars(args)), command="tools/robustness.py " + " ".join(argv))
