#!/usr/bin/env python3
"""Does an actor's reward prefer what we want? The actor and two controllers that arrive
without overshoot (`pid` on the noisy readings; `pd-expert`, privileged: the true state and
the episode's arm) run the same episodes in the actor's own env, each paid the actor's reward:

    .venv/bin/python tools/reward_audit.py runs/ddpg-s0/best_actor.npz --episodes 40

If a reference earns more than the actor, the reward already prefers its arrival and the
learner did not find it: the fix is in the inputs, the algorithm or the budget, not the
reward (policy/campaigns/reward_audit.py). Prints a markdown table: the mean discounted
return from the first state (what the actor maximises) with the actor's paired difference
and 95 % bootstrap interval, the undiscounted return, each term's sum, the overshoot.
Exit 2 on bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from policy.campaigns.reward_audit import audit, render  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]) if __doc__ else None,
    )
    parser.add_argument("actor", type=Path, help="a trained actor's weights file (.npz)")
    parser.add_argument("--episodes", type=int, default=40, help="episodes (default 40)")
    parser.add_argument(
        "--seed", type=int, default=40_000, help="first episode's seed (default: the held-out set)"
    )
    args = parser.parse_args(argv)
    if not args.actor.is_file():
        print(f"error: no weights file {args.actor}", file=sys.stderr)
        return 2
    if args.episodes < 2:
        print("error: --episodes must be at least 2", file=sys.stderr)
        return 2
    rows = render(audit(args.actor, args.episodes, args.seed))
    print("| " + " | ".join(rows[0]) + " |")
    print("|" + "---|" * len(rows[0]))
    for row in rows[1:]:
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
