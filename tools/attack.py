"""Attack the stack as an adversarial tester would, and print what held.

    .venv/bin/python tools/attack.py                 # every attack, about a minute
    .venv/bin/python tools/attack.py --only codec-fuzz udp-stranger --scale 0.2
    .venv/bin/python tools/attack.py --json out/attacks.json

Each attack is bounded in count and time and stops by itself; all traffic stays on loopback
(a virtual arm in this process, on a pty and 127.0.0.1). The table it prints (attack, count,
result, held) is the one in docs/reliability.md. Exit status 1 when any attack got through.
The same properties are asserted by the test suite (tests/test_sim_hostile.py,
tests/test_protocol_properties.py, tests/test_driver_sim.py ...); this script is for rerunning
the attacks at a larger scale and reading the figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

from policy.campaigns.attacks import ATTACKS


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Attack the driver and the virtual arm (loopback only, bounded) and print "
        "what held.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="attacks: " + ", ".join(ATTACKS),
    )
    parser.add_argument("--only", nargs="+", choices=sorted(ATTACKS), metavar="ATTACK")
    parser.add_argument(
        "--scale", type=float, default=1.0, help="multiply every count (default 1.0)"
    )
    parser.add_argument("--json", type=Path, help="also write the outcomes as JSON")
    args = parser.parse_args(argv)
    if not (math.isfinite(args.scale) and 0.0 < args.scale <= 10.0):
        parser.error(f"--scale must be in (0, 10], got {args.scale}")
    outcomes = []
    with tempfile.TemporaryDirectory(prefix="attack-") as tmp:
        for name in args.only or ATTACKS:
            print(f"... {name}", file=sys.stderr, flush=True)
            outcomes.append(ATTACKS[name](args.scale, tmp))
    print("| attack | count | result | held |")
    print("|---|---|---|---|")
    for o in outcomes:
        print(f"| {o.attack} | {o.count} | {o.result} | {'yes' if o.held else 'NO'} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps([asdict(o) for o in outcomes], indent=1))
    return 0 if all(o.held for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
