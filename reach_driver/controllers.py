"""The controller interface, the state it sees, and controllers found by name.

`Controller` and `ControlState` are the one definition of what a controller is, for the
driver's control loop and for every evaluation backend in `policy`. Controllers are found
through the `reach_stack.controllers` entry points.

Like python-can's interface plugins: the driver never imports `policy` (or anyone else's
controller package); a package registers `name = "module:factory"` and the factory is called
with keyword arguments to build an object with `reset()` and `act(state, target)`.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Protocol

import numpy as np

from reach_driver.errors import DriverError

GROUP = "reach_stack.controllers"


@dataclass(frozen=True)
class ControlState:
    """What a controller sees: arm angles and velocities (E D C B) and the loop's time (s)."""

    q: np.ndarray
    qdot: np.ndarray
    t: float


class Controller(Protocol):
    """Currents (mA, E D C B) from the state and the target angles; `reset()` between runs.

    A controller trained at a fixed rate may also expose `period_s` (or `control_hz`), and
    one with something to say about a run (what a supervisor inside it did) `report()`, a
    JSON-able dict the driver prints and records after the run (`controller_report`).
    """

    def reset(self) -> None: ...

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray: ...


def controller_report(controller: object) -> dict[str, Any]:
    """The controller's `report()` after a run, {} if it has none; a report that fails says so
    instead of failing the run it describes."""
    report = getattr(controller, "report", None)
    if not callable(report):
        return {}
    try:
        out = report()
    except Exception as exc:  # the run is over: its summary must still be printed
        return {"report_error": f"{type(exc).__name__}: {exc}"}
    return dict(out) if isinstance(out, dict) else {"report": out}


def _entry_points() -> dict[str, EntryPoint]:
    return {ep.name: ep for ep in entry_points(group=GROUP)}


def available_controllers() -> list[str]:
    """Registered controller names (whether or not their modules import cleanly)."""
    return sorted(_entry_points())


def load_controller(name: str, **kwargs: Any) -> Controller:
    """Build the controller registered as `name`; a clear `DriverError` if it cannot be."""
    eps = _entry_points()
    ep = eps.get(name)
    if ep is None:
        known = ", ".join(sorted(eps)) or "none (is reach-stack installed? pip install -e .)"
        raise DriverError(f"unknown controller {name!r}; registered: {known}")
    try:
        factory = ep.load()
    except Exception as exc:
        raise DriverError(
            f"controller {name!r} is registered as {ep.value} but failed to load: "
            f"{type(exc).__name__}: {exc}"
        ) from exc
    try:
        controller = factory(**kwargs)
    except TypeError as exc:
        raise DriverError(f"controller {name!r} rejected its parameters {kwargs}: {exc}") from exc
    for method in ("reset", "act"):
        if not callable(getattr(controller, method, None)):
            raise DriverError(f"controller {name!r} ({ep.value}) has no {method}() method")
    return controller  # type: ignore[no-any-return]
