#!/usr/bin/env python3
"""Write reach_driver/arm_geometry.py from the link geoms of reach_sim_bridge/model/alpha5.xml,
and reach_driver/bravo7_drawing.py from the chain and geoms of reach_sim_bridge/model/bravo7.xml.

The driver draws the arm in its recordings without importing the simulator, so it carries the
geoms itself, as data generated here: each geom's shape, size and pose in its link's frame (the
frames of reach_driver.kinematics.CHAIN), as MuJoCo compiles them (fromto -> centre, rotation,
half-length). The jaw's fingers are put in the wrist frame (m1) with the jaw at its default
opening. tests/test_recording_views.py checks that the files match the MJCFs.

    python tools/gen_arm_geometry.py            # rewrite the modules
    python tools/gen_arm_geometry.py --check    # exit 1 if one is out of date
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from reach_sim_bridge.model.geometry import extract, extract_bravo7, render, render_bravo7

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "reach_driver" / "arm_geometry.py"
OUT_BRAVO7 = ROOT / "reach_driver" / "bravo7_drawing.py"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--check", action="store_true", help="exit 1 if a module is out of date")
    args = p.parse_args()
    texts = {OUT: render(extract()), OUT_BRAVO7: render_bravo7(*extract_bravo7())}
    if args.check:
        stale = [out for out, text in texts.items() if not out.exists() or out.read_text() != text]
        for out in stale:
            print(f"{out} is out of date: run tools/gen_arm_geometry.py", file=sys.stderr)
        return 1 if stale else 0
    for out, text in texts.items():
        out.write_text(text)
        print(f"wrote {out} ({text.count('LinkGeom(') - 1} geoms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
