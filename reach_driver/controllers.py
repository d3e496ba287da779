"""The controller interface, the state it sees, and controllers found by name.

`Controller` and `ControlState` are the one definition of what a controller is, for the
driver's control loop and for every evaluation backend in `policy`. Controllers are found
through the `reach_stack.controllers` entry points.

Like python-can's interface plugins: the driver never imports `policy` (or anyone else's
controller package); a package registers `name = "module:factory"` and the factory is called
with keyword arguments to build an object with `reset()` and `act(state, target)`.

A factory may also say what it is, for `reach-driver controllers` (`describe_controllers`): the
first line of its docstring is its summary, and the decorators `learned(provenance)` and
`engineered` mark how it was made; a learned one's `provenance()` says how it was trained
(algorithm, demonstrations, teacher, env steps...), so nobody has to guess from its name.

Which arms a factory's controllers drive it says with `drives(...)`: such a factory is called
with `model=` (the arm's `ArmModel`, for its joint count and defaults). A factory that does
not say drives the Alpha 5 alone and is called without it, as every factory was before the
stack knew another arm.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Protocol, TypeVar

import numpy as np

from protocol.extras import MissingExtra
from protocol.models import ALPHA5, ArmModel, model_named
from reach_driver.errors import DriverError, ExtraNotInstalledError

GROUP = "reach_stack.controllers"


@dataclass(frozen=True)
class ControlState:
    """What a controller sees: arm angles and velocities in the arm's joint order (E D C B
    on the Alpha 5, G F E D C B on the Bravo 7) and the loop's time (s)."""

    q: np.ndarray
    qdot: np.ndarray
    t: float


class Controller(Protocol):
    """Currents (mA, one per joint in the arm's order) from the state and the target angles;
    `reset()` between runs.

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


def registered_list() -> str:
    """The registered names as help and errors list them ("ddpg, mpc, pid"): read from the
    entry points, so no text names a stale set."""
    return ", ".join(available_controllers()) or "none (is reach-stack installed? pip install -e .)"


class ControllerModelError(DriverError):
    """The controller asked for does not drive the arm's model (it says which it drives)."""


def load_controller(name: str, *, arm: ArmModel = ALPHA5, **kwargs: Any) -> Controller:
    """Build the controller registered as `name` for an `arm` of that model; a clear
    `DriverError` if it cannot be (`ControllerModelError` if it does not drive that model,
    `ExtraNotInstalledError` naming the extra to install if it needs a library that is not
    installed)."""
    ep = _entry_points().get(name)
    if ep is None:
        raise DriverError(f"unknown controller {name!r}; registered: {registered_list()}")
    try:
        factory = ep.load()
    except MissingExtra as exc:  # e.g. mpc without CasADi: say what to install
        raise ExtraNotInstalledError(str(exc), exc.extra) from None
    except Exception as exc:
        raise DriverError(
            f"controller {name!r} is registered as {ep.value} but failed to load: "
            f"{type(exc).__name__}: {exc}"
        ) from exc
    models = driven_models(factory)
    if arm.name not in models:
        raise ControllerModelError(
            f"controller {name!r} drives the {_titles(models)} only, not the {arm.title}"
        )
    if _declares_models(factory):
        kwargs = {**kwargs, "model": arm}
    try:
        controller = factory(**kwargs)
    except TypeError as exc:
        raise DriverError(f"controller {name!r} rejected its parameters {kwargs}: {exc}") from exc
    for method in ("reset", "act"):
        if not callable(getattr(controller, method, None)):
            raise DriverError(f"controller {name!r} ({ep.value}) has no {method}() method")
    return controller  # type: ignore[no-any-return]


F = TypeVar("F", bound=Callable[..., Any])


def drives(*models: ArmModel) -> Callable[[F], F]:
    """Mark a factory as building controllers for these arm models: it is called with
    `model=` (the arm's). The factory itself is unchanged."""

    def mark(factory: F) -> F:
        factory.arm_models = tuple(m.name for m in models)  # type: ignore[attr-defined]
        return factory

    return mark


def _declares_models(factory: object) -> bool:
    return isinstance(getattr(factory, "arm_models", None), tuple)


def _titles(names: tuple[str, ...]) -> str:
    titles = []
    for name in names:
        try:
            titles.append(model_named(name).title)
        except ValueError:
            titles.append(name)
    return ", ".join(titles)


def driven_models(factory: object) -> tuple[str, ...]:
    """The names of the arm models a factory's controllers drive (`drives`); the Alpha 5's
    alone for a factory that does not say."""
    models = getattr(factory, "arm_models", None)
    return models if isinstance(models, tuple) else (ALPHA5.name,)


class ControllerKind(str, Enum):
    """How a registered controller was made, as its factory declares it."""

    LEARNED = "learned"  #: its factory has a `provenance()` (how it was trained)
    ENGINEERED = "engineered"  #: marked `@engineered`: designed and tuned, nothing learned
    UNDECLARED = "undeclared"  #: a plain factory that says neither (or failed to load)


def learned(provenance: Callable[[], Mapping[str, Any]]) -> Callable[[F], F]:
    """Mark a factory as building a learned controller whose training `provenance()` tells
    (called only when asked: it may read a weights file). The factory itself is unchanged."""

    def mark(factory: F) -> F:
        factory.provenance = provenance  # type: ignore[attr-defined]
        factory.controller_kind = ControllerKind.LEARNED  # type: ignore[attr-defined]
        return factory

    return mark


def engineered(factory: F) -> F:
    """Mark a factory as building an engineered controller (designed and tuned, not learned)."""
    factory.controller_kind = ControllerKind.ENGINEERED  # type: ignore[attr-defined]
    return factory


@dataclass(frozen=True)
class ControllerInfo:
    """One registered controller as `reach-driver controllers` lists it. `error` says why its
    entry point (or its provenance) could not be loaded; the rest is then what is known.
    `extra` names the extra to install when the reason is a library that is not installed."""

    name: str
    target: str  #: the entry point's "module:attr"
    summary: str  #: the first line of the factory's docstring ("" if it has none)
    provenance: dict[str, Any] | None  #: a learned controller's, else None
    error: str | None
    kind: ControllerKind = ControllerKind.UNDECLARED
    extra: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "target": self.target,
            "kind": self.kind.value,
            "summary": self.summary,
            "provenance": self.provenance,
            "error": self.error,
            "extra": self.extra,
        }


def _summary(factory: object) -> str:
    for line in (getattr(factory, "__doc__", None) or "").strip().splitlines():
        if line.strip():
            return line.strip()
    return ""


def _describe(ep: EntryPoint) -> ControllerInfo:
    try:
        factory = ep.load()
    except MissingExtra as exc:  # its library is not installed: say which extra brings it
        return ControllerInfo(ep.name, ep.value, "", None, str(exc), extra=exc.extra)
    except Exception as exc:  # a broken plugin is listed with its error, never a traceback
        return ControllerInfo(ep.name, ep.value, "", None, f"{type(exc).__name__}: {exc}")
    summary = _summary(factory)
    kind = getattr(factory, "controller_kind", ControllerKind.UNDECLARED)
    if not isinstance(kind, ControllerKind):
        kind = ControllerKind.UNDECLARED
    provenance_of = getattr(factory, "provenance", None)
    if not callable(provenance_of):
        return ControllerInfo(ep.name, ep.value, summary, None, None, kind)
    try:
        provenance = dict(provenance_of())
    except Exception as exc:  # e.g. its weights file is missing
        error = f"provenance: {type(exc).__name__}: {exc}"
        return ControllerInfo(ep.name, ep.value, summary, None, error, ControllerKind.LEARNED)
    return ControllerInfo(ep.name, ep.value, summary, provenance, None, ControllerKind.LEARNED)


def controllers_for(model: ArmModel, kind: ControllerKind) -> list[str]:
    """The names of the registered controllers of `kind` that drive `model`, sorted; one
    that fails to load (an extra not installed) is left out: `reach-driver controllers` says
    why."""
    out = []
    for name, ep in sorted(_entry_points().items()):
        try:
            factory = ep.load()
        except Exception:  # listed with its error by describe_controllers
            continue
        if getattr(factory, "controller_kind", None) is kind and model.name in driven_models(
            factory
        ):
            out.append(name)
    return out


def describe_controllers() -> list[ControllerInfo]:
    """Every registered controller, by name: what it is and, for a learned one, how it was
    trained. Each entry point is loaded (imported) to read its docstring; one that fails is
    listed with `error` set instead of raising."""
    eps = _entry_points()
    return [_describe(eps[name]) for name in sorted(eps)]
