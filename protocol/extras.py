"""What to install for a feature whose optional dependency is missing, said in one line.

`pip install reach-stack` brings the codec, the driver and its command line, recordings and the
controllers that need no solver or simulator; the heavy libraries come with extras by role
(pyproject.toml): MuJoCo with `sim`, CasADi with `mpc`, torch and Gymnasium with `train`, Ray
with `scale`, and the MCAP writer of `reach-driver export` with `export`. A module that needs
one imports it inside `needs_extra(feature, extra)`, so a user without it reads "the mpc
controller needs CasADi: pip install 'reach-stack[mpc]'" (`MissingExtra`) instead of a
traceback ending in "No module named 'casadi'". A script's own imports go inside
`script_needs_extra`, which ends the program with that line (exit 2).

None of this is the codec. It lives in `protocol` for the reason `protocol.viewer` does: the
driver, the simulator and the controllers all name a missing extra, and this is the one package
they all may import. `protocol/__init__` does not import it.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

#: The distribution a user installs, with an extra: pip install 'reach-stack[EXTRA]'.
DISTRIBUTION = "reach-stack"

#: The optional libraries by top-level module, as their projects spell them. Only these are
#: taken for a missing extra: any other missing module is a bug and keeps its traceback.
OPTIONAL_MODULES: dict[str, str] = {
    "mujoco": "MuJoCo",
    "casadi": "CasADi",
    "torch": "PyTorch",
    "gymnasium": "Gymnasium",
    "ray": "Ray",
    "mcap": "the mcap library",
}


class MissingExtra(ModuleNotFoundError):
    """`feature` needs `module`, which the extra `extra` installs. A ModuleNotFoundError, so
    code that already tolerates a missing module still does, and an outer `needs_extra`
    restates it for the feature the user asked for."""

    def __init__(self, feature: str, extra: str, module: str) -> None:
        self.feature = feature
        self.extra = extra
        library = OPTIONAL_MODULES.get(module, module)
        super().__init__(
            f"{feature} needs {library}: pip install '{DISTRIBUTION}[{extra}]'", name=module
        )


@contextmanager
def needs_extra(feature: str, extra: str) -> Iterator[None]:
    """Imports in this block that fail for want of an optional library raise `MissingExtra`
    naming `extra` (e.g. `with needs_extra("the mpc controller", "mpc"): import casadi`)."""
    try:
        yield
    except ModuleNotFoundError as exc:
        module = (exc.name or "").split(".")[0]
        if module not in OPTIONAL_MODULES:
            raise
        raise MissingExtra(feature, extra, module) from None


#: A script that cannot start for want of an extra exits as for a bad command line.
USAGE_EXIT = 2


@contextmanager
def script_needs_extra(program: str, extra: str) -> Iterator[None]:
    """For a script's imports (e.g. `tools/train.py`): a missing optional library ends the
    program with one line on stderr naming `extra`, exit 2, not a traceback."""
    try:
        with needs_extra(program, extra):
            yield
    except MissingExtra as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(USAGE_EXIT) from None
