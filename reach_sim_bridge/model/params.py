"""Physical parameters of a simulated arm that vary between arms, fluids and faults.

The MJCF (model/alpha5.xml) holds the nominal Alpha 5; ``ArmParams()`` holds the same nominal
values (a test keeps the two equal) so they can be perturbed, read by MPC, and applied to a
compiled model without recompiling. Per-joint arrays have one value per joint of the arm, in
its joint order: four on the Alpha 5 (E D C B), six on the Bravo 7 (G F E D C B, nominal
values read from its MJCF: `reach_sim_bridge.model.bravo7.Bravo7Arm.nominal`). The
link arrays name the body each joint moves (Alpha: E -> m2_1_1, D -> m2, C -> m2_1_3, B -> m1
+ jaws; Bravo: joint i -> link i, the jaws' link 7 not a parameter).
"""

from __future__ import annotations

import difflib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from protocol.files import UserFileError, read_json
from protocol.models import ALPHA5, MODELS, ArmModel
from reach_sim_bridge.model.motor import (
    ALPHA5_MOTORS,
    DEFAULT_CURRENT_LIMITS_MA,
    DEFAULT_JAW_CURRENT_LIMIT_MA,
    DEFAULT_SUPPLY_VOLTAGE,
    JAW_MOTOR,
    MotorParams,
)

LINK_BODIES = ("m2_1_1", "m2", "m2_1_3", "m1")  # the body each of E D C B moves
NOSLIP_ITERATIONS = 10  # MuJoCo no-slip solver iterations when `friction_holds`

Vec = tuple[float, ...]  # one value per joint

_JOINT_FIELDS = (
    "armature",
    "damping",
    "frictionloss",
    "link_mass_kg",
    "link_volume_l",
    "torque_scale",
    "current_limits_mA",
)


@dataclass(frozen=True)
class ArmParams:
    """Everything about one simulated arm that a run may change (see model/README.md)."""

    # Joints E D C B: reflected rotor inertia (kg m^2), viscous (N m s/rad), Coulomb (N m).
    armature: Vec = (0.12, 0.12, 0.12, 0.007)
    damping: Vec = (2.40, 2.24, 0.82, 0.36)
    frictionloss: Vec = (0.7, 0.7, 0.7, 0.075)
    # Links moved by E D C B: mass (kg) and displaced volume (litres) from the datasheet.
    link_mass_kg: Vec = (0.161, 0.380, 0.142, 0.355)
    link_volume_l: Vec = (0.032, 0.218, 0.032, 0.134)
    # Medium: water density 0 means in air (no buoyancy, no drag).
    water_density: float = 1000.0  # kg/m^3 (1000 fresh, ~1025 sea)
    fluid_viscosity: float = 0.0009  # Pa s
    fluid_drag: bool = True  # MuJoCo's ellipsoid drag model; off for speed
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)  # in the base frame (z up)
    # Motors and drive.
    motors: MotorParams = ALPHA5_MOTORS
    supply_voltage: float = DEFAULT_SUPPLY_VOLTAGE
    current_limits_mA: Vec = DEFAULT_CURRENT_LIMITS_MA  # type: ignore[assignment]
    torque_scale: Vec = (1.0, 1.0, 1.0, 1.0)
    # A load held in the jaws, at the tool centre point: mass (kg) and displaced volume
    # (litres), a solid sphere's inertia. Known loads anchor what identification cannot
    # otherwise weigh (docs/identification.md, "A known payload").
    payload_kg: float = 0.0
    payload_volume_l: float = 0.0
    # Jaw (slide joint A, metres): assumed values, see model/README.md.
    jaw_motor: MotorParams = JAW_MOTOR
    jaw_current_limit_mA: float = DEFAULT_JAW_CURRENT_LIMIT_MA
    jaw_armature: float = 725.0  # kg: B's rotor inertia reflected through jaw gear + screw
    jaw_damping: float = 5000.0  # N s/m
    jaw_frictionloss: float = 10.0  # N
    # The real wrist B turns without end stops and reports 0..2pi; by default the model
    # gives it stops at 0 and 2pi so the reported angle never jumps.
    wrist_continuous: bool = False
    # Contacts between the links and the base. Off by default: the link cylinders are
    # sized by displaced volume, fatter than the real links (see model/README.md).
    self_collision: bool = False
    # Coulomb friction that holds: MuJoCo's frictionloss is a soft constraint, and below
    # breakaway a joint slides at push / ~120 N m s/rad (tools/creep.py) where a gearbox holds.
    # True runs MuJoCo's no-slip solver (NOSLIP_ITERATIONS), which holds it and leaves the slip
    # above breakaway as it was. Off by default: every published figure was measured without.
    friction_holds: bool = False

    def __post_init__(self) -> None:
        n = self.motors.count
        if self.jaw_motor.count != 1:
            raise ValueError("jaw_motor needs 1 entry")
        for name in _JOINT_FIELDS:
            vec = tuple(float(v) for v in np.asarray(getattr(self, name), float).reshape(-1))
            if len(vec) != n or not all(math.isfinite(v) for v in vec):
                raise ValueError(f"{name} needs {n} finite values ({joint_order(n)}), got {vec}")
            object.__setattr__(self, name, vec)
        for name in ("armature", "link_mass_kg"):
            if any(v <= 0.0 for v in getattr(self, name)):
                raise ValueError(f"{name} must be > 0 for every joint, got {getattr(self, name)}")
        for name in ("damping", "frictionloss", "link_volume_l", "current_limits_mA"):
            if any(v < 0.0 for v in getattr(self, name)):
                raise ValueError(f"{name} must be >= 0 for every joint, got {getattr(self, name)}")
        if any(not 0.0 <= v <= 1.0 for v in self.torque_scale):
            raise ValueError(f"torque_scale must be in [0, 1] per joint, got {self.torque_scale}")
        gravity = tuple(float(v) for v in self.gravity)
        if len(gravity) != 3 or not all(math.isfinite(v) for v in gravity):
            raise ValueError(f"gravity needs 3 finite values (m/s^2), got {self.gravity}")
        object.__setattr__(self, "gravity", gravity)
        for name in (
            "water_density",
            "fluid_viscosity",
            "jaw_current_limit_mA",
            "jaw_damping",
            "jaw_frictionloss",
            "payload_kg",
            "payload_volume_l",
        ):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
            object.__setattr__(self, name, value)
        for name in ("supply_voltage", "jaw_armature"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a finite number > 0, got {value}")
            object.__setattr__(self, name, value)

    @property
    def n_joints(self) -> int:
        return self.motors.count

    @property
    def in_water(self) -> bool:
        return self.water_density > 0.0

    def buoyancy_kg(self) -> np.ndarray:
        """Mass of water each joint's link displaces (kg), in joint order."""
        return np.asarray(self.link_volume_l) * 1e-3 * self.water_density

    def in_air(self) -> ArmParams:
        """The same arm out of the water (no buoyancy, no drag)."""
        return replace(self, water_density=0.0)

    def randomized(self, rng: np.random.Generator | int | None, spread: float = 0.2) -> ArmParams:
        """A perturbed copy: friction, armature, link masses and buoyancy each scaled by an
        independent uniform factor in [1 - spread, 1 + spread] (per joint)."""
        if not (math.isfinite(spread) and 0.0 <= spread < 1.0):
            raise ValueError(f"spread must be in [0, 1), got {spread}")
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)

        def scaled(values: Vec) -> Vec:
            f = gen.uniform(1.0 - spread, 1.0 + spread, size=len(values))
            return tuple(float(v) for v in np.asarray(values) * f)

        return replace(
            self,
            damping=scaled(self.damping),
            frictionloss=scaled(self.frictionloss),
            armature=scaled(self.armature),
            link_mass_kg=scaled(self.link_mass_kg),
            link_volume_l=scaled(self.link_volume_l),
        )

    def as_dict(self) -> dict[str, object]:
        """Plain values for logs and recordings."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to_json_dict(self) -> dict[str, Any]:
        """Every field as plain JSON values (the `--params` file format; see
        `load_arm_params`): tuples become lists, the motor tables nested objects."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, MotorParams):
                out[f.name] = {name: list(getattr(value, name)) for name in _MOTOR_FIELDS}
            elif isinstance(value, tuple):
                out[f.name] = list(value)
            else:
                out[f.name] = value
        return out

    @classmethod
    def from_json_dict(
        cls,
        data: Any,
        where: str = "params",
        model: ArmModel = ALPHA5,
        nominal: ArmParams | None = None,
    ) -> ArmParams:
        """The arm of `model` a `--params` object describes: the fields it names, `nominal`
        otherwise (the model's nominal arm; default `ArmParams()`, the Alpha 5's).

        Keys starting with ``_`` (``_fit``, ``_comment``...) are metadata and ignored.
        Raises `ParamsFileError` (a ValueError) naming the key for unknown keys (with the
        nearest field name), wrong types or lengths, per-joint arrays for another number of
        joints than the model's (naming the arm they fit), and non-physical values."""
        if not isinstance(data, Mapping):
            raise ParamsFileError(
                f"{where}: expected a JSON object of ArmParams fields, got {_kind(data)}"
            )
        nominal = cls() if nominal is None else nominal
        if nominal.n_joints != model.n_joints:
            raise ValueError(
                f"nominal parameters of {nominal.n_joints} joints for the {model.title}"
            )
        _check_joint_count(data, model, where)
        values: dict[str, Any] = {}
        for key, raw in data.items():
            if not isinstance(key, str):
                raise ParamsFileError(f"{where}: keys must be strings, got {key!r}")
            if key.startswith("_"):
                continue
            if key not in _FILE_FIELDS:
                raise ParamsFileError(f"{where}: unknown key {key!r}{_suggest(key, _FILE_FIELDS)}")
            values[key] = _parse_field(key, raw, getattr(nominal, key), f"{where}: {key}")
        try:
            params = replace(nominal, **values)
        except ValueError as exc:
            raise ParamsFileError(f"{where}: {exc}") from exc
        _check_physical(params, where)
        return params


class ParamsFileError(ValueError):
    """An arm parameter file (or object) that does not describe a physical arm."""


_MOTOR_FIELDS = (
    "resistance_ohm",
    "torque_constant",
    "backemf_constant",
    "gear_ratio",
    "efficiency",
)
_FILE_FIELDS = tuple(f.name for f in fields(ArmParams))
_BOOL_FIELDS = ("fluid_drag", "wrist_continuous", "self_collision", "friction_holds")


def joint_order(n: int) -> str:
    """How the joints of an arm of `n` joints read: "E D C B" (the known model with that many
    joints), else "n joints"."""
    for model in MODELS.values():
        if model.n_joints == n:
            return " ".join(model.joint_letters)
    return f"{n} joints"


def _check_joint_count(data: Mapping[str, Any], model: ArmModel, where: str) -> None:
    """One line if the file's per-joint arrays all have the joint count of another known
    model: the file describes that arm, not `model`'s (any other wrong length is the field's
    own error, naming the values it needs)."""
    counts = {len(v) for k, v in data.items() if k in _JOINT_FIELDS and isinstance(v, list)}
    motors = data.get("motors")
    if isinstance(motors, Mapping):
        counts |= {len(v) for v in motors.values() if isinstance(v, list)}
    other = next(
        (m for m in MODELS.values() if counts == {m.n_joints} and m.n_joints != model.n_joints),
        None,
    )
    if other is not None:
        raise ParamsFileError(
            f"{where}: describes an arm of {other.n_joints} joints ({joint_order(other.n_joints)}:"
            f" a {other.title}), not a {model.title} ({model.n_joints} joints "
            f"{' '.join(model.joint_letters)})"
        )


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return f"the number {value!r}"
    if isinstance(value, str):
        return f"the string {value!r}"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if isinstance(value, Mapping):
        return "an object"
    return type(value).__name__


def _suggest(key: str, names: tuple[str, ...]) -> str:
    close = difflib.get_close_matches(key, names, n=1, cutoff=0.5)
    if close:
        return f"; did you mean {close[0]!r}?"
    return f"; known keys: {', '.join(names)}"


def _number(raw: Any, what: str) -> float:
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise ParamsFileError(f"{what} must be a number, got {_kind(raw)}")
    value = float(raw)
    if not math.isfinite(value):
        raise ParamsFileError(f"{what} must be finite, got {raw!r}")
    return value


def _numbers(raw: Any, n: int, what: str, order: str) -> tuple[float, ...]:
    if not isinstance(raw, list):
        raise ParamsFileError(f"{what} must be a list of {n} numbers ({order}), got {_kind(raw)}")
    if len(raw) != n:
        raise ParamsFileError(f"{what} needs {n} values ({order}), got {len(raw)}")
    return tuple(_number(v, f"{what}[{i}]") for i, v in enumerate(raw))


def _parse_field(key: str, raw: Any, nominal: Any, what: str) -> Any:
    if key in _BOOL_FIELDS:
        if not isinstance(raw, bool):
            raise ParamsFileError(f"{what} must be true or false, got {_kind(raw)}")
        return raw
    if isinstance(nominal, MotorParams):
        if not isinstance(raw, Mapping):
            raise ParamsFileError(
                f"{what} must be an object of {', '.join(_MOTOR_FIELDS)}, got {_kind(raw)}"
            )
        n = nominal.count
        order = joint_order(n) if key == "motors" else "the jaw"
        table: dict[str, tuple[float, ...]] = {}
        for name, value in raw.items():
            if name not in _MOTOR_FIELDS:
                raise ParamsFileError(
                    f"{what}: unknown key {name!r}{_suggest(str(name), _MOTOR_FIELDS)}"
                )
            if n == 1 and not isinstance(value, list):
                value = [value]
            table[name] = _numbers(value, n, f"{what}.{name}", order)
        try:
            return replace(nominal, **table)
        except ValueError as exc:
            raise ParamsFileError(f"{what}: {exc}") from exc
    if key in _JOINT_FIELDS:
        return _numbers(raw, len(nominal), what, joint_order(len(nominal)))
    if key == "gravity":
        return _numbers(raw, 3, what, "x y z in the base frame, m/s^2")
    return _number(raw, what)


def _check_physical(p: ArmParams, where: str) -> None:
    """What `ArmParams` itself allows but no arm has (a file states a real arm)."""
    letters = joint_order(p.n_joints).split()
    for joint, scale in zip(letters, p.torque_scale, strict=True):
        if not 0.0 < scale <= 1.0:
            raise ParamsFileError(
                f"{where}: torque_scale of {joint} must be in (0, 1], got {scale:g}"
            )
    for joint, limit in zip(letters, p.current_limits_mA, strict=True):
        if limit <= 0.0:
            raise ParamsFileError(
                f"{where}: current_limits_mA of {joint} must be > 0 mA, got {limit:g}"
            )
    if p.jaw_current_limit_mA <= 0.0:
        raise ParamsFileError(
            f"{where}: jaw_current_limit_mA must be > 0, got {p.jaw_current_limit_mA:g}"
        )
    if p.water_density > 2000.0:
        raise ParamsFileError(
            f"{where}: water_density is kg/m^3 (1000 fresh, ~1025 sea, 0 air), "
            f"got {p.water_density:g}"
        )
    if not 0.0 < math.hypot(*p.gravity) < 20.0:
        raise ParamsFileError(f"{where}: gravity {p.gravity} m/s^2 is not an Earth gravity")


def load_arm_params(
    path: str | Path, model: ArmModel = ALPHA5, nominal: ArmParams | None = None
) -> ArmParams:
    """The arm of `model` a `--params FILE.json` describes: a JSON object of `ArmParams`
    field names (any subset; per-joint arrays in the model's joint order, E D C B on the
    Alpha 5; the rest `nominal`, the model's nominal arm). Keys starting with ``_`` are ignored
    (a fit's metadata, ``_fit``, is read by `reach_sim_bridge.model.twin`)."""
    return ArmParams.from_json_dict(read_params_json(path), str(path), model, nominal)


def read_params_json(path: str | Path) -> Any:
    """The JSON value of a parameter file (`ParamsFileError` if unreadable or not JSON)."""
    try:
        return read_json(path, "arm parameters")
    except UserFileError as exc:
        raise ParamsFileError(str(exc)) from None


def save_arm_params(
    params: ArmParams, path: str | Path, extra: Mapping[str, Any] | None = None
) -> Path:
    """Write `params` in the `--params` format (every field), plus metadata keys from
    `extra` (each must start with ``_`` so the loader ignores it)."""
    data = params.to_json_dict()
    for key, value in (extra or {}).items():
        if not key.startswith("_"):
            raise ValueError(f"metadata keys start with '_' (the loader ignores them), got {key!r}")
        data[key] = value
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    return path
