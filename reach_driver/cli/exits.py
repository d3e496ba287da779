"""The CLI's exit statuses, in one table (`reach-driver --help` shows it), and the wording of
messages for a person at the command line rather than a Python caller."""

from __future__ import annotations

import signal
import textwrap
from enum import IntEnum

from rich.console import Console
from rich.markup import escape


class UsageError(Exception):
    """A bad option or parameter found after parsing (exit 2, one line, no traceback)."""


class Exit(IntEnum):
    OK = 0
    FAILED = 1
    USAGE = 2
    LIMIT = 3
    NO_ARM = 4
    LINK_LOST = 5  # the link went down while a command was under way
    RECORDING_INCOMPLETE = 6  # the run completed; its --record file stops early
    NO_REALTIME = 7  # run --realtime require, and real-time priority was not granted
    # A signal ended a move or run: 128 + its number, the shell's convention.
    HANGUP = 128 + signal.SIGHUP  # 129: the terminal went away (an ssh drop)
    INTERRUPTED = 128 + signal.SIGINT  # 130: Ctrl-C
    QUIT = 128 + signal.SIGQUIT  # 131: Ctrl-\
    TERMINATED = 128 + signal.SIGTERM  # 143: kill, systemd stop

    @classmethod
    def for_signal(cls, signum: int) -> Exit:
        """The exit status of a move or run a signal ended (SIGHUP, SIGINT, SIGQUIT or
        SIGTERM, the ones `reach-driver` handles): 128 + its number."""
        return cls(128 + int(signum))


EXIT_TABLE: dict[Exit, str] = {
    Exit.OK: "done: the command finished; a run lasted --seconds (whether it got there: "
    "'reached'); monitor stopped by Ctrl-C or --seconds",
    Exit.FAILED: "failed: a run cut short (watchdog, lost link, fault, a non-finite reading, "
    "a controller error), a move that timed out, a fault before starting, an unreadable or "
    "malformed recording (inspect, export), an export whose file could not be written",
    Exit.USAGE: "bad command line: unknown option, malformed value, no --port, a --period "
    "the --watchdog cannot span, --record at the arm's port or a device, a controller's "
    "weights or parameter file that cannot be used, a controller whose extra is not "
    "installed (the line names the extra to install); export: a --to suffix it does not "
    "write, or .mcap without the export extra",
    Exit.LIMIT: "refused by a limit: nothing was sent, nothing moved (workspace --xyz: the "
    "point is out of reach)",
    Exit.NO_ARM: "no arm: wrong port, no permission, nothing answering, wrong baud; or "
    "another arm than --arm names (wrong arm)",
    Exit.LINK_LOST: "the link was lost during a move (the message says since when and the "
    "last positions the arm reported)",
    Exit.RECORDING_INCOMPLETE: "a run completed but its --record file is incomplete (e.g. a "
    "full disk: recording stopped, control went on)",
    Exit.NO_REALTIME: "run --realtime require and the driver was not given real-time "
    "priority (the line says why: CAP_SYS_NICE or an rtprio limit is needed); nothing was "
    "commanded",
    Exit.HANGUP: "move or run ended by SIGHUP (the terminal or ssh session went away)",
    Exit.INTERRUPTED: "move or run ended by Ctrl-C (SIGINT)",
    Exit.QUIT: "move or run ended by SIGQUIT (Ctrl-\\)",
    Exit.TERMINATED: "move or run ended by SIGTERM. For 129-143 as for 1: the joints were "
    "put in zero_velocity, resent until the arm confirmed it or --safe-wait ran out; the line "
    "'arm left in ...' says which",
}


def exit_table_text(indent: str = "  ") -> str:
    """The table as `--help` prints it."""
    lead = indent + " " * 5
    return "\n".join(
        textwrap.fill(text, 88, initial_indent=f"{indent}{int(code):>3}  ", subsequent_indent=lead)
        for code, text in EXIT_TABLE.items()
    )


# Advice written for Python callers of the client, and what a CLI user should read instead.
_API_ADVICE = {
    "call rearm() to command again": "the command stopped; read the lines above for why "
    "(a stalled controller, a loaded host, lost feedback), then run it again",
    "SafetyConfig.watchdog_s": "--watchdog",
}


def for_operator(message: str) -> str:
    """`message` without advice only a Python caller can follow."""
    for api, operator in _API_ADVICE.items():
        message = message.replace(api, operator)
    return message


def left_in_for_operator(left_in: str, port: str | None) -> str:
    """How the arm was left, true once this process has exited, with what to do when the arm
    did not confirm its safe mode. The client's own wording for an unreachable arm promises
    a safe mode 'as soon as the arm answers', which only holds while the client lives; the
    CLI exits right after saying it."""
    if not left_in.startswith("unknown:"):
        return left_in
    head, _, _ = left_in.partition("; the driver sends ")
    where = f" --port {port}" if port else ""
    return (
        f"{head}. reach-driver exits now and sends nothing more: each joint keeps the last "
        "mode and command it received (in current mode, the last current) until it is told "
        "otherwise or powered off; the Alpha 5 has no documented watchdog of its own. If it "
        f"is moving, cut its power; once it answers, `reach-driver{where} info` shows its "
        "mode and position."
    )


def notes() -> Console:
    """Where notes and warnings go: stderr, so that --json's stdout stays parseable."""
    return Console(stderr=True, highlight=False)


def say_interrupted(signum: int | None, left_in: str) -> None:
    """The last line on stderr of a move or run a signal ended."""
    if signum is not None:
        notes().print(
            f"interrupted: by {signal.Signals(signum).name}; arm left in {escape(left_in)}",
            soft_wrap=True,
        )
