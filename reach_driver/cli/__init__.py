"""`reach-driver`: talk to a Reach Alpha 5 (or the virtual arm) from the command line.

`parser` holds the options and help, `commands` the subcommands, `render` how they print,
`report` and `recorder` what a run's summary becomes; `main` maps errors to exit statuses.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from types import FrameType

from rich.console import Console
from rich.markup import escape

from protocol.viewer import viewer_options_problem
from reach_driver.cli.commands import COMMANDS
from reach_driver.cli.connect import safety_config
from reach_driver.cli.exits import Exit, UsageError, for_operator
from reach_driver.cli.parser import build_parser, package_version
from reach_driver.cli.recorder import output_path_problem
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

log = logging.getLogger("reach_driver.cli")


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def _configure_logging(args: argparse.Namespace) -> Callable[[], None]:
    """stderr gets errors (-v: info, -vv: debug); --log-file gets info (-vv: debug) whatever
    -q says. Returns what undoes it (main() may run many times in one process)."""
    verbose = int(args.verbose or 0)
    stderr_level = logging.DEBUG if verbose >= 2 else logging.INFO if verbose else logging.ERROR
    handlers: list[logging.Handler] = []
    stream = logging.StreamHandler(sys.stderr)
    stream.setLevel(stderr_level)
    stream.addFilter(lambda record: not record.name.startswith("reach_driver.cli"))  # shown
    handlers.append(stream)
    file_level = logging.DEBUG if verbose >= 2 else logging.INFO
    if args.log_file:
        to_file = logging.FileHandler(args.log_file, encoding="utf-8")
        to_file.setLevel(file_level)
        handlers.append(to_file)
    logger = logging.getLogger("reach_driver")
    old_level = logger.level
    levels = [stderr_level] + ([file_level] if args.log_file else [])
    logger.setLevel(min(levels))
    for handler in handlers:
        handler.setFormatter(logging.Formatter(LOG_FORMAT))
        logger.addHandler(handler)

    def undo() -> None:
        for handler in handlers:
            logger.removeHandler(handler)
            handler.close()
        logger.setLevel(old_level)

    return undo


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    viewer_problem = viewer_options_problem(args)
    if viewer_problem:
        parser.error(viewer_problem)
    if hasattr(args, "max_current"):
        try:
            safety_config(args)
        except ValueError as exc:
            parser.error(str(exc))  # exit 2 with the usage line
    # Piped output is not squeezed to 80 columns: tables stay one line per joint.
    console = Console(highlight=False, width=None if sys.stdout.isatty() else 160)
    errors = Console(stderr=True, highlight=False)
    if args.log_file:
        problem = output_path_problem(
            "--log-file", args.log_file, getattr(args, "port", None), devices=False
        )
        if problem:
            errors.print(f"[red]error[/]: {escape(problem)}; nothing was sent", soft_wrap=True)
            return int(Exit.USAGE)
    try:
        undo_logging = _configure_logging(args)
    except OSError as exc:
        errors.print(f"[red]error[/]: --log-file {escape(str(args.log_file))}: {escape(str(exc))}")
        return int(Exit.USAGE)
    previous = signal.getsignal(signal.SIGTERM)
    if previous is signal.SIG_DFL and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_interrupt)  # terminate leaves the arm safe too
    log.info(
        "reach-driver %s: %s", package_version(), " ".join(sys.argv[1:] if argv is None else argv)
    )
    code = int(Exit.FAILED)
    try:
        code = _run(args, console, errors)
        return code
    finally:
        log.info("exit %d", code)
        if signal.getsignal(signal.SIGTERM) is _raise_interrupt:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
        undo_logging()


def _say(errors: Console, label: str, message: str, style: str = "red") -> None:
    """One line on stderr, and the same in --log-file."""
    message = for_operator(message)
    log.error("%s: %s", label, message)
    shown = f"[{style}]{label}[/]" if style else label
    errors.print(f"{shown}: {escape(message)}", soft_wrap=True)


def _run(args: argparse.Namespace, console: Console, errors: Console) -> int:
    try:
        return int(COMMANDS[args.command](args, console))
    except KeyboardInterrupt:
        if args.command in ("move", "run"):
            _say(errors, "interrupted", "arm left in a safe mode, link closed", style="")
        else:
            _say(errors, "interrupted", "nothing was commanded, link closed", style="")
        return int(Exit.INTERRUPTED)
    except LimitError as exc:
        _say(errors, "limit", str(exc))
        return int(Exit.LIMIT)
    except UsageError as exc:
        _say(errors, "error", str(exc))
        return int(Exit.USAGE)
    except BadUrlError as exc:
        _say(errors, "error", str(exc))
        return int(Exit.USAGE)
    except (PortNotFoundError, PortPermissionError, GarbageError, NoResponseError) as exc:
        _say(errors, "no arm", str(exc))
        return int(Exit.NO_ARM)
    except TransportError as exc:
        _say(errors, "no arm", str(exc))
        return int(Exit.NO_ARM)
    except (LinkDownError, DriverError) as exc:
        _say(errors, "failed", str(exc))
        return int(Exit.FAILED)
