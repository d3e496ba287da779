"""`reach-driver`: talk to a Reach Alpha 5 or Bravo 7 (or a virtual one) from the command line.

`parser` holds the options and help, `commands` the subcommands, `render` how they print,
`report` and `recorder` what a run's summary becomes; `main` maps errors to exit statuses.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from types import FrameType
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.markup import escape

from protocol.viewer import viewer_options_problem
from reach_driver.cli.commands import COMMANDS
from reach_driver.cli.connect import safety_config
from reach_driver.cli.exits import Exit, UsageError, for_operator, left_in_for_operator
from reach_driver.cli.parser import build_parser, package_version
from reach_driver.cli.recorder import output_path_problem
from reach_driver.errors import (
    ArmModelError,
    BadUrlError,
    DriverError,
    ExtraNotInstalledError,
    GarbageError,
    Interrupted,
    LimitError,
    LinkDownError,
    NoResponseError,
    PortNotFoundError,
    PortPermissionError,
    RealtimeRefusedError,
    TransportError,
)

if TYPE_CHECKING:
    from reach_driver.recording import RunRecorder

__all__ = ["Exit", "build_parser", "main"]

log = logging.getLogger("reach_driver.cli")


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
    # Piped output is never wrapped or cut: a line stays one line, a table is plain aligned
    # text (reach_driver.cli.tables).
    console = Console(highlight=False, soft_wrap=not sys.stdout.isatty())
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
    signals = Signals()
    args.signals = signals  # move and run take the signals over while they command the arm
    args.kept_viewers = []  # --viewer-keep: live viewers left serving when the command is done
    signals.install()
    log.info(
        "reach-driver %s: %s", package_version(), " ".join(sys.argv[1:] if argv is None else argv)
    )
    code = int(Exit.FAILED)
    try:
        code = _run(args, console, errors)
        if signals.first is not None and args.command in ("move", "run"):
            code = Exit.for_signal(signals.first)  # also one that came while it reported
        _serve_on(args.kept_viewers, errors, signals)
        return code
    finally:
        for kept in args.kept_viewers:
            kept.close_viewer()
        log.info("exit %d", code)
        signals.restore()
        undo_logging()


#: A signal that ended the command this way leaves no one to stop --viewer-keep's serving
#: (the terminal went away) or asked for the process to end: the viewer is closed at once.
_NO_KEEP_AFTER = (signal.SIGHUP, signal.SIGTERM, signal.SIGQUIT)


def _serve_on(kept: Sequence[RunRecorder], errors: Console, signals: Signals) -> None:
    """`--viewer-keep`: the command is done (the arm left safe, everything printed, the port
    closed); its live viewers go on serving until a signal (Ctrl-C), which changes nothing
    of the exit status, or until they fail (the recorder has said so)."""
    live = [rec for rec in kept if rec.viewing and rec.viewer is not None]
    if not live or signals.first in _NO_KEEP_AFTER:
        return
    where = ", ".join(rec.viewer.web_url for rec in live if rec.viewer is not None)
    stop = threading.Event()
    try:
        with signals.rerouted(stop.set):
            sys.stdout.flush()  # the summary is out, even into a pipe, before the wait
            errors.print(
                f"viewer: done; still serving it at {escape(where)} (Ctrl-C to stop)",
                soft_wrap=True,
            )
            log.info("--viewer-keep: serving at %s until a signal", where)
            while not stop.wait(0.25) and any(rec.viewing for rec in live):
                pass
    except KeyboardInterrupt:  # one that came before the handlers were rerouted
        pass
    log.info("--viewer-keep: stopped serving")


def _say(errors: Console, label: str, message: str, style: str = "red") -> None:
    """One line on stderr, and the same in --log-file."""
    message = for_operator(message)
    log.error("%s: %s", label, message)
    shown = f"[{style}]{label}[/]" if style else label
    errors.print(f"{shown}: {escape(message)}", soft_wrap=True)


def _run(args: argparse.Namespace, console: Console, errors: Console) -> int:
    try:
        return int(COMMANDS[args.command](args, console))
    except KeyboardInterrupt as exc:
        stop = exc if isinstance(exc, Interrupted) else Interrupted()
        how = (
            f"arm left in {left_in_for_operator(stop.left_in, args.port)}"
            if stop.left_in
            else "nothing was commanded, link closed"
        )
        _say(errors, "interrupted", f"by {stop.signal_name}; {how}", style="")
        return Exit.for_signal(stop.signum)
    except LimitError as exc:
        _say(errors, "limit", str(exc))
        return int(Exit.LIMIT)
    except UsageError as exc:
        _say(errors, "error", str(exc))
        return int(Exit.USAGE)
    except BadUrlError as exc:
        _say(errors, "error", str(exc))
        return int(Exit.USAGE)
    except ExtraNotInstalledError as exc:  # e.g. --controller mpc without CasADi
        _say(errors, "error", str(exc))
        return int(Exit.USAGE)
    except ArmModelError as exc:  # --arm names another model than the one answering
        _say(errors, "wrong arm", str(exc))
        return int(Exit.NO_ARM)
    except (PortNotFoundError, PortPermissionError, GarbageError, NoResponseError) as exc:
        _say(errors, "no arm", str(exc))
        return int(Exit.NO_ARM)
    except TransportError as exc:
        _say(errors, "no arm", str(exc))
        return int(Exit.NO_ARM)
    except RealtimeRefusedError as exc:  # run --realtime require, not granted
        _say(errors, "refused", str(exc))
        return int(Exit.NO_REALTIME)
    except (LinkDownError, DriverError) as exc:
        _say(errors, "failed", str(exc))
        return int(Exit.FAILED)
    except OSError as exc:
        if args.signals.first is None:
            raise
        # After SIGHUP the terminal may be gone: the arm was seen to first, only output failed.
        log.warning("output failed after %s: %s", args.signals.first, exc)
        return Exit.for_signal(args.signals.first)
    except Exception as exc:  # a bug: one line here, the traceback in --log-file
        log.exception("internal error")
        _say(errors, "internal error", f"{type(exc).__name__}: {exc}")
        return int(Exit.FAILED)


class Signals:
    """SIGINT, SIGTERM, SIGHUP and SIGQUIT end a command one way. Outside a `taken` stretch
    the first raises `Interrupted` in the main thread (where commands run); inside one (a
    move or run commanding the arm) it calls that stretch's stop instead, so the command
    ends between steps and leaves the arm safe the way any other end does. Later signals are
    logged and ignored: they cannot cut short the safe stop under way (bounded by
    --safe-wait). A signal the caller set to be ignored (nohup, a background job's SIGINT)
    stays ignored."""

    HANDLED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)

    def __init__(self) -> None:
        self.received: list[int] = []
        self._stop: Callable[[], None] | None = None
        self._previous: dict[int, Any] = {}

    @property
    def first(self) -> int | None:
        return self.received[0] if self.received else None

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # only the main thread gets signals (tests run main() on others)
        for sig in self.HANDLED:
            previous = signal.getsignal(sig)
            if previous is signal.SIG_DFL or previous is signal.default_int_handler:
                self._previous[sig] = previous
                signal.signal(sig, self._on_signal)

    def restore(self) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()

    @contextmanager
    def taken(self, stop: Callable[[], None]) -> Iterator[None]:
        """Within: a signal calls `stop` instead of raising (and does after it, too: once a
        command commands the arm, it reports to the end)."""
        self._stop = stop
        if self.received:
            stop()  # one came before: do not start
        yield

    @contextmanager
    def rerouted(self, stop: Callable[[], None]) -> Iterator[None]:
        """Within: every handled signal calls `stop`, whatever came before, and is not counted
        in `received` (what ends `--viewer-keep`'s serving says nothing of the command)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {
            sig: signal.signal(sig, lambda _signum, _frame: stop())
            for sig in self.HANDLED
            if signal.getsignal(sig) is not signal.SIG_IGN
        }
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        first = not self.received
        self.received.append(signum)
        name = signal.Signals(signum).name
        log.warning("%s received%s", name, "" if first else "; already stopping, ignored")
        if not first:
            return
        if self._stop is not None:
            self._stop()
            return
        raise Interrupted(signum)
