"""Which arm this is: its model, told by the devices that answer at connect; what each
device reported then (serial and model numbers, firmware version); and the check after a
reconnect that the same arm answers.

The model is read from which joints answer (`model_answering`): the Bravo 7's F and G
(0x06, 0x07) are not devices of an Alpha 5. Not from a device type:
0x67, which newer vendor software reads as DEVICE_TYPE, is the internal pressure in the
protocol this stack follows (docs/protocol.md, "The 0x67 clash"), and the model numbers the
vendor's devices report are not published.

A reconnect reopens a path (a pty, a serial adapter, a UDP address) that another arm can sit
behind by then. Re-applying the old set-up to it, or accepting its positions as this arm's,
would drive or report the wrong machine, so the client confirms the identity first.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from enum import Enum

from protocol import DeviceID, Packet, PacketID, ProtocolError, commands
from protocol.models import ArmModel
from reach_driver.errors import ArmModelError
from reach_driver.state import joint_name, packet_value


class ModelCheck(str, Enum):
    """What `ArmClient.start` makes of the arm's model."""

    #: Take the client's model as given and ask only its devices (the Python default).
    TRUST = "trust"
    #: Ask every known model's joints and jaws and adopt the model whose devices answer.
    DETECT = "detect"
    #: Ask them too; `ArmModelError` if the devices answering are another model's.
    CONFIRM = "confirm"


def devices_to_ask(first: Sequence[int], models: Iterable[ArmModel]) -> tuple[int, ...]:
    """`first` (the client's devices, asked as before), then every other joint and jaw of
    `models`: what discovery asks when the model is to be found. Not the devices that do not
    move (a router): the virtual Bravo's does not answer MODE, and each silent device costs
    discovery its retries (on a half-duplex line one after the other)."""
    out = [int(d) for d in first]
    for model in models:
        out += [int(d) for d in model.actuators if int(d) not in out]
    return tuple(out)


def model_answering(found: Collection[int], models: Iterable[ArmModel]) -> ArmModel | None:
    """The model the answering devices `found` are: one with every answering device among
    its own, the fewest of its joints and jaw silent, then the fewest devices (an Alpha 5's
    five answering are an Alpha 5, not a Bravo 7 missing two joints); None if no model owns
    every answering device."""
    answered = {int(d) for d in found}
    owners = [m for m in models if answered <= {int(d) for d in m.devices}]
    if not owners:
        return None
    return min(
        owners, key=lambda m: (len({int(d) for d in m.actuators} - answered), len(m.devices))
    )


def device_list(devices: Iterable[int]) -> str:
    """'A B C D E (0x01-0x05)' for messages: the devices by name, then their ids."""
    ids = sorted({int(d) for d in devices})
    if not ids:
        return "none"
    names = " ".join(_name(d) for d in ids)
    runs: list[list[int]] = []
    for d in ids:
        if runs and d == runs[-1][-1] + 1:
            runs[-1].append(d)
        else:
            runs.append([d])
    spans = ", ".join(
        f"0x{r[0]:02X}" if len(r) == 1 else f"0x{r[0]:02X}-0x{r[-1]:02X}" for r in runs
    )
    return f"{names} ({spans})"


def _name(device: int) -> str:
    try:
        return DeviceID(device).name
    except ValueError:
        return f"0x{device:02X}"


def model_mismatch(
    url: str, expected: ArmModel, found: Collection[int], models: Iterable[ArmModel]
) -> str | None:
    """Why the devices answering on `url` are not `expected` (None when they are)."""
    answered = {int(d) for d in found}
    actual = model_answering(answered, models)
    if actual is expected:
        return None
    silent = [d for d in expected.actuators if int(d) not in answered]
    what = f"a {actual.title}'s devices" if actual is not None else "no known arm's devices"
    return f"the arm on {url} is not a {expected.title}: {device_list(answered)} answer, {what}" + (
        f"; the {expected.title}'s {device_list(silent)} do not" if silent else ""
    )


def model_taken(
    check: ModelCheck,
    expected: ArmModel,
    found: Collection[int],
    models: Iterable[ArmModel],
    url: str,
) -> ArmModel:
    """The model `ArmClient.start` takes from the devices `found` answering on `url`: with
    DETECT the one they are, with CONFIRM `expected` if they are its; else `ArmModelError`
    (nothing but REQUESTs was sent)."""
    models = tuple(models)
    model = model_answering(found, models)
    if check is ModelCheck.CONFIRM:
        problem = model_mismatch(url, expected, found, models)
        if problem is not None:
            raise ArmModelError(
                f"{problem}; nothing was sent", None if model is None else model.name
            )
        return expected
    if model is None:
        raise ArmModelError(
            f"the devices answering on {url} are no known arm's: "
            f"{', '.join(joint_name(d) for d in found)}; nothing was sent"
        )
    return model


#: What identifies a device, and the JointState/DeviceIdentity field each fills.
IDENTITY_FIELDS: dict[int, str] = {
    PacketID.SERIAL_NUMBER: "serial_number",
    PacketID.MODEL_NUMBER: "model_number",
    PacketID.SOFTWARE_VERSION: "software_version",
}
IDENTITY_PACKETS: tuple[int, ...] = tuple(IDENTITY_FIELDS)


@dataclass(frozen=True)
class DeviceIdentity:
    """One device's identity; None for what it did not report at connect (not checked)."""

    serial_number: float | None = None
    model_number: float | None = None
    software_version: str | None = None

    @classmethod
    def from_replies(cls, replies: Mapping[int, Packet]) -> DeviceIdentity:
        values: dict[str, object] = {}
        for pid, name in IDENTITY_FIELDS.items():
            packet = replies.get(pid)
            if packet is not None:
                try:
                    values[name] = packet_value(packet)
                except ProtocolError:
                    pass
        return cls(**values)  # type: ignore[arg-type]

    def known(self) -> dict[str, object]:
        return {
            f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None
        }


def field_label(name: str) -> str:
    return name.replace("_", " ")


class IdentityCheck:
    """Collects a reopened link's identity replies (reader thread) and compares them."""

    def __init__(self, expected: Mapping[int, DeviceIdentity]) -> None:
        self.expected = dict(expected)
        self.wanted: set[tuple[int, int]] = {
            (dev, pid)
            for dev, ident in self.expected.items()
            for pid, name in IDENTITY_FIELDS.items()
            if getattr(ident, name) is not None
        }
        self.differences: list[str] = []

    def frames(self) -> list[bytes]:
        out = []
        for dev in sorted(self.expected, reverse=True):
            ids = [pid for pid in IDENTITY_PACKETS if (dev, pid) in self.wanted]
            if ids:
                out.append(commands.request(dev, ids).encode())
        return out

    @property
    def complete(self) -> bool:
        return not self.wanted

    def offer(self, packet: Packet) -> None:
        key = (int(packet.device_id), int(packet.packet_id))
        if key not in self.wanted:
            return
        self.wanted.discard(key)
        dev, pid = key
        name = IDENTITY_FIELDS[pid]
        was = getattr(self.expected[dev], name)
        try:
            now = packet_value(packet)
        except ProtocolError:
            now = f"malformed {packet.data.hex()}"
        if now != was:
            self.differences.append(
                f"{joint_name(dev)} {field_label(name)} {_show(now)} (was {_show(was)})"
            )


def _show(value: object) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)
