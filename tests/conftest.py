"""Helpers shared by the test modules (import them as `from conftest import ...`)."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(
    predicate: Callable[[], object], timeout: float = 5.0, poll_s: float = 0.005
) -> bool:
    """Poll `predicate` until it is truthy or `timeout` seconds pass; its last verdict."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())
