#!/usr/bin/env python3
"""Score an ablation: every ROOT/INGREDIENT/seed-N/best_actor.npz on the same held-out test
episodes, and a table of what each ingredient brings, with seed-then-episode bootstrap
intervals and the change against the recipe (ROOT/baseline).

Train the runs first, one seed sweep per ingredient (docs/ablation.md):
    tools/sweep.py --config scratch --ablate no-away --seeds 0 1 2 --steps 200000 \\
        --set eps_steps=80000 --out runs/ablation/no-away
then:
    tools/ablation.py runs/ablation                       # print the table
    tools/ablation.py runs/ablation --markdown table.md   # and write it
    tools/ablation.py --list                              # the ingredients and their overrides
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from policy.campaigns.ablation import INGREDIENTS, HeldOutSets, markdown, score_root, summarize


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ablation.py",
        description="Score every ROOT/INGREDIENT/seed-N/best_actor.npz on held-out test "
        "episodes and print what each ingredient brings against ROOT/baseline.",
        epilog="docs/ablation.md: every table, what it says and its commands.",
    )
    p.add_argument("root", type=Path, nargs="?", help="the ablation's directory")
    p.add_argument("--list", action="store_true", help="list the ingredients and exit")
    HeldOutSets().add_arguments(p, "test", "--test-seed")
    p.add_argument("--markdown", type=Path, metavar="FILE", help="write the table here too")
    p.add_argument("--json", type=Path, metavar="FILE", help="write the summary here too")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    out, err = Console(soft_wrap=True), Console(stderr=True, soft_wrap=True)
    if args.list:
        for item in INGREDIENTS:
            flags = " ".join(f"--set {o}" for o in item.overrides) or "(none)"
            out.print(f"{item.name:12} {escape(item.summary)}\n{'':12} {escape(flags)}")
        return 0
    if args.root is None:
        err.print("[red]error:[/red] give the ablation's directory (or --list)")
        return 2
    if not args.root.is_dir():
        err.print(f"[red]error:[/red] no directory {escape(str(args.root))}")
        return 2
    if args.standard < 1 or args.envelope < 1:
        err.print("[red]error:[/red] --standard and --envelope must be at least 1")
        return 2
    sets = HeldOutSets.from_args(args)
    scores = score_root(args.root, sets, lambda what: err.print(f"scoring {escape(what)}"))
    if not scores:
        err.print(
            f"[red]error:[/red] no INGREDIENT/seed-N/best_actor.npz under {escape(str(args.root))}"
        )
        return 2
    summary = summarize(scores)
    table = markdown(summary)
    out.print(table, markup=False, highlight=False)
    if args.markdown is not None:
        args.markdown.write_text(table, encoding="utf-8")
    if args.json is not None:
        data = {
            "sets": sets.to_dict(),
            "ingredients": {
                name: {
                    "seeds": row["seeds"],
                    "figures": {k: vars(f) for k, f in row["figures"].items()},
                }
                for name, row in summary.items()
            },
        }
        args.json.write_text(json.dumps(data, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
