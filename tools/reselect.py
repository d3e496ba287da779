#!/usr/bin/env python3
"""Reselect a training run's actor from every checkpoint it kept, on a validation set larger
than the run's own checkpoint sets, by a fixed rule (policy/campaigns/reselect.py):

    the most validation episodes reached at rest with overshoot under 2 % (the standard set's
    share plus the envelope's); ties to the most reached at rest, then the lower mean
    standard overshoot.

Validation episodes (seed 60000 and up by default) are apart from training's checkpoint sets
and from the ablation's test sets (40000 and up), so a reselected actor can be tested on those
as any other (tools/ablation.py, tools/table1_line.py). Each checkpoint's figures are cached
beside its actor; a second call only reads them.

    tools/reselect.py runs/ddpg-s0 runs/ddpg-s1          # score, print, write
    tools/reselect.py runs/avg-s0 --kind online-actor     # the online actors of an averaged run

Writes RUN/reselected_actor.npz (+ .json, the chosen checkpoint's actor) and
RUN/reselection.json (every checkpoint's figures and the choice) unless --dry-run.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from policy.campaigns.ablation import HeldOutSets
from policy.campaigns.parallel import CampaignError
from policy.campaigns.reselect import VALIDATION, Reselection, reselect, write
from policy.controllers.weights import CheckpointActor


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="reselect.py",
        description="Score every checkpoint actor a run kept on a validation set and pick one "
        "by a fixed rule (most episodes at rest under 2 % overshoot).",
        epilog="docs/ablation.md 'Reselecting on more episodes': what it brings, measured.",
    )
    p.add_argument("runs", nargs="+", type=Path, help="training run directories")
    p.add_argument(
        "--kind",
        choices=[kind.value for kind in CheckpointActor],
        default=CheckpointActor.KEPT.value,
        help="which checkpoint actors: the kept ones (actor, default) or, in a run with an "
        "averaged actor, the online ones",
    )
    VALIDATION.add_arguments(p, "validation", "--seed")
    p.add_argument(
        "--workers", type=int, help="score the checkpoints on a local Ray with this many CPUs"
    )
    p.add_argument("--address", help="score the checkpoints on the Ray cluster at this address")
    p.add_argument("--dry-run", action="store_true", help="print the choice, write nothing")
    p.add_argument("--json", type=Path, metavar="FILE", help="write every run's report here")
    return p


def _kept_steps(run: Path) -> int | None:
    """The env steps of the actor the run itself kept (best_actor.json), if any."""
    meta = run / "best_actor.json"
    if not meta.is_file():
        return None
    steps = json.loads(meta.read_text(encoding="utf-8")).get("env_steps")
    return int(steps) if steps is not None else None


def table(result: Reselection, kept: int | None) -> Table:
    out = Table(title=f"{result.run}: {result.kind.value} checkpoints on the validation set")
    heads = [
        *("env steps", "good std %", "good env %", "at rest std %", "at rest env %"),
        *("OS %", "MSSE mrad", "E J", ""),
    ]
    for head in heads:
        out.add_column(head, justify="right")
    for r in result.rows:
        marks = []
        if r is result.chosen:
            marks.append("reselected")
        if r.env_steps == kept:
            marks.append("run's own")
        out.add_row(
            f"{r.env_steps // 1000:,}k",
            f"{100 * r.standard_good:.1f}",
            f"{100 * r.envelope_good:.1f}",
            f"{100 * r.standard_reached:.1f}",
            f"{100 * r.envelope_reached:.1f}",
            f"{r.standard_overshoot_pct:.2f}",
            f"{1000 * r.standard_msse:.2f}",
            f"{r.standard_energy_j:.2f}",
            ", ".join(marks),
            style="bold" if r is result.chosen else None,
        )
    return out


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    out, err = Console(soft_wrap=True), Console(stderr=True, soft_wrap=True)
    if args.standard < 1 or args.envelope < 0:
        err.print("[red]error:[/red] --standard must be at least 1 and --envelope at least 0")
        return 2
    sets = HeldOutSets.from_args(args)
    reports = []
    for run in args.runs:
        try:
            result = reselect(
                run,
                CheckpointActor(args.kind),
                sets,
                lambda what: err.print(escape(what)),
                args.workers,
                args.address,
            )
        except (FileNotFoundError, ValueError, CampaignError) as exc:
            err.print(f"[red]error:[/red] {escape(str(exc))}")
            return 2
        out.print(table(result, _kept_steps(run)))
        chosen = result.chosen
        line = f"{escape(str(run))}: reselected the {args.kind} at {chosen.env_steps:,} env steps"
        if not args.dry_run:
            line += f" -> {escape(str(write(result)))}"
        out.print(line)
        reports.append(result.to_dict())
    if args.json is not None:
        args.json.write_text(json.dumps(reports, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
