"""Which arm model a command is for, and the per-joint values the command line takes for it.

The model is `--arm`'s, else the one whose devices answer at connect
(`reach_driver.identity.model_answering`); until the port is open a command can only check
that what it was given fits some model (the one `--arm` names, else any known one), and
after it that it fits the arm that answered. Either way a bad count is one line naming the
joints in order, before anything is sent.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from protocol.models import ALPHA5, MODELS, ArmModel, model_named

#: Every model the CLI drives, the default (the Alpha 5) first.
KNOWN: tuple[ArmModel, ...] = (ALPHA5, *(m for m in MODELS.values() if m is not ALPHA5))

_WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine")


def count_word(n: int) -> str:
    return _WORDS[n] if 0 <= n < len(_WORDS) else str(n)


def given_model(args: argparse.Namespace) -> ArmModel | None:
    """The model `--arm` names (None: found at connect)."""
    name = getattr(args, "arm", None)
    return model_named(name) if name else None


def in_scope(args: argparse.Namespace) -> tuple[ArmModel, ...]:
    """The models a command may meet: `--arm`'s, else every known one."""
    given = given_model(args)
    return (given,) if given is not None else KNOWN


def _angles(model: ArmModel) -> str:
    return f"the {count_word(model.n_joints)} angles {' '.join(model.joint_letters)}"


def angles_problem(
    what: str, count: int, models: Sequence[ArmModel], *, jaw: bool = False, on: str = ""
) -> str | None:
    """Why `count` angles fit none of `models` (with `jaw`, one more value, the jaw's, may
    follow them), or None. `on`: where the arm answered, once it has ("the Reach Bravo 7
    on /tmp/bravo7")."""
    if any(count in (m.n_joints, m.n_joints + 1) if jaw else count == m.n_joints for m in models):
        return None
    first, rest = models[0], models[1:]
    text = f"{what} needs {_angles(first)} (rad)"
    if on:
        text += f" of {on}"
    text += f", got {count}"
    if rest:
        text += " (" + "; ".join(f"on a {m.title} {_angles(m)}" for m in rest) + ")"
    return text


def current_values(text: str | None) -> list[float]:
    """`--max-current`'s values (ValueError naming the option if one is not a number)."""
    if not text:
        return []
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--max-current takes mA values, got {text!r}") from None


def currents_problem(
    values: Sequence[float], models: Sequence[ArmModel], on: str = ""
) -> str | None:
    """Why `--max-current`'s values fit none of `models` (one positive value for every
    joint, or one per joint in order), or None. `on`: the arm that answered."""
    fits = len(values) == 1 or any(len(values) == m.n_joints for m in models)
    if fits and all(np.isfinite(v) and v > 0 for v in values):
        return None
    orders = " or ".join(
        f"{count_word(m.n_joints)} comma-separated ({','.join(m.joint_letters)}"
        + (")" if len(models) == 1 else f": a {m.title})")
        for m in models
    )
    where = f" for {on}" if on else ""
    given = ",".join(f"{v:g}" for v in values)
    return f"--max-current takes one positive value or {orders}{where}, got {given!r}"


def currents_by_device(values: Sequence[float], models: Sequence[ArmModel]) -> dict[int, float]:
    """`--max-current` by device: one value for every joint of every model in scope (the
    limits are looked up by device, so the joints of a model the arm is not cost nothing),
    else the model with that many joints in its order."""
    if not values:
        return {}
    if len(values) == 1:
        return {int(d): values[0] for m in models for d in m.joints}
    model = next(m for m in models if m.n_joints == len(values))
    return {int(d): v for d, v in zip(model.joints, values, strict=True)}


@dataclass(frozen=True)
class JointValues:
    """Angles as typed after `move`: in joint order (`values`, the jaw's mm may follow), or
    by letter (`named`: `G=1.2 A=5`, the jaw as A; joints not named keep their angle)."""

    values: tuple[float, ...] = ()
    named: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def parse(cls, tokens: Sequence[str]) -> JointValues:
        """ValueError naming the token that is neither a number nor LETTER=number, or a mix."""
        named: dict[str, float] = {}
        values: list[float] = []
        for token in tokens:
            letter, sep, number = token.partition("=")
            try:
                value = float(number if sep else token)
            except ValueError:
                raise ValueError(
                    f"{token!r} is neither an angle (rad) nor JOINT=ANGLE (e.g. G=1.5)"
                ) from None
            if not np.isfinite(value):
                raise ValueError(f"{token!r}: angles must be finite")
            if sep:
                key = letter.strip().upper()
                if key in named:
                    raise ValueError(f"joint {key} is named twice")
                named[key] = value
            else:
                values.append(value)
        if named and values:
            raise ValueError(
                "give every angle in joint order, or name each joint (G=1.5), not both"
            )
        return cls(tuple(values), named)

    def names_problem(self, models: Sequence[ArmModel], on: str = "") -> str | None:
        """Why a named joint is no joint (nor the jaw A) of any of `models`, or None."""
        for letter in self.named:
            if any(letter in (*m.joint_letters, m.jaw.name) for m in models):
                continue
            which = "; ".join(
                f"{m.title}: {' '.join(m.joint_letters)}, the jaw {m.jaw.name}" for m in models
            )
            where = f" of {on}" if on else ""
            return f"no joint {letter}{where} ({which})"
        return None

    def target(
        self, model: ArmModel, present: np.ndarray, jaw: float | None
    ) -> tuple[np.ndarray, float | None]:
        """The joint target in `model`'s order and the jaw's (mm, or None): named joints
        set, the others at `present`; the jaw from the values, the names or `jaw`."""
        if self.named:
            q = np.array(present, dtype=float)
            for letter, value in self.named.items():
                if letter == model.jaw.name:
                    jaw = value
                else:
                    q[model.joint_letters.index(letter)] = value
            return q, jaw
        q = np.array(self.values[: model.n_joints], dtype=float)
        if len(self.values) > model.n_joints:
            jaw = self.values[-1]
        return q, jaw

    def gives_jaw(self, model: ArmModel) -> bool:
        return model.jaw.name in self.named or len(self.values) == model.n_joints + 1
