#!/usr/bin/env python3
"""Does a trained actor meet the Table I line? Each actor (the `ddpg` controller with that
weights file: the actor alone) runs Table I's 80 episodes (seeds 2020 2120 2220 2320: random
targets, sensor noise, arms within +-20 %) beside the MPC and the PID on the same episodes,
and every item of the line is checked (policy/campaigns/table1_line.py says which):

    .venv/bin/python tools/table1_line.py runs/ddpg-s0/best_actor.npz runs/ddpg-s1/best_actor.npz
    .venv/bin/python tools/table1_line.py shipped --json

With --table, or for another arm (--arm bravo7: its own set, the 20 episodes of seed 7020),
it prints instead Table I's metrics with 95 % bootstrap intervals, as markdown, for every
engineered controller that drives the arm (--controllers picks some) and the actors given,
each of which must have been trained for that arm:

    .venv/bin/python tools/table1_line.py --arm bravo7 runs/bravo/best_actor.npz

Runs are kept in --runs and reused while the arm, the controller, the weights (by their bytes)
and the settings are unchanged: the MPC's 80 episodes take about 5 minutes once. Exit 0 when
every actor meets the line (or the table is printed), 1 when one misses it, 2 on bad input.
Needs the [sim,mpc] extras.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from policy.campaigns.table1_line import (  # noqa: E402
    ARM_TABLE_SEEDS,
    line_checks,
    metrics_table,
    table_runs,
)
from policy.controllers.weights import LEARNED_WEIGHTS, ActorWeights  # noqa: E402
from protocol.models import ALPHA5, ArmModel, ArmModelName, model_named  # noqa: E402
from reach_driver.controllers import ControllerKind, controllers_for  # noqa: E402


def actor_problem(actor: str, model: ArmModel) -> str | None:
    """Why `actor` ('shipped' or a weights file) cannot run on `model`, or None."""
    path = LEARNED_WEIGHTS if actor == "shipped" else Path(actor)
    if not path.is_file():
        return f"no weights file {actor}"
    try:
        theirs = ActorWeights.load(path).model
    except (OSError, ValueError) as exc:
        return f"{actor}: {exc}"
    if theirs.name != model.name:
        return (
            f"{actor} holds an actor for the {theirs.title}, not the {model.title} "
            f"(give --arm {theirs.name})"
        )
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]) if __doc__ else None,
    )
    parser.add_argument(
        "actors", nargs="*", help="weights files (.npz), or 'shipped' for ddpg's own weights"
    )
    parser.add_argument(
        "--arm",
        choices=[m.value for m in ArmModelName],
        default=ALPHA5.name,
        help="the arm and its Table I set (default alpha5; another arm implies --table)",
    )
    parser.add_argument(
        "--table",
        action="store_true",
        help="print Table I's metrics with 95 %% intervals as markdown instead of the line",
    )
    parser.add_argument(
        "--controllers",
        metavar="A,B",
        help="with --table: these engineered controllers (default: every one that drives the arm)",
    )
    parser.add_argument(
        "--runs", type=Path, default=ROOT / "runs" / "table1-line", help="where runs are kept"
    )
    parser.add_argument("--json", action="store_true", help="print the line's checks as JSON")
    args = parser.parse_args(argv)
    model = model_named(args.arm)
    seeds = ARM_TABLE_SEEDS[model.name]
    table = args.table or model.name != ALPHA5.name
    for actor in args.actors:
        problem = actor_problem(actor, model)
        if problem:
            print(f"error: {problem}", file=sys.stderr)
            return 2
    if not table and not args.actors:
        print("error: give at least one actor to check against the line", file=sys.stderr)
        return 2
    misplaced = "--json" if table and args.json else None
    if not table and args.controllers is not None:
        misplaced = "--controllers"
    if misplaced:
        print(
            f"error: {misplaced} does not go with {'the table' if table else 'the line'}",
            file=sys.stderr,
        )
        return 2
    drive = controllers_for(model, ControllerKind.ENGINEERED)
    chosen = drive if args.controllers is None else args.controllers.split(",")
    wrong = [name for name in chosen if name not in drive]
    if wrong:
        print(
            f"error: {', '.join(wrong)} not among the engineered controllers of the "
            f"{model.title} here ({', '.join(drive)})",
            file=sys.stderr,
        )
        return 2

    def progress(what: str) -> None:
        print(f"running {what} ...", file=sys.stderr, flush=True)

    def actor_runs(actor: str) -> list[dict[str, object]]:
        params = {} if actor == "shipped" else {"weights": str(Path(actor).resolve())}
        return table_runs("ddpg", params, args.runs, seeds, progress, model)

    if table:
        rows = {name: table_runs(name, {}, args.runs, seeds, progress, model) for name in chosen}
        rows.update({actor: actor_runs(actor) for actor in args.actors})
        n = sum(len(run["episodes"]) for run in next(iter(rows.values())))
        print(
            f"Table I on the {model.title}: {n} episodes (seeds {' '.join(map(str, seeds))}); "
            "mean [95 % bootstrap interval]\n"
        )
        print("\n".join(metrics_table(rows)))
        return 0
    mpc = table_runs("mpc", {}, args.runs, seeds, progress)
    pid = table_runs("pid", {}, args.runs, seeds, progress)
    report = {actor: line_checks(actor_runs(actor), mpc, pid) for actor in args.actors}
    met = {actor: all(c.passed for c in checks) for actor, checks in report.items()}
    if args.json:
        out = {
            actor: {"met": met[actor], "checks": [c.__dict__ for c in checks]}
            for actor, checks in report.items()
        }
        print(json.dumps(out, indent=1))
    else:
        for actor, checks in report.items():
            passed = sum(c.passed for c in checks)
            print(
                f"{actor}: {'meets' if met[actor] else 'misses'} the Table I line "
                f"({passed} of {len(checks)} items)"
            )
            for c in checks:
                print(f"  {'pass' if c.passed else 'MISS'}  {c.item}: {c.figure}")
        print(f"{sum(met.values())} of {len(met)} actors meet the line")
    return 0 if all(met.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
