"""The CLI's exit statuses (documented in `reach-driver --help`)."""

from __future__ import annotations

from enum import IntEnum


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
    INTERRUPTED = 130
