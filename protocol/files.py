"""Reading a file a person names on a command line (a parameter file, a targets list, weights'
metadata): bounded, and every failure one `UserFileError` saying which file and why.

None of this is the codec. It lives in `protocol` for the reason `protocol.viewer` does: the
driver, the simulator and the controllers all read such files, and `protocol` is the one
package each of them may import. `protocol/__init__` does not import it.

What it guards against: a path that is not a regular file (`/dev/zero`, a FIFO, the arm's
tty) would be read until memory runs out; a file far larger than any real one is refused
before it is read; JSON nested deeper than Python's recursion limit raises RecursionError,
not a JSONDecodeError, in `json.loads`.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any

#: The largest parameter, targets or metadata file read (bytes): real ones are a few kB.
MAX_JSON_BYTES = 16 * 2**20
#: The largest weights (.npz) file read: the shipped actors are about 0.2 MB.
MAX_WEIGHTS_BYTES = 256 * 2**20


class UserFileError(ValueError):
    """A file a person named cannot be used (the message names it and says why)."""


def read_bounded(path: str | Path, what: str, max_bytes: int) -> bytes:
    """The bytes of the regular file `path`, at most `max_bytes` (UserFileError otherwise)."""
    try:
        # O_NONBLOCK: opening a FIFO for reading would otherwise wait for a writer.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
        with open(fd, "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise UserFileError(f"{what} {path} is not a regular file (a device or pipe?)")
            if st.st_size > max_bytes:
                raise UserFileError(
                    f"{what} {path} is {st.st_size:,} bytes, more than the {max_bytes:,} read"
                )
            os.set_blocking(fd, True)
            data = f.read(max_bytes + 1)  # a file growing as it is read stops here too
    except OSError as exc:
        raise UserFileError(f"cannot read {what} {path}: {exc.strerror or exc}") from exc
    if len(data) > max_bytes:
        raise UserFileError(f"{what} {path} is more than the {max_bytes:,} bytes read")
    return data


def parse_json(text: str | bytes, where: str) -> Any:
    """The JSON value of `text` (UserFileError naming `where` if it is not JSON)."""
    try:
        return json.loads(text)
    except RecursionError:
        raise UserFileError(f"{where}: JSON nested too deeply") from None
    except UnicodeDecodeError as exc:
        raise UserFileError(f"{where} is not UTF-8 text: {exc.reason}") from None
    except json.JSONDecodeError as exc:
        raise UserFileError(f"{where} is not valid JSON: {exc}") from None


def read_json(path: str | Path, what: str, max_bytes: int = MAX_JSON_BYTES) -> Any:
    """The JSON value of the file `path`, read with `read_bounded`'s limits."""
    return parse_json(read_bounded(path, what, max_bytes), f"{what} {path}")
