#!/usr/bin/env python3
"""Identify an Alpha 5 (virtual or real) through the driver and fit the twin to it.

    reach-sim --link /tmp/alpha5 --speed 4 &
    tools/identify.py --port /tmp/alpha5 --out arm.json            # excite, record, fit, report
    tools/identify.py --fit-only arm.log.npz --out arm.json        # refit a recorded log
    reach-sim --params arm.json ...                                # serve the fitted twin

The excitation, the fit and the report are `policy.campaigns.identification`'s; its `cli`
holds the options (`tools/identify.py --help`) and describes the method, and
`python -m policy.campaigns.identification` is the same command from the installed package.
Method: docs/identification.md.
"""

from __future__ import annotations

import sys

from policy.campaigns.identification.cli import build_parser, main

__all__ = ["build_parser", "main"]

if __name__ == "__main__":
    sys.exit(main())
