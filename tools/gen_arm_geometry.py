#!/usr/bin/env python3
"""Write reach_driver/arm_geometry.py from the link geoms of reach_sim_bridge/model/alpha5.xml.

The driver draws the arm in its recordings without importing the simulator, so it carries the
geoms itself, as data generated here: each geom's shape, size and pose in its link's frame (the
frames of reach_driver.kinematics.CHAIN), as MuJoCo compiles them (fromto -> centre, rotation,
half-length). The jaw's fingers are put in the wrist frame (m1) with the jaw at its default
opening. tests/test_recording_views.py checks that the file matches the MJCF.

    python tools/gen_arm_geometry.py            # rewrite the module
    python tools/gen_arm_geometry.py --check    # exit 1 if it is out of date
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from reach_sim_bridge.model.geometry import extract, render

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "reach_driver" / "arm_geometry.py"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--check", action="store_true", help="exit 1 if the module is out of date")
    args = p.parse_args()
    text = render(extract())
    if args.check:
        current = OUT.read_text() if OUT.exists() else ""
        if current != text:
            print(f"{OUT} is out of date: run tools/gen_arm_geometry.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    print(f"wrote {OUT} ({text.count('LinkGeom(') - 1} geoms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
