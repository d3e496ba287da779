"""`reach-driver`: talk to a Reach Alpha 5 (or the virtual arm) from the command line.

`parser` holds the options and help, `commands` the subcommands, `render` how they print,
`report` and `recorder` what a run's summary becomes; `main` maps errors to exit statuses.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType

from rich.console import Console
from rich.markup import escape

from reach_driver.cli.commands import COMMANDS
from reach_driver.cli.connect import safety_config
from reach_driver.cli.exits import Exit, UsageError
from reach_driver.cli.parser import build_parser
from reach_driver.errors import (
    BadUrlError,
    DriverError,
    GarbageError,
    LimitError,
    LinkDownError,
    NoResponseError,
    PortNotFoundError,
    PortPermissionError,
    TransportError,
)

__all__ = ["Exit", "build_parser", "main"]


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if hasattr(args, "max_current"):
        try:
            safety_config(args)
        except ValueError as exc:
            parser.error(str(exc))  # exit 2 with the usage line
    # Piped output is not squeezed to 80 columns: tables stay one line per joint.
    console = Console(highlight=False, width=None if sys.stdout.isatty() else 160)
    errors = Console(stderr=True, highlight=False)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.ERROR,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    previous = signal.getsignal(signal.SIGTERM)
    if previous is signal.SIG_DFL and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_interrupt)  # terminate leaves the arm safe too
    try:
        return int(COMMANDS[args.command](args, console))
    except KeyboardInterrupt:
        errors.print("interrupted: arm left in a safe mode, link closed")
        return int(Exit.INTERRUPTED)
    except LimitError as exc:
        errors.print(f"[red]limit[/]: {escape(str(exc))}")
        return int(Exit.LIMIT)
    except UsageError as exc:
        errors.print(f"[red]error[/]: {escape(str(exc))}")
        return int(Exit.USAGE)
    except BadUrlError as exc:
        errors.print(f"[red]error[/]: {escape(str(exc))}")
        return int(Exit.USAGE)
    except (PortNotFoundError, PortPermissionError, GarbageError, NoResponseError) as exc:
        errors.print(f"[red]no arm[/]: {escape(str(exc))}")
        return int(Exit.NO_ARM)
    except TransportError as exc:
        errors.print(f"[red]no arm[/]: {escape(str(exc))}")
        return int(Exit.NO_ARM)
    except (LinkDownError, DriverError) as exc:
        errors.print(f"[red]failed[/]: {escape(str(exc))}")
        return int(Exit.FAILED)
    finally:
        if signal.getsignal(signal.SIGTERM) is _raise_interrupt:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
