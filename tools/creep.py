"""How fast the twin's joints creep under a torque their Coulomb friction should hold.

MuJoCo's ``frictionloss`` is a soft constraint: below breakaway it acts as a stiff viscous
damper rather than a lock, so a joint pushed at a fraction of its friction slides at a speed
proportional to the push. A real gearbox holds. This script measures the slide
(reach_sim_bridge.model.creep): each joint in turn (the arm held still against gravity and
buoyancy, the others' commands their holds) gets its hold plus a fraction of its friction, and
the mean speed over 4 s after a 1 s transient is printed with the damping it implies (push /
speed). docs/robustness.md, "The twin's friction creeps", uses the figures.

    .venv/bin/python tools/creep.py                # E D C at 0.7, 1.9 and 6.6 N m
    .venv/bin/python tools/creep.py --friction 3.3 --fractions 0.5
    .venv/bin/python tools/creep.py --holds        # ArmParams(friction_holds=True): it holds
"""

from __future__ import annotations

import argparse

from protocol.alpha5 import JOINT_LETTERS
from reach_sim_bridge.model.creep import creep_speed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--friction",
        type=float,
        nargs="+",
        default=[0.7, 1.9, 6.6],
        help="Coulomb friction on E D C (N m; the envelope spans 0-6.6)",
    )
    parser.add_argument(
        "--fractions",
        type=float,
        nargs="+",
        default=[0.1, 0.5, 0.9],
        help="the push, as fractions of the friction (below 1: a real joint holds)",
    )
    parser.add_argument(
        "--holds",
        action="store_true",
        help="with ArmParams.friction_holds (MuJoCo's no-slip solver): the friction holds",
    )
    args = parser.parse_args(argv)
    if any(f <= 0 for f in args.friction) or any(not 0 < x < 1 for x in args.fractions):
        parser.error("friction must be > 0 and fractions in (0, 1)")
    print("joint  friction [N m]  push [N m]  creep [mrad/s]  push/speed [N m s/rad]")
    for joint in range(3):
        for friction in args.friction:
            for fraction in args.fractions:
                push = fraction * friction
                v = creep_speed(friction, joint, fraction, args.holds)
                damping = push / v if abs(v) > 1e-6 else float("inf")
                print(
                    f"{JOINT_LETTERS[joint]:>5}  {friction:14.2f}  {push:10.2f}  "
                    f"{v * 1000:14.2f}  {damping:22.0f}"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
