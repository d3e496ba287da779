#!/usr/bin/env python3
"""Does a trained actor meet the Table I line? Each actor (the `ddpg` controller with that
weights file: the actor alone) runs Table I's 80 episodes (seeds 2020 2120 2220 2320: random
targets, sensor noise, arms within +-20 %) beside the MPC and the PID on the same episodes,
and every item of the line is checked (policy/campaigns/table1_line.py says which):

    .venv/bin/python tools/table1_line.py runs/ddpg-s0/best_actor.npz runs/ddpg-s1/best_actor.npz
    .venv/bin/python tools/table1_line.py shipped --json

Runs are kept in --runs and reused while the controller, the weights (by their bytes) and the
settings are unchanged: the MPC's 80 episodes take about 5 minutes once. Exit 0 when every
actor meets the line, 1 when one misses it, 2 on bad input. Needs the [sim,mpc] extras.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from policy.campaigns.table1_line import TABLE_SEEDS, line_checks, table_runs  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]) if __doc__ else None,
    )
    parser.add_argument(
        "actors", nargs="+", help="weights files (.npz), or 'shipped' for ddpg's own weights"
    )
    parser.add_argument(
        "--runs", type=Path, default=ROOT / "runs" / "table1-line", help="where runs are kept"
    )
    parser.add_argument("--json", action="store_true", help="print the checks as JSON")
    args = parser.parse_args(argv)
    for actor in args.actors:
        if actor != "shipped" and not Path(actor).is_file():
            print(f"error: no weights file {actor}", file=sys.stderr)
            return 2

    def progress(what: str) -> None:
        print(f"running {what} ...", file=sys.stderr, flush=True)

    mpc = table_runs("mpc", {}, args.runs, TABLE_SEEDS, progress)
    pid = table_runs("pid", {}, args.runs, TABLE_SEEDS, progress)
    report = {}
    for actor in args.actors:
        params = {} if actor == "shipped" else {"weights": str(Path(actor).resolve())}
        runs = table_runs("ddpg", params, args.runs, TABLE_SEEDS, progress)
        report[actor] = line_checks(runs, mpc, pid)
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
