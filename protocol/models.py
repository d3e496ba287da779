"""The arm models this stack knows, as data: one `ArmModel` per arm, in `MODELS`.

A model is what both ends of the wire must agree on for one kind of arm: which devices are
its joints and in what order, which is the jaw and in what unit, the factory limits, the
default current limits, the motor constants that turn a reported current into a torque, and
which devices answer for the arm as a whole. Code that depends on the arm takes an
`ArmModel` (the Alpha 5 by default) instead of assuming four joints.

The numbers are stated once, in the model's own module with their sources
(`protocol.alpha5`, `protocol.bravo7`); this table only gathers them. Adding an arm is one
more module of facts, one entry here and its MJCF (docs/architecture.md, "Arm models").
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from types import MappingProxyType

from . import alpha5, bravo7
from .ids import DeviceID

Range = tuple[float, float]  # (minimum, maximum)

__all__ = [
    "ALPHA5",
    "BRAVO7",
    "MODELS",
    "ArmModel",
    "ArmModelName",
    "MotorConstants",
    "Range",
    "model_named",
]


class ArmModelName(str, Enum):
    """The models in `MODELS`; the value is what `--arm` takes."""

    ALPHA5 = "alpha5"
    BRAVO7 = "bravo7"


def _floats(values: object, name: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a sequence of numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name} must be finite, got {out}")
    return out


@dataclass(frozen=True)
class MotorConstants:
    """Datasheet constants of each joint's motor and gearbox, in the model's joint order."""

    resistance_ohm: tuple[float, ...]
    torque_constant_nm_per_a: tuple[float, ...]  # at the motor shaft
    backemf_v_s_per_rad: tuple[float, ...]  # at the motor shaft
    gear_ratio: tuple[float, ...]
    gear_efficiency: tuple[float, ...]  # 0..1

    def __post_init__(self) -> None:
        sizes = set()
        for name in (
            "resistance_ohm",
            "torque_constant_nm_per_a",
            "backemf_v_s_per_rad",
            "gear_ratio",
            "gear_efficiency",
        ):
            values = _floats(getattr(self, name), f"motor {name}")
            if not values or any(v <= 0.0 for v in values):
                raise ValueError(f"motor {name} needs values > 0, got {values}")
            object.__setattr__(self, name, values)
            sizes.add(len(values))
        if len(sizes) != 1:
            raise ValueError("every motor constant needs one value per joint")
        if any(v > 1.0 for v in self.gear_efficiency):
            raise ValueError(f"gear efficiency is a fraction in (0, 1], got {self.gear_efficiency}")

    @property
    def count(self) -> int:
        return len(self.resistance_ohm)

    @property
    def torque_per_amp_nm(self) -> tuple[float, ...]:
        """Joint output torque per amp of motor current: Kt x gear ratio x efficiency (on a
        real arm the only torque estimate)."""
        return tuple(
            k * g * e
            for k, g, e in zip(
                self.torque_constant_nm_per_a, self.gear_ratio, self.gear_efficiency, strict=True
            )
        )


def _ranges(table: Mapping[DeviceID, Range], name: str) -> Mapping[DeviceID, Range]:
    out: dict[DeviceID, Range] = {}
    for device, values in table.items():
        lo, hi = _floats(values, f"{name} of {DeviceID(device).name}")
        if not lo < hi:
            raise ValueError(f"{name} of {DeviceID(device).name}: min {lo} >= max {hi}")
        out[DeviceID(device)] = (lo, hi)
    return MappingProxyType(out)


@dataclass(frozen=True)
class ArmModel:
    """One kind of arm, as both ends of the wire see it. Per-joint tuples are in `joints`
    order (base to tip); limit tables hold every joint and the jaw."""

    name: str  # the key people type (`--arm alpha5`)
    title: str  # for messages: "Reach Alpha 5"
    joints: tuple[DeviceID, ...]  # the rotary joints, base to tip
    jaw: DeviceID  # the jaws: a linear axis
    position_limits: Mapping[DeviceID, Range]  # factory envelope (rad; `jaw_unit` for jaws)
    velocity_limits: Mapping[DeviceID, Range]  # rad/s; `jaw_unit`/s for the jaws
    current_limits_mA: tuple[float, ...]  # default symmetric motor current limit per joint
    jaw_current_limit_mA: float
    #: rad/s per joint no joint can exceed (with margin): the driver's feedback check
    max_joint_speed: tuple[float, ...]
    motors: MotorConstants
    nominal_supply_v: float
    serial_baud: int  # bits/s, 8N1, of its serial line
    #: The device that answers for the arm as a whole: the one the host link enters at
    #: (where the virtual arm flags a frame it could not decode).
    base: DeviceID
    #: The device that does kinematics (KM_END_POS, KM_END_VEL); None: none does.
    kinematics: DeviceID | None = None
    #: Devices that are not actuators: a router, a compute module (empty on the Alpha 5).
    others: tuple[DeviceID, ...] = ()
    #: The device that reports the optional wrist force-torque sensor (FORCE_TORQUE).
    force_torque: DeviceID | None = None
    jaw_unit: str = "mm"
    #: Supply range the arm is rated for (V); None: not published.
    supply_range_v: Range | None = None
    notes: tuple[str, ...] = field(default=())  # where the facts come from

    def __post_init__(self) -> None:
        joints = tuple(DeviceID(d) for d in self.joints)
        if not joints:
            raise ValueError(f"{self.name}: a model needs at least one joint")
        devices = (*joints, DeviceID(self.jaw), *(DeviceID(d) for d in self.others))
        if len(set(devices)) != len(devices):
            raise ValueError(f"{self.name}: a device is named twice in {devices}")
        if DeviceID.BROADCAST in devices:
            raise ValueError(f"{self.name}: the broadcast id 0xFF is not a device")
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "jaw", DeviceID(self.jaw))
        object.__setattr__(self, "others", tuple(DeviceID(d) for d in self.others))
        n = len(joints)
        for name in ("position_limits", "velocity_limits"):
            table = _ranges(getattr(self, name), name)
            missing = [d.name for d in (*joints, self.jaw) if d not in table]
            extra = [d.name for d in table if d not in (*joints, self.jaw)]
            if missing or extra:
                raise ValueError(
                    f"{self.name}: {name} needs the joints and the jaw exactly "
                    f"(missing {missing}, not devices of the arm {extra})"
                )
            object.__setattr__(self, name, table)
        for device, (lo, hi) in self.velocity_limits.items():
            if not lo <= 0.0 <= hi:
                raise ValueError(f"{self.name}: velocity limits of {device.name} must include 0")
        for name in ("current_limits_mA", "max_joint_speed"):
            values = _floats(getattr(self, name), name)
            if len(values) != n or any(v <= 0.0 for v in values):
                raise ValueError(f"{self.name}: {name} needs {n} values > 0, got {values}")
            object.__setattr__(self, name, values)
        if self.motors.count != n:
            raise ValueError(f"{self.name}: motors have {self.motors.count} entries for {n} joints")
        for name in ("jaw_current_limit_mA", "nominal_supply_v"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{self.name}: {name} must be > 0, got {value}")
            object.__setattr__(self, name, value)
        if self.serial_baud <= 0:
            raise ValueError(f"{self.name}: serial_baud must be > 0, got {self.serial_baud}")
        for name in ("base", "kinematics", "force_torque"):
            device = getattr(self, name)
            if device is not None and DeviceID(device) not in devices:
                raise ValueError(f"{self.name}: {name} {device!r} is not one of its devices")

    # -- derived ----------------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def joint_letters(self) -> tuple[str, ...]:
        """The joints' letters in order, as the CLI takes angles and recordings name them."""
        return tuple(d.name for d in self.joints)

    @property
    def actuators(self) -> tuple[DeviceID, ...]:
        """The joints and the jaw: every device that moves."""
        return (*self.joints, self.jaw)

    @property
    def devices(self) -> tuple[DeviceID, ...]:
        """Every device of the arm: the actuators, then the others."""
        return (*self.actuators, *self.others)

    @property
    def current_limits(self) -> Mapping[DeviceID, Range]:
        """Default current limits per actuator (mA), as (-limit, limit)."""
        table = {d: (-mA, mA) for d, mA in zip(self.joints, self.current_limits_mA, strict=True)}
        table[self.jaw] = (-self.jaw_current_limit_mA, self.jaw_current_limit_mA)
        return MappingProxyType(table)

    @property
    def torque_per_amp_nm(self) -> tuple[float, ...]:
        return self.motors.torque_per_amp_nm

    def index(self, device: int) -> int:
        """Where `device` sits in `joints` (ValueError naming the joints if it is not one)."""
        try:
            return self.joints.index(DeviceID(device))
        except ValueError:
            raise ValueError(
                f"0x{int(device):02X} is not a joint of the {self.title} "
                f"({' '.join(self.joint_letters)})"
            ) from None

    def unit(self, device: int) -> str:
        """The unit of `device`'s position: rad for a joint, `jaw_unit` for the jaws."""
        return self.jaw_unit if int(device) == self.jaw else "rad"

    def wraps(self, device: int) -> bool:
        """Whether a joint's envelope is a whole turn (0 and 2 pi are one angle)."""
        lo, hi = self.position_limits[DeviceID(device)]
        return hi - lo >= 2.0 * math.pi - 1e-6


ALPHA5 = ArmModel(
    name=ArmModelName.ALPHA5.value,
    title="Reach Alpha 5",
    joints=alpha5.JOINTS,
    jaw=alpha5.JAW,
    position_limits=alpha5.FACTORY_POSITION_LIMITS,
    velocity_limits=alpha5.FACTORY_VELOCITY_LIMITS,
    current_limits_mA=alpha5.DEFAULT_CURRENT_LIMITS_MA,
    jaw_current_limit_mA=alpha5.DEFAULT_JAW_CURRENT_LIMIT_MA,
    max_joint_speed=alpha5.MAX_JOINT_SPEED,
    motors=MotorConstants(
        alpha5.MOTOR_RESISTANCE_OHM,
        alpha5.MOTOR_TORQUE_CONSTANT_NM_PER_A,
        alpha5.MOTOR_BACKEMF_V_S_PER_RAD,
        alpha5.GEAR_RATIO,
        alpha5.GEAR_EFFICIENCY,
    ),
    nominal_supply_v=alpha5.NOMINAL_SUPPLY_V,
    supply_range_v=alpha5.SUPPLY_RANGE_V,
    serial_baud=alpha5.SERIAL_BAUD,
    base=alpha5.BASE,
    kinematics=alpha5.BASE,
    notes=("protocol/alpha5.py", "reach_sim_bridge/model/README.md"),
)

BRAVO7 = ArmModel(
    name=ArmModelName.BRAVO7.value,
    title="Reach Bravo 7",
    joints=bravo7.JOINTS,
    jaw=bravo7.JAW,
    position_limits=bravo7.FACTORY_POSITION_LIMITS,
    velocity_limits=bravo7.FACTORY_VELOCITY_LIMITS,
    current_limits_mA=bravo7.DEFAULT_CURRENT_LIMITS_MA,
    jaw_current_limit_mA=bravo7.DEFAULT_JAW_CURRENT_LIMIT_MA,
    max_joint_speed=bravo7.MAX_JOINT_SPEED,
    motors=MotorConstants(
        bravo7.MOTOR_RESISTANCE_OHM,
        bravo7.MOTOR_TORQUE_CONSTANT_NM_PER_A,
        bravo7.MOTOR_BACKEMF_V_S_PER_RAD,
        bravo7.GEAR_RATIO,
        bravo7.GEAR_EFFICIENCY,
    ),
    nominal_supply_v=bravo7.NOMINAL_SUPPLY_V,
    serial_baud=bravo7.SERIAL_BAUD,
    base=bravo7.ROUTER,
    kinematics=bravo7.COMPUTE,
    others=(bravo7.ROUTER, bravo7.COMPUTE),
    force_torque=bravo7.FORCE_TORQUE_DEVICE,
    notes=("protocol/bravo7.py", "reach_sim_bridge/model/bravo7.md"),
)

#: Every model this stack knows, by name.
MODELS: Mapping[ArmModelName, ArmModel] = MappingProxyType(
    {ArmModelName.ALPHA5: ALPHA5, ArmModelName.BRAVO7: BRAVO7}
)


def model_named(name: str | ArmModelName) -> ArmModel:
    """The model called `name` ("alpha5", "bravo7"); ValueError naming the known ones."""
    try:
        return MODELS[ArmModelName(name)]
    except ValueError:
        known = ", ".join(m.value for m in ArmModelName)
        raise ValueError(f"no arm model {name!r}; known models: {known}") from None
