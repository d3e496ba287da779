"""`python -m reach_driver`, the same as the `reach-driver` script."""

import sys

from reach_driver.cli import main

sys.exit(main())
