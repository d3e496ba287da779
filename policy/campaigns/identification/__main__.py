"""`python -m policy.campaigns.identification`: `tools/identify.py` from the package."""

import sys

from policy.campaigns.identification.cli import main

sys.exit(main())
